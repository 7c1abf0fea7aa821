"""The guided calibration's command: `ftsensord guide` (a person, masses and a printed fixture
instead of a robot; docs/guide/guided-calibration.md)."""

from __future__ import annotations

import argparse
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from ftsensord.errors import ConfigError

if TYPE_CHECKING:
    from ftsensord.chip.i2c import Bus
    from ftsensord.chip.mpu6050 import MPU6050

T = TypeVar("T")


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "guide",
        help="calibrate without a robot: a guided procedure with masses and a printed fixture",
        description="Tell the user what to do at each step (a face of the printed holder down, a mass on a "
        "hook), wait for the silicone to settle, record, check the pose against the plan (a wrong face, "
        "hook or mass, a bump: named and asked again), keep the poses as they come (a stopped run "
        "resumes), then fit as `ftsensord calibrate` does and report the accuracy on held-out poses. "
        "With --fixture alone: write the fixture's OpenSCAD file and print the plan.",
    )
    p.add_argument(
        "-o", "--output", help="calibration file to write (JSON); the run's progress is kept beside it"
    )
    p.add_argument("--fixture", help="write the fixture's OpenSCAD file here")
    p.add_argument("--scene", help="run on the simulator: a scene file (its [person] follows the prompts)")
    p.add_argument("--sim", action="store_true", help="run on the simulator's default scene")
    p.add_argument("--bus", help="a real bus (/dev/i2c-N): the user does each step and presses a key")
    p.add_argument("--addresses", help="the sensor's 8 chip addresses on --bus, e.g. 0x0C,0x0D,...")
    p.add_argument(
        "--imu",
        help="an MPU-6050 on the bus, fixed to the holder: its address (0x68 or 0x69); "
        "default: looked for at both (on the simulator: the scene's sensor's imu)",
    )
    p.add_argument(
        "--no-imu", action="store_true", help="trust each face for gravity, even with an IMU present"
    )
    p.add_argument("--sensor", default="sensor1", help="which sensor of the scene (default: sensor1)")
    p.add_argument(
        "--yes", action="store_true", help="confirm each step without a key (scripts, the simulator)"
    )
    p.add_argument(
        "--quick", action="store_true", help="a short plan (a quarter of the fit steps): for a try"
    )
    p.add_argument("--samples", type=int, default=100, help="readings averaged per pose (default: 100)")
    p.add_argument(
        "--arm-g", type=float, default=22.0, help="the hook arm's mass as weighed, g (default: 22)"
    )
    p.add_argument("--seed", type=int, default=0, help="the simulated chips' noise seed (default: 0)")
    p.add_argument("--stop-after", type=int, help="stop after this many poses recorded (the run resumes)")
    p.add_argument("--restart", action="store_true", help="discard a stopped run's poses and start afresh")
    p.add_argument("--linear-only", action="store_true", help="skip the nonlinear estimator's calibration")
    p.set_defaults(func=cmd_guide)


class TerminalPrompter:
    """Lines on stdout; each step confirmed by a key, or by --yes. In a terminal one key does
    it (Enter or space: record; q or s: stop; Ctrl-C: stop), without Enter; from a pipe a line
    is read (empty: record; q or s: stop; end of input: stop)."""

    def __init__(self, yes: bool):
        self.yes = yes

    def say(self, line: str) -> None:
        print(line, flush=True)

    def confirm(self, line: str) -> None:
        from ftsensord.calibration.guided import Stop

        if self.yes:
            return
        try:
            if sys.stdin.isatty():
                answer = self._key()
            else:
                answer = input("  done? Enter to record, q to stop: ").strip().lower()
        except (EOFError, KeyboardInterrupt):
            print(flush=True)
            raise Stop from None
        if answer in ("s", "q", "stop", "quit"):
            raise Stop

    @staticmethod
    def _key() -> str:
        """One key, read without Enter (the terminal in cbreak mode: Ctrl-C still interrupts)."""
        import termios
        import tty

        fd = sys.stdin.fileno()
        saved = termios.tcgetattr(fd)
        try:
            # At once, not flushing: a key typed early is kept. The prompt after it: a key
            # typed once the prompt shows is read as a key, not held for a line.
            tty.setcbreak(fd, termios.TCSANOW)
            print("  done? Enter to record, q to stop: ", end="", flush=True)
            while True:
                key = os.read(fd, 1).decode(errors="replace").lower()
                if not key:
                    raise EOFError
                if key in ("\r", "\n", " "):
                    print(flush=True)
                    return ""
                if key in ("q", "s"):
                    print(key, flush=True)
                    return key
        finally:
            termios.tcsetattr(fd, termios.TCSADRAIN, saved)


