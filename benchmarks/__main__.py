"""The benchmarks' own command line.

    python -m benchmarks regenerate                       # every page of docs/results/ (an hour or more)
    python -m benchmarks regenerate --only tradeoff creep # some of them
    python -m benchmarks regenerate --quick --out /tmp/r  # short runs, for CI: the pages' structure
    python -m benchmarks list                             # the pages and what makes each

A full run measures one page after another (the rate and CPU figures of some pages would
suffer from a neighbour); ``--quick`` runs ``--jobs`` of them at once and needs ``--out``, so
that it never overwrites the figures in docs/results/.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from benchmarks.common import RESULTS, ROOT, machine


@dataclass(frozen=True)
class Generator:
    """A benchmark that writes pages of docs/results/: its name, the files it writes, and
    what it runs (the output folder and the quick flag in, the commands run out)."""

    name: str
    pages: tuple[str, ...]
    run: Callable[[Path, bool], list[str]]
    about: str


def _python(*args: str) -> list[str]:
    return [sys.executable, *args]


def _run(cmd: list[str], *, cwd: Path = ROOT, env: dict[str, str] | None = None) -> str:
    """``cmd`` from ``cwd``; its output, or SystemExit with its last lines when it fails."""
    done = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(
            f"{' '.join(cmd)} failed ({done.returncode}):\n{(done.stdout + done.stderr)[-3000:]}"
        )
    return done.stdout


def _module(
    module: str, page: str | None = None, has_quick: bool = True
) -> Callable[[Path, bool], list[str]]:
    """`python -m benchmarks.<module> [--quick] --out OUT` (OUT/<page> where the script's
    --out names a file, not a folder; ``has_quick``: the script has a quick mode)."""

    def run(out: Path, quick: bool) -> list[str]:
        cmd = _python(
            "-m",
            f"benchmarks.{module}",
            *(["--quick"] if quick and has_quick else []),
            "--out",
            str(out / page if page else out),
        )
        _run(cmd)
        return [" ".join(cmd)]

    return run


def _calibration_report(out: Path, quick: bool) -> list[str]:
    """The packaged calibration's report, made as ftsensord/data/README.md says (the dataset
    of the default scene's sensor1, seed 1) from a scratch copy of the repository's paths, so
    that the report names the command a user reads and the packaged file stays as it is."""
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        (work / "ftsensord" / "data").mkdir(parents=True)
        (work / "docs" / "results").mkdir(parents=True)
        small = ["--poses", "40", "--validation-poses", "6", "--samples", "10"] if quick else []
        # -P: the scratch folder's ftsensord/ is not the package
        dataset = _python(
            "-P", "-m", "ftsensord", "dataset", "-o", "s1.json", "--sensor", "sensor1", "--seed", "1", *small
        )
        calibrate = _python(
            "-P",
            "-m",
            "ftsensord",
            "calibrate",
            "s1.json",
            "-o",
            "ftsensord/data/sim-sensor1.json",
            "--serial",
            "sim-sensor1",
            "--frame",
            "sensor1",
            "--report",
            "docs/results/calibration-report.md",
            *(["--allow-poor-fit"] if quick else []),
        )
        _run(dataset, cwd=work)
        _run(calibrate, cwd=work)
        for name in ("calibration-report.md", "calibration-report.png"):
            shutil.copyfile(work / "docs" / "results" / name, out / name)
    return [" ".join(["ftsensord", *dataset[4:]]), " ".join(["ftsensord", *calibrate[4:]])]


def _plot(out: Path, quick: bool) -> list[str]:
    """`ftsensord plot` of a running daemon's wrench/sensor1 and wrench/tip, as docs/guide/clients.md
    shows it: the default configuration (simulated bus, default scene, at rest, not tared)."""
    from ftsensord.testing.harness import packaged_config, start_daemon, stop

    seconds = "1" if quick else "3"
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        proc, notify = start_daemon(packaged_config(folder / "ftsensord.toml"), folder)
        try:
            env = {**os.environ, "XDG_RUNTIME_DIR": str(folder)}
            env.pop("RUNTIME_DIRECTORY", None)
            cmd = _python(
                "-m",
                "ftsensord",
                "plot",
                "wrench/sensor1",
                "wrench/tip",
                "--seconds",
                seconds,
                "--png",
                str(out / "plot.png"),
            )
            _run(cmd, env=env)
        finally:
            stop(proc, notify)
    return [" ".join(["ftsensord", *cmd[3:]])]


GENERATORS = (
    Generator(
        "accuracy",
        ("accuracy-figures.md",),
        _module("accuracy.accuracy", "accuracy-figures.md"),
        "the estimators on as-built sensors in the Earth's field",
    ),
    Generator(
        "coverage",
        ("coverage.md",),
        _module("accuracy.coverage", "coverage.md"),
        "each sample's sigma against the truth: coverage at 1 and 2 sigma, per estimator, filter and chips",
    ),
    Generator(
        "axis_gain",
        ("axis-gain.md",),
        _module("accuracy.axis_gain", "axis-gain.md"),
        "a load along one axis alone: the static gain per axis and estimator",
    ),
    Generator(
        "sigma_cost",
        ("sigma-cost.md",),
        _module("performance.sigma_cost", "sigma-cost.md"),
        "what each sample's sigma costs the pipeline's step, per estimator",
    ),
    Generator(
        "motor",
        ("motor-figures.md",),
        _module("accuracy.motor", "motor-figures.md"),
        "a motor's field a few cm from the tool, per stray-field model",
    ),
    Generator(
        "tradeoff",
        ("tradeoff.md", "tradeoff.png"),
        _module("accuracy.tradeoff"),
        "speed against accuracy: chip settings, averaging, schedulers, estimators",
    ),
    Generator(
        "creep",
        ("silicone-figures.md", "silicone.png"),
        _module("accuracy.creep"),
        "the silicone's memory, identified and compensated, through the daemon",
    ),
    Generator(
        "creep_trade",
        ("tradeoff-dynamic.md", "tradeoff-dynamic.png"),
        _module("accuracy.creep_trade"),
        "the trade under moving loads on a silicone that relaxes",
    ),
    Generator(
        "field_models",
        ("field-model.png",),
        _module("accuracy.field_models", has_quick=False),
        "the point dipole against the exact cylinder magnet",
    ),
    Generator(
        "calibration_report",
        ("calibration-report.md", "calibration-report.png"),
        _calibration_report,
        "the packaged calibration's report (ftsensord dataset and calibrate)",
    ),
    Generator("plot", ("plot.png",), _plot, "a headless `ftsensord plot` of the running daemon"),
)


#: The first words of the line `stamp` writes last on a generated page.
STAMP = "Generated on "


def stamp(page: Path, name: str, seconds: float, quick: bool) -> None:
    """Ends a generated page with when, by what command and on what host it was made, in
    one line (`STAMP`), replacing the one a former run left: each page says its own date and
    machine, written by one rule whatever the benchmark."""
    lines = [line for line in page.read_text().rstrip("\n").split("\n") if not line.startswith(STAMP)]
    while lines and not lines[-1]:
        lines.pop()
    load = os.getloadavg()[0]
    mode = " --quick" if quick else ""
    lines += [
        "",
        f"{STAMP}{time.strftime('%Y-%m-%d', time.gmtime())} by `python -m benchmarks regenerate{mode} "
        f"--only {name}` in {seconds:.0f} s on a {machine()} host (1-min load {load:.2f} at the end).",
    ]
    page.write_text("\n".join(lines) + "\n")


def regenerate(out: Path, quick: bool, only: list[str] | None = None, jobs: int = 1) -> dict[str, float]:
    """Runs the generators (``only``: these by name), writing into ``out``; each one's
    wall time (s). ``jobs`` at once (1: one after another)."""
    chosen = [g for g in GENERATORS if only is None or g.name in only]
    out.mkdir(parents=True, exist_ok=True)

    def one(g: Generator) -> tuple[str, float]:
        began = time.monotonic()
        for cmd in g.run(out, quick):
            print(f"{g.name}: {cmd}", flush=True)
        missing = [p for p in g.pages if not (out / p).is_file() or (out / p).stat().st_size == 0]
        if missing:
            raise SystemExit(f"{g.name} wrote no {', '.join(missing)} in {out}")
        seconds = time.monotonic() - began
        for page in g.pages:
            if page.endswith(".md"):
                stamp(out / page, g.name, seconds, quick)
        return g.name, seconds

    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:  # each generator is a process of its own
        return dict(pool.map(one, chosen))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    regen = sub.add_parser("regenerate", help="write the generated pages (docs/results/ by default)")
    regen.add_argument(
        "--quick",
        action="store_true",
        help="short runs (the pages' structure, not their figures); needs --out",
    )
    regen.add_argument("--out", type=Path, help="folder to write into (default: docs/results/)")
    regen.add_argument(
        "--only", nargs="+", choices=[g.name for g in GENERATORS], help="these generators alone"
    )
    regen.add_argument(
        "--jobs",
        type=int,
        default=None,
        help="generators run at once (default: 1, --quick: the cores this process may use)",
    )
    sub.add_parser("list", help="the generated pages and what makes each")
    args = parser.parse_args(argv)
    if args.command == "list":
        for g in GENERATORS:
            print(f"{g.name:20s} {', '.join(g.pages):45s} {g.about}")
        return 0
    if args.quick and args.out is None:
        parser.error("--quick needs --out: its pages are not the figures of docs/results/")
    jobs = args.jobs or (len(os.sched_getaffinity(0)) if args.quick else 1)
    times = regenerate(args.out or RESULTS, args.quick, args.only, jobs)
    for name, seconds in times.items():
        print(f"{name:20s} {seconds:7.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
