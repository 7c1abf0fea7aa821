"""`ftsensord plot`: the figure's panels, units and traces, from made-up samples and
from the running daemon (headless snapshot, as `--png` writes it)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from ftsensord.plot import FLAG_BITS, History, draw, make_figure, snapshot
from ftsensord.protocol import wire

from .test_record import daemon  # noqa: F401  (the module's running daemon)


def sample(topic: str, seq: int, t: float, flags: int = 0, values: list[float] | None = None) -> wire.Sample:
    kind = wire.KIND_WRENCH if topic.startswith("wrench/") else wire.KIND_FLUX
    v = np.array(values if values is not None else [seq * 0.1, -seq * 0.1, 1.0, 0.01, 0.0, -0.01])
    return wire.Sample(topic, kind, seq, t, 1.7e9 + t, flags, v)


def test_wrench_panels_units_and_traces():
    h = History(window_s=2.0)
    for i in range(300):  # 128 Hz (times exact in binary), 2.3 s: the first 42 fall out of the window
        h.add(
            sample("wrench/sensor1", i + (i >= 150), i / 128, flags=wire.FLAG_SATURATED if i % 50 == 0 else 0)
        )
    fig, plots = make_figure(["wrench/sensor1"], {"wrench/sensor1": wire.KIND_WRENCH})
    draw(plots, {"wrench/sensor1": h})
    force, moment, flags = fig.axes
    assert force.get_ylabel() == "force (N)" and moment.get_ylabel() == "moment (Nm)"
    assert flags.get_ylabel() == "flags" and flags.get_xlabel().startswith("time (s)")
    assert [ln.get_label() for ln in force.lines] == ["fx", "fy", "fz"]
    assert [ln.get_label() for ln in moment.lines] == ["mx", "my", "mz"]
    assert len(flags.lines) == len(FLAG_BITS) and [t.get_text() for t in flags.get_yticklabels()] == [
        wire.FLAG_NAMES[b] for b in FLAG_BITS
    ]
    x, y = force.lines[0].get_data()
    assert len(x) == 257 and x[-1] == 0 and x[0] == -2.0  # the window's samples (i 43-299), 0 the newest
    np.testing.assert_allclose(y, [(i + (i >= 150)) * 0.1 for i in range(43, 300)])
    assert force.get_xlim() == (-2.0, 0.0) and force.get_ylim()[1] >= y.max()
    row = FLAG_BITS.index(wire.FLAG_SATURATED)
    marks = flags.lines[row].get_data()[1]
    assert np.sum(np.isfinite(marks)) == 5 and np.all(
        marks[np.isfinite(marks)] == row
    )  # i = 50, 100, 150, 200, 250
    assert all(np.all(np.isnan(ln.get_data()[1])) for i, ln in enumerate(flags.lines) if i != row)
    assert "1 missed" in force.get_title()


def test_flux_panels_in_millitesla_per_chip():
    h = History(window_s=1.0)
    b = np.tile([0.0, 3e-3, 4e-3], 8)  # |B| 5 mT, B_z 4 mT at each chip
    for i in range(50):
        h.add(sample("flux/sensor1", i, i * 0.01, values=b.tolist()))
    fig, plots = make_figure(["flux/sensor1"], {"flux/sensor1": wire.KIND_FLUX})
    draw(plots, {"flux/sensor1": h})
    norm, bz, _ = fig.axes
    assert "mT" in norm.get_ylabel() and "mT" in bz.get_ylabel()
    assert len(norm.lines) == len(bz.lines) == 8
    np.testing.assert_allclose(norm.lines[3].get_data()[1], 5.0)
    np.testing.assert_allclose(bz.lines[3].get_data()[1], 4.0)


def test_snapshot_of_the_running_daemon(daemon, tmp_path):  # noqa: F811
    pub, _ = daemon
    png = tmp_path / "plot.png"
    shot = snapshot(["wrench/sensor1", "wrench/tip"], 1.5, png, endpoint=pub)
    assert len(shot.figure.axes) == 6
    newest = max(max(h.t) for h in shot.histories.values())  # x = 0: the newest sample of any stream
    for column, stream in enumerate(["wrench/sensor1", "wrench/tip"]):
        h = shot.histories[stream]
        assert h.samples > 50  # 1.5 s of a 100 Hz stream, with room for a loaded machine
        force = shot.figure.axes[3 * column]
        assert force.get_title().startswith(f"{stream}: {h.samples} samples")
        _, values, _ = h.arrays(newest)
        for line, column_values in zip(force.lines, values.T[:3]):
            np.testing.assert_array_equal(line.get_data()[1], column_values)
    fx = shot.figure.axes[0].lines[0].get_data()[1]  # the test scene loads sensor1: fx = 1 N (LOAD)
    assert 0.7 < np.mean(fx) < 1.3
    import matplotlib.image

    picture = matplotlib.image.imread(png)
    w, h_ = shot.figure.get_size_inches() * 100
    assert picture.shape[:2] == (round(h_), round(w)) and picture[..., :3].std() > 0.05  # drawn, not blank


def test_plot_cli_writes_a_png(daemon, tmp_path):  # noqa: F811
    pub, _ = daemon
    png = tmp_path / "cli.png"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "ftsensord",
            "plot",
            "wrench/sensor1",
            "--endpoint",
            pub,
            "--seconds",
            "1",
            "--png",
            str(png),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0 and done.stdout.startswith(f"wrote {png}: wrench/sensor1 "), done.stderr
    assert png.stat().st_size > 10_000


def _plot(tmp_path, *args: str, blocked_matplotlib: bool = False) -> subprocess.CompletedProcess:
    """`ftsensord plot` as a user on ssh runs it: no display, no daemon (nothing to wait for)."""
    env = {
        k: v
        for k, v in __import__("os").environ.items()
        if k not in ("DISPLAY", "WAYLAND_DISPLAY", "MPLBACKEND")
    }
    if blocked_matplotlib:  # an install without the 'plot' extra
        (tmp_path / "matplotlib").mkdir()
        (tmp_path / "matplotlib" / "__init__.py").write_text("raise ImportError('no matplotlib here')\n")
        env["PYTHONPATH"] = str(tmp_path)
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "ftsensord",
            "plot",
            "wrench/sensor1",
            "--endpoint",
            f"ipc://{tmp_path}/nobody",
            "--timeout",
            "1",
            *args,
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )


def test_a_live_plot_without_a_display_fails_naming_the_snapshot(tmp_path):
    """Over ssh matplotlib falls back to Agg, which opens no window: the command says so
    and gives the one that works, instead of exiting 0 after a warning."""
    out = _plot(tmp_path)
    assert out.returncode == 2, (out.returncode, out.stderr)
    assert "no display" in out.stderr and "--png" in out.stderr, out.stderr


def test_plot_without_matplotlib_names_the_extra_before_collecting(tmp_path):
    out = _plot(tmp_path, "--png", str(tmp_path / "p.png"), blocked_matplotlib=True)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert "pip install 'ftsensord[plot]'" in out.stderr, out.stderr
