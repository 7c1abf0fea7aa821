"""What heat costs the emulator: CPU per conversion of an emulated MLX90393, with and without
a temperature profile.

Three scenes of the same two as-built sensors at rest (the default scene's room and parts):
``static``, the default scene as it is (25 degC, no profile); ``held``, each sensor with a
recorded profile that stays at 25 degC (the scene knows it is held and skips every law);
``warming``, config/scene-warm.toml between 20 s and 140 s, where magnets, silicone and each
chip's sensitivity and offset follow the temperature. Each round runs every chip's conversion
(`EmulatedMLX90393._convert`, what a RM costs the simulator beyond the wire) for ``--cycles``
cycles 10 ms apart; the scenes take turns round by round (``--rounds``), so a busy host slows
all alike, and the medians of the rounds are reported, in us per conversion.

    python -m benchmarks.performance.emulator_heat            # the docs' figures (a few seconds)
    python -m benchmarks.performance.emulator_heat --json     # one JSON object
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from benchmarks.common import ROOT
from ftsensord.chip import mlx90393 as mlx
from ftsensord.sim import NOISELESS, VirtualClock, load_scene, simulated_bus
from ftsensord.sim.scene import default_scene_path

CONFIG = ROOT / "config"
HELD = '[sensor.temperature]\nkind = "recorded"\ntimes_s = [0.0, 60.0]\ncelsius = [25.0, 25.0]\n'


def chips(path: Path) -> list:
    """The emulated chips of the scene at ``path``, configured at the paper's settings."""
    bus = simulated_bus(load_scene(path), clock=VirtualClock(), noise=NOISELESS)
    for chip in bus.chips.values():
        for reg, value in mlx.Settings().to_registers().items():
            chip.registers[reg] = value
    return list(bus.chips.values())


def round_us(emulated: list, start_s: float, cycles: int) -> float:
    """Mean CPU (us) of one conversion over ``cycles`` cycles of every chip from ``start_s``."""
    begin = time.process_time_ns()
    for k in range(cycles):
        t = start_s + k * 0.01
        for chip in emulated:
            chip._convert(t)
    return (time.process_time_ns() - begin) / 1e3 / (cycles * len(emulated))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=500, help="cycles of 16 conversions a round")
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        held = Path(folder) / "held.toml"
        held.write_text(
            default_scene_path()
            .read_text()
            .replace("seed = 1", "seed = 1\n" + HELD, 1)
            .replace("seed = 2", "seed = 2\n" + HELD, 1)
        )
        scenes = {
            "static": (chips(default_scene_path()), 0.0),
            "held": (chips(held), 0.0),
            "warming": (chips(CONFIG / "scene-warm.toml"), 20.0),
        }
        times: dict[str, list[float]] = {name: [] for name in scenes}
        for _ in range(args.rounds):
            for name, (emulated, start) in scenes.items():
                times[name].append(round_us(emulated, start, args.cycles))
    n = args.cycles * 16
    result = {
        name: {"median_us": round(statistics.median(v), 2), "min_us": round(min(v), 2)}
        for name, v in times.items()
    }
    result["samples"] = {"rounds": args.rounds, "conversions_per_round": n}
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"{args.rounds} rounds of {n} conversions each (16 chips x {args.cycles} cycles, 10 ms apart)")
    for name in scenes:
        print(
            f"  {name:8s} median {result[name]['median_us']:6.2f} us a conversion (min {result[name]['min_us']:.2f})"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