def saving_whole(save: Callable[[T], None]) -> Callable[[T], None]:
    """``save`` with Ctrl-C held off while it writes: the dataset and the progress file are
    written one after the other, and a stop between them would leave a run that cannot resume."""

    def whole(run: T) -> None:
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            save(run)
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})

    return whole


class NoStation:
    """A real sensor: the user has done the step when they confirm it."""

    def perform(self, *args: object) -> None:
        return None


def _imu(bus: Bus, given: str | None, scene_address: int | None) -> MPU6050 | None:
    """The IMU to read each pose's gravity with: at ``given`` (an address), else the scene's,
    else the first MPU-6050 that answers at 0x68 or 0x69; None when there is none."""
    from ftsensord.chip import mpu6050

    if given is not None:
        try:
            address: int | None = int(given, 0)
        except ValueError as exc:
            raise ConfigError(f"--imu: expected 0x68 or 0x69, got {given!r}") from exc
        if address not in mpu6050.ADDRESSES:
            raise ConfigError(f"--imu: expected 0x68 or 0x69 (an MPU-6050's, AD0 low or high), got {given!r}")
    else:
        address = scene_address if scene_address is not None else mpu6050.probe(bus)
    if address is None:
        print("no IMU found (an MPU-6050 at 0x68 or 0x69): each pose's gravity is taken from its face")
        return None
    imu = mpu6050.MPU6050(bus, address)
    imu.start()
    print(
        f"IMU: an MPU-6050 at 0x{address:02X} reads each pose's gravity (its map fitted on the no-load faces)"
    )
    return imu


