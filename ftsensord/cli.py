"""The ``ftsensord`` command line.

``main(argv) -> int`` is what the console script runs and what tests call.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

import numpy as np

from . import __version__
from .acquire.bus import ACCEPTED_FORMS, open_bus
from .acquire.scan import ChipReport, scan
from .chip import mlx90393 as mlx
from .errors import ConfigError, DaemonNotAnswering, FtsensordError
from .service.config import ESTIMATORS
from .sim.loads import PLANS


def _format_table(reports: list[ChipReport], spec: str) -> str:
    nan3 = [float("nan")] * 3
    lines = [f"{'addr':<5} {'part':<20} {'CONF1':<6} {'CONF2':<6} {'CONF3':<6} "
             f"{'Bx/uT':>9} {'By/uT':>9} {'Bz/uT':>9} {'T/degC':>7}  notes"]
    for r in reports:
        regs = [f"0x{r.registers[i]:04X}" if i in r.registers else "-" for i in range(3)]
        m = r.measurement
        field = nan3 if m is None else [float(v) * 1e6 for v in m.field_t]
        temp = float("nan") if m is None or m.temperature_c is None else m.temperature_c
        notes = []
        if len(r.registers) == 3:
            s = mlx.Settings.from_registers(r.registers)
            notes.append(f"found GAIN_SEL={s.gain_sel} RES={s.res_x}{s.res_y}{s.res_z} "
                         f"OSR={s.osr} DIG_FILT={s.dig_filt}")
        if m is not None and m.any_saturated:
            notes.append("SATURATED " + "".join(a for a, sat in zip("XYZ", m.saturated) if sat))
        if r.error:
            notes.append(f"ERROR: {r.error}")
        lines.append(f"0x{r.address:02X}  {r.part:<20} {regs[0]:<6} {regs[1]:<6} {regs[2]:<6} "
                     f"{field[0]:>9.1f} {field[1]:>9.1f} {field[2]:>9.1f} {temp:>7.2f}  "
                     + "; ".join(notes))
    lines.append(f"{len(reports)} chip(s) found on {spec}")
    return "\n".join(lines)


def cmd_scan(args: argparse.Namespace) -> int:
    bus = open_bus(args.bus)
    try:
        reports = scan(bus)
    finally:
        bus.close()
    if args.json:
        print(json.dumps({"bus": args.bus, "chips": [r.as_dict() for r in reports]}, indent=2))
    else:
        print(_format_table(reports, args.bus))
    if not reports:
        print(f"no MLX90393 answered on {args.bus} (0x0C-0x1B)", file=sys.stderr)
        return 1
    return 2 if any(r.error for r in reports) else 0


def cmd_dataset(args: argparse.Namespace) -> int:
    from .calibration.rig import record_dataset, simulate_sweeps
    from .model.geometry import SensorGeometry
    from .sim import PhysicalScene, default_scene, load_scene, simulated_bus
    from .sim.loads import StaticLoad, paper_plan

    scene = load_scene(args.scene) if args.scene else default_scene()
    if not isinstance(scene, PhysicalScene):
        raise ConfigError(f"{args.scene}: a calibration dataset needs a scene of kind \"sensors\"")
    names = [s.name for s in scene.sensors]
    if args.sensor not in names:
        raise ConfigError(f"--sensor {args.sensor!r}: the scene's sensors are {', '.join(names)}")
    sensor = next(s for s in scene.sensors if s.name == args.sensor)
    bus = simulated_bus(scene, seed=args.seed)
    plan = paper_plan(args.plan, n_fit=args.poses, n_validation=args.validation_poses)
    dataset = record_dataset(bus, sensor.addresses, plan, lambda w: scene.set_load(sensor.name, StaticLoad(w)),
                             samples=args.samples, serial=f"sim-{sensor.name}",
                             source=f"simulated: scene {args.scene or 'default'}, sensor {sensor.name}, "
                                    f"plan {args.plan}, seed {args.seed}")
    if not args.no_sweep:
        dataset.sweeps = simulate_sweeps(sensor.addresses, SensorGeometry.ring(), field_model=scene.field_model,
                                         samples=args.samples, rng=np.random.default_rng(args.seed))
    dataset.save(args.output)
    print(f"wrote {args.output}: {len(dataset)} poses ({args.plan}), {args.samples} samples each, "
          f"{int(dataset.saturated.any(axis=1).sum())} with a saturated chip")
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from .calibration.calfile import Calibration
    from .calibration.dataset import Dataset
    from .calibration.fit import fit
    from .calibration.report import format_rmse, write_report

    dataset = Dataset.load(args.dataset)
    result = fit(dataset)
    report = result.report
    nonlinear = None
    if not args.linear_only:
        from .calibration.nlfit import fit_nonlinear, nonlinear_rmse
        nonlinear = fit_nonlinear(dataset)
        validation = dataset.select(dataset.split == "validation")
        report["nonlinear"] = {"gap_mm": nonlinear.gap_m * 1e3, "fit_rms_residual_ut": nonlinear.fit_rms_residual_t * 1e6,
                               "validation_rmse": (dict(zip(("Fx", "Fy", "Fz", "Mx", "My", "Mz"),
                                                            nonlinear_rmse(nonlinear, validation).tolist()))
                                                   if len(validation) else None)}
    cal = Calibration(result.model, dataset.addresses, args.serial or dataset.serial, args.frame,
                      result.position_map, report, nonlinear, result.wrench_range)
    cal.save(args.output)
    sv, iso = report["singular_values_ka"], report["isotropy"]
    print(f"fit on {report['fit_poses']} poses ({report['left_out_saturated']} left out: saturated), "
          f"validated on {report['validation_poses']}")
    if report["validation_rmse"]:
        print("validation RMSE: " + format_rmse(report["validation_rmse"]))
    print("fit RMSE:        " + format_rmse(report["fit_rmse"]))
    if nonlinear is not None and report["nonlinear"]["validation_rmse"]:
        print(f"nonlinear (gap {nonlinear.gap_m * 1e3:.2f} mm) validation RMSE: "
              + format_rmse(report["nonlinear"]["validation_rmse"]))
    print(f"sigma(KA): forces {sv['forces'][0]:.3g}..{sv['forces'][-1]:.3g} N/uT (isotropy {iso['forces']:.2f}), "
          f"torques {sv['torques'][0]:.3g}..{sv['torques'][-1]:.3g} Nm/uT (isotropy {iso['torques']:.2f})")
    print(f"wrote {args.output}")
    if args.report:
        command = "ftsensord calibrate " + " ".join(args.argv)
        write_report(args.report, result.model, report, dataset.select(dataset.split == "validation"), command)
        print(f"wrote {args.report}")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    import logging

    from .service.config import load_config
    from .service.run import run

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    return run(load_config(args.config))


def _control(args: argparse.Namespace):
    from .client import ControlClient
    curve = (args.curve_cert, args.server_cert) if args.curve_cert else None
    if (args.curve_cert is None) != (args.server_cert is None):
        raise ConfigError("--curve-cert and --server-cert go together (CURVE needs both)")
    return ControlClient(args.control, timeout_s=args.timeout, curve=curve)


def cmd_status(args: argparse.Namespace) -> int:
    status = _control(args).status()
    if args.json:
        print(json.dumps(status, indent=2))
        return 0
    jitter = status["jitter_us"]
    rate = status["achieved_rate_hz"]
    print(f"ftsensord {status['version']}, up {status['uptime_s']:.0f} s, bus {status['bus']}, "
          f"scheduler {status['scheduler']}")
    print(f"rate: {rate:.2f} Hz achieved of {status['rate_hz']:g} Hz configured" if rate else
          f"rate: - of {status['rate_hz']:g} Hz configured")
    print(f"bound: {status['bound']}")
    print(f"cycles {status['cycles']}, missed {status['missed_cycles']}, late {status['late_cycles']}; "
          f"jitter p50 {jitter['p50']:.0f} us, p99 {jitter['p99']:.0f} us")
    cycle = status["cycle_us"]
    print(f"cycle p50 {cycle['p50']:.0f} us, p99 {cycle['p99']:.0f} us, max {cycle['max']:.0f} us "
          f"of a {status['period_us']:.0f} us period")
    print(f"averaging {status['averaging']}, low-pass {status['lowpass_hz'] or 'off'}")
    for name, s in status["sensors"].items():
        tare = "tared, offset " + " ".join(f"{v:+.4g}" for v in s["tare_wrench"]) if s["tared"] else "not tared"
        print(f"sensor {name}: frame {s['frame']}, serial {s['serial']}, {tare}; calibration {s['calibration']}")
    bad = {a: c for a, c in status["chips"].items() if not c["ok"] or c["errors"] or c["reinits"]}
    temps = [c["temperature_c"] for c in status["chips"].values() if c["temperature_c"] is not None]
    print(f"chips: {len(status['chips'])}, failing {sum(not c['ok'] for c in status['chips'].values())}"
          + (f", {min(temps):.1f}-{max(temps):.1f} degC" if temps else ""))
    for address, c in bad.items():
        retry = f", retry in {c['retry_in_s']:.2f} s" if c["retry_in_s"] is not None else ""
        print(f"  {address}: {c['state'].upper()}{retry}, {c['errors']} errors, {c['reinits']} resets, "
              f"{c['register_drifts']} register changes, {c['stuck_detections']} stuck; last: {c['last_error']}")
    return 0


def cmd_tare(args: argparse.Namespace) -> int:
    result = _control(args).tare(samples=args.samples, sensor=args.sensor)
    for name, offset in result["tare_wrench"].items():
        print(f"{name}: tared on {result['samples']} samples; removed " + " ".join(f"{v:+.4g}" for v in offset)
              + " (N, N, N, Nm, Nm, Nm)")
    return 0


def cmd_set(args: argparse.Namespace) -> int:
    changes = {k: v for k, v in (("rate_hz", args.rate), ("averaging", args.averaging),
                                 ("lowpass_hz", args.lowpass), ("estimator", args.estimator)) if v is not None}
    if not changes:
        raise ConfigError("set: nothing to change; give --rate, --averaging, --lowpass or --estimator")
    if args.sensor and set(changes) != {"estimator"}:
        raise ConfigError("set: --sensor goes with --estimator only (rate, averaging and low-pass are the loop's)")
    control = _control(args)
    if "estimator" in changes:  # its own request: it is per sensor, the others are the loop's
        sensor = {"sensor": args.sensor} if args.sensor else {}
        result = control.set(estimator=changes.pop("estimator"), **sensor)
        print("estimator: " + ", ".join(f"{n} {e}" for n, e in result["estimator"].items()))
    if changes:
        result = control.set(**changes)
        print(f"rate {result['rate_hz']:g} Hz, averaging {result['averaging']}, "
              f"low-pass {result['lowpass_hz'] or 'off'}")
    return 0


def cmd_reload(args: argparse.Namespace) -> int:
    result = _control(args).reload()
    print(f"reloaded {result['config']}; calibrations: "
          + ", ".join(f"{name} {path}" for name, path in result["calibrations"].items()))
    return 0


def _subscriber(args: argparse.Namespace):
    from .client import Subscriber
    return Subscriber(args.endpoint, [args.stream])


def cmd_echo(args: argparse.Namespace) -> int:
    from .service.wire import flag_names

    with _subscriber(args) as sub:
        n = 0
        while args.count is None or n < args.count:
            sample = sub.receive(timeout_s=args.timeout)
            if sample is None:
                print(f"ftsensord: no sample on {args.stream} within {args.timeout:g} s", file=sys.stderr)
                return 1
            values = " ".join(f"{v:+10.4f}" if sample.kind == 1 else f"{v * 1e6:+9.1f}" for v in sample.values)
            flags = ",".join(flag_names(sample.flags))
            print(f"{sample.seq:8d} {sample.t_mono:14.6f} {values}  {flags}", flush=True)
            n += 1
        if sub.gaps:
            print(f"gaps: {sub.gaps}", file=sys.stderr)
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    import time

    rows: list[tuple[float, ...]] = []
    with _subscriber(args) as sub:
        end = time.monotonic() + args.seconds if args.seconds else None
        while (args.count is None or len(rows) < args.count) and (end is None or time.monotonic() < end):
            sample = sub.receive(timeout_s=args.timeout)
            if sample is None:
                print(f"ftsensord: no sample on {args.stream} within {args.timeout:g} s", file=sys.stderr)
                break
            rows.append((sample.seq, sample.t_mono, sample.t_wall, sample.flags, *sample.values))
        gaps = sub.gaps.get(args.stream, 0)
    data = np.array(rows, dtype=float).reshape(len(rows), -1)
    if args.file.endswith(".npz"):
        np.savez(args.file, seq=data[:, 0].astype(np.int64), t_mono=data[:, 1], t_wall=data[:, 2],
                 flags=data[:, 3].astype(np.int64), values=data[:, 4:], gaps=gaps, stream=args.stream)
    else:
        n_values = data.shape[1] - 4
        names = (["fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm"] if args.stream.startswith("wrench/")
                 else [f"b{i // 3}{'xyz'[i % 3]}_T" for i in range(n_values)])
        with open(args.file, "w") as f:
            f.write(f"# ftsensord record of {args.stream}; {len(rows)} samples, {gaps} missed (sequence gaps)\n")
            f.write(",".join(["seq", "t_mono_s", "t_wall_s", "flags", *names]) + "\n")
            for row in data:
                f.write(f"{int(row[0])},{row[1]:.6f},{row[2]:.6f},{int(row[3])},"
                        + ",".join(f"{v:.9g}" for v in row[4:]) + "\n")
    print(f"wrote {args.file}: {len(rows)} samples of {args.stream}, {gaps} missed")
    return 0 if rows else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ftsensord", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"ftsensord {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="run the daemon (the systemd unit runs this)",
                       description="Read every chip in a steady loop, publish wrenches over ZeroMQ, and "
                                   "serve control requests. SIGTERM stops it cleanly, SIGHUP reloads.")
    p.add_argument("--config", help="configuration file (default: the simulated bus, default scene)")
    p.set_defaults(func=cmd_run)

    def control_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--control", help="control endpoint (default: the running daemon's ipc socket)")
        p.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the daemon (default 3)")
        p.add_argument("--curve-cert", help="this client's certificate (with secret key), for a CURVE endpoint")
        p.add_argument("--server-cert", help="the daemon's public certificate, for a CURVE endpoint")

    def stream_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("stream", help="stream: wrench/<sensor>, wrench/tip or flux/<sensor>")
        p.add_argument("--endpoint", help="publish endpoint (default: the running daemon's ipc socket)")
        p.add_argument("--count", type=int, help="stop after this many samples")
        p.add_argument("--timeout", type=float, default=3.0, help="give up after this long without a sample")

    p = sub.add_parser("status", help="the running daemon's health",
                       description="Rate achieved against configured and the computed bound, jitter, "
                                   "missed cycles, per-chip errors and temperatures, tare offsets, "
                                   "calibrations. Exit 1 with a message when no daemon answers.")
    p.add_argument("--json", action="store_true", help="print the whole status as JSON")
    control_options(p)
    p.set_defaults(func=cmd_status)

    p = sub.add_parser("tare", help="zero the output at the present load")
    p.add_argument("--samples", type=int, default=100, help="cycles to average (default 100)")
    p.add_argument("--sensor", help="only this sensor (default: all)")
    control_options(p)
    p.set_defaults(func=cmd_tare)

    p = sub.add_parser("set", help="change the rate, averaging, low-pass or estimator of the running daemon",
                       description="Changes last until the next restart or reload; a rate above the "
                                   "computed bound is refused, and nothing changes.")
    p.add_argument("--rate", type=float, help="loop rate, Hz")
    p.add_argument("--averaging", type=int, help="samples in the moving average (1: off)")
    p.add_argument("--lowpass", type=float, help="first-order low-pass cutoff, Hz (0: off)")
    p.add_argument("--estimator", choices=ESTIMATORS, help="K A, or the flux model (docs/nonlinear.md)")
    p.add_argument("--sensor", help="with --estimator: only this sensor (default: all)")
    control_options(p)
    p.set_defaults(func=cmd_set)

    p = sub.add_parser("reload", help="re-read the configuration and calibration files (as SIGHUP does)",
                       description="A file with an error is refused with a message naming the file and key; "
                                   "the running configuration then stays.")
    control_options(p)
    p.set_defaults(func=cmd_reload)

    p = sub.add_parser("echo", help="print a stream's samples live")
    stream_options(p)
    p.set_defaults(func=cmd_echo)

    p = sub.add_parser("record", help="record a stream to CSV or NPZ (by the file's extension)")
    stream_options(p)
    p.add_argument("file", help="output file: .csv or .npz")
    p.add_argument("--seconds", type=float, help="stop after this long")
    p.set_defaults(func=cmd_record)
    p = sub.add_parser("scan", help="find MLX90393 chips on a bus and read each once",
                       description="Probe 0x0C-0x1B and print each chip's part variant, "
                                   "configuration registers (as found) and one reading. "
                                   "Stops and reconfigures the chips: not while the daemon runs. "
                                   "Exit 0: all read; 1: none found; 2: some failed.")
    p.add_argument("--bus", default="sim", help=f"bus to scan: {ACCEPTED_FORMS} (default: sim)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=cmd_scan)

    p = sub.add_parser("dataset", help="record a calibration dataset on the simulated bus",
                       description="Run the paper's calibration procedure (section VII-B) on a simulated "
                                   "sensor: for each pose of the plan, apply the weight's wrench and average "
                                   "the chips' readings; also simulate each chip's position-map sweep. The "
                                   "file has the format a real calibration run records (docs/calibration.md).")
    p.add_argument("-o", "--output", required=True, help="dataset file to write (JSON)")
    p.add_argument("--scene", help="scene file of kind \"sensors\" (default: the two-sensor scene)")
    p.add_argument("--sensor", default="sensor1", help="which sensor of the scene (default: sensor1)")
    p.add_argument("--plan", default="six-axis", choices=sorted(PLANS),
                   help="lever arms: four that excite all six axes (default), or the paper's single rod")
    p.add_argument("--poses", type=int, default=193, help="fit poses, 50 g and 200 g (default: 193)")
    p.add_argument("--validation-poses", type=int, default=60, help="validation poses, 100 g (default: 60)")
    p.add_argument("--samples", type=int, default=100, help="readings averaged per pose (default: 100)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default: 0)")
    p.add_argument("--no-sweep", action="store_true", help="leave out the position-map sweeps")
    p.set_defaults(func=cmd_dataset)

    p = sub.add_parser("calibrate", help="fit K, A and the zero from a dataset",
                       description="Fit the linear model w = K A (b - b0) to the dataset's fit poses, "
                                   "report the RMSE per axis on its validation poses, and write the "
                                   "calibration file. Refuses (exit 2) when the dataset does not excite all "
                                   "six axes, saying what to add to the plan.")
    p.add_argument("dataset", help="dataset file (from `ftsensord dataset` or a real calibration run)")
    p.add_argument("-o", "--output", required=True, help="calibration file to write (JSON)")
    p.add_argument("--report", help="also write a Markdown report (and a PNG plot beside it)")
    p.add_argument("--serial", help="sensor serial to record (default: the dataset's)")
    p.add_argument("--frame", default="sensor", help="name of the sensor frame (default: sensor)")
    p.add_argument("--linear-only", action="store_true",
                   help="skip the nonlinear estimator's calibration (about 10 s for 193 poses)")
    p.set_defaults(func=cmd_calibrate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.argv = argv[1:]
    try:
        return int(args.func(args))
    except DaemonNotAnswering as exc:
        print(f"ftsensord: {exc}", file=sys.stderr)
        return 1
    except FtsensordError as exc:
        print(f"ftsensord: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # e.g. /dev/i2c-N missing or not permitted
        print(f"ftsensord: {exc}", file=sys.stderr)
        return 2