def cmd_guide(args: argparse.Namespace) -> int:
    from ftsensord.calibration import fixture as fx
    from ftsensord.calibration import guided
    from ftsensord.calibration.procedure import calibrate, summary
    from ftsensord.calibration.report import PAPER_TABLE_II, format_rmse
    from ftsensord.model.viscoelastic import Relaxation
    from ftsensord.sim.memory import DEFAULT_RELAXATION

    fixture = fx.Fixture(arm_g=args.arm_g)
    steps = fx.guided_plan(
        fixture,
        every=2 if args.quick else 1,
        no_load=8 if args.quick else 12,
        validation=6 if args.quick else 12,
    )
    if args.fixture:
        Path(args.fixture).write_text(fx.openscad(fixture))
        print(
            f"wrote {args.fixture}: the holder ({len(fixture.normals)} faces at {fixture.face_mm:g} mm) "
            "and the hook arm"
        )
    if args.output is None:
        if args.fixture:
            series = Relaxation.from_pairs([list(p) for p in DEFAULT_RELAXATION])
            print(
                f"plan: {len(steps)} steps ({sum(s.split == 'no-load' for s in steps)} no-load first), about "
                f"{fx.person_time_s(steps, series) / 60:.0f} min for a person (the default silicone series' wait)"
            )
            for k, s in enumerate(steps):
                print(f"  step {k + 1}: {s.instruction()}")
            return 0
        raise ConfigError("guide: -o/--output (the calibration file to write) is needed, or --fixture alone")
    if args.samples < 2:
        raise ConfigError(
            f"--samples: expected 2 or more readings per pose (a bump is told by their scatter), got {args.samples}"
        )
    relaxation = None
    if args.bus:
        if args.scene or args.sim:
            raise ConfigError("--bus and --scene/--sim: one or the other")
        if not args.addresses:
            raise ConfigError("--bus: --addresses (the sensor's 8 chips) is needed")
        from ftsensord.acquire.bus import open_bus

        try:
            addresses = tuple(int(a, 0) for a in args.addresses.split(","))
        except ValueError as exc:
            raise ConfigError(
                f"--addresses: expected addresses such as 0x0C,0x0D, got {args.addresses!r}"
            ) from exc
        bus = open_bus(args.bus, exclusive=True)
        station: guided.Station = NoStation()
        relaxation = Relaxation.from_pairs(
            [list(p) for p in DEFAULT_RELAXATION]
        )  # not known: the generous default
        serial, source = "", f"guided: bus {args.bus}"
        imu_address = None
    else:
        from ftsensord.sim import PhysicalScene, default_scene, load_scene, simulated_bus
        from ftsensord.sim.person import Person

        scene = load_scene(args.scene) if args.scene else default_scene()
        if not isinstance(scene, PhysicalScene):
            raise ConfigError(f'{args.scene}: the guided calibration needs a scene of kind "sensors"')
        names = [s.name for s in scene.sensors]
        if args.sensor not in names:
            raise ConfigError(f"--sensor {args.sensor!r}: the scene's sensors are {', '.join(names)}")
        sensor = next(s for s in scene.sensors if s.name == args.sensor)
        addresses = sensor.addresses
        bus = simulated_bus(scene, seed=args.seed)
        station = guided.SimStation(scene, sensor.name, fixture, scene.person or Person())
        relaxation = sensor.relaxation
        imu_address = sensor.imu_address
        serial = f"sim-{sensor.name}"
        source = f"guided, simulated: scene {args.scene or 'default'}, sensor {sensor.name}, seed {args.seed}"
    imu = None if args.no_imu else _imu(bus, args.imu, imu_address)
    settle = fx.step_settle_s(relaxation)
    out = Path(args.output)
    progress, partial = out.with_name(out.name + ".progress.json"), out.with_name(out.name + ".poses.json")
    if progress.exists() and not args.restart:
        run = guided.load_run(steps, progress, partial)
        print(f"resuming: {len(run.kept)} of {len(steps)} steps kept ({progress})")
    else:
        run = guided.GuideRun(steps)
        minutes = (
            fx.person_time_s(
                steps,
                relaxation
                if relaxation is not None
                else Relaxation.from_pairs([list(p) for p in DEFAULT_RELAXATION]),
            )
            / 60
        )
        print(
            f"plan: {len(steps)} steps ({sum(s.split == 'no-load' for s in steps)} no-load first, then the hook "
            f"arm on), about {minutes:.0f} min for a person"
        )
    prompter = TerminalPrompter(args.yes)
    try:
        done = guided.guide(
            run,
            bus=bus,
            addresses=addresses,
            fixture=fixture,
            station=station,
            prompter=prompter,
            samples=args.samples,
            settle_s=settle,
            save=saving_whole(lambda r: guided.save_run(r, progress, partial, serial, source)),
            stop_after=args.stop_after,
            imu=imu,
        )
    except (guided.Stop, KeyboardInterrupt):  # Ctrl-C while a pose is read: that pose is dropped
        done = False
    if not done:
        print(
            f"stopped: {len(run.kept)} of {len(steps)} steps kept in {partial}; run the same command to resume"
        )
        return 3
    dataset = run.dataset(serial, source)
    dataset.save(partial)
    cal, _ = calibrate(dataset, nonlinear=not args.linear_only)
    slips = getattr(station, "slips", None)
    cal.report["guided"] = {
        "steps": len(steps),
        "poses_refused": len(run.refused),
        "refused": run.refused,
        "settle_s": settle,
        "person_time_s": fx.person_time_s(steps, relaxation) + len(run.refused) * (fx.HANDLING_S + settle),
        **(
            {"person_slips": [f"step {k + 1}, try {a + 1}: {s}" for k, a, s in slips]}
            if slips is not None
            else {}
        ),
    }
    cal.save(out)
    print(summary(cal))
    rmse = cal.report["validation_rmse"]
    if rmse:
        within = [a for a, v, t in zip(rmse, rmse.values(), PAPER_TABLE_II) if v <= t]
        print(
            f"expected accuracy (held-out 100 g poses): {format_rmse(rmse)}; within the paper's Table II on "
            f"{len(within)} of 6 axes"
        )
    print(f"{len(run.refused)} poses refused and done again" + "".join(f"\n  {r}" for r in run.refused))
    print(f"wrote {out}")
    return 0
