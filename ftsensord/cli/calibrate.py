"""The calibration's commands: dataset (the simulated procedure) and calibrate (the fit)."""

from __future__ import annotations

import argparse
import sys

from ftsensord.sim.loads import HOLD_PERIOD_S, HOLD_S, PLANS


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Its commands, in the order `ftsensord --help` lists them."""
    p = sub.add_parser(
        "dataset",
        help="record a calibration dataset on the simulated bus",
        description="Run the paper's calibration procedure (section VII-B) on a simulated "
        "sensor: for each pose of the plan, apply the weight's wrench and average "
        "the chips' readings; also simulate each chip's position-map sweep. The "
        "file has the format a real calibration run records "
        "(docs/guide/calibration.md).",
    )
    p.add_argument("-o", "--output", required=True, help="dataset file to write (JSON)")
    p.add_argument("--scene", help='scene file of kind "sensors" (default: two as-built sensors in the room)')
    p.add_argument("--sensor", default="sensor1", help="which sensor of the scene (default: sensor1)")
    p.add_argument(
        "--plan",
        default="six-axis",
        choices=sorted(PLANS),
        help="lever arms: four long ones and the flange's centre, exciting all six axes (default), "
        "or the paper's single rod",
    )
    p.add_argument("--poses", type=int, default=193, help="fit poses, 50 g and 200 g (default: 193)")
    p.add_argument("--validation-poses", type=int, default=60, help="validation poses, 100 g (default: 60)")
    p.add_argument("--samples", type=int, default=100, help="readings averaged per pose (default: 100)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default: 0)")
    p.add_argument("--no-sweep", action="store_true", help="leave out the position-map sweeps")
    p.add_argument(
        "--no-load-poses",
        type=int,
        default=24,
        help="poses with the rod and masses off, to measure the room's field (default: 24; "
        "at least 6 for the fit to use them, 12 or more advised)",
    )
    p.add_argument(
        "--check-poses",
        type=int,
        default=24,
        help="poses with 1, 2 and 4 kg at the flange's centre, "
        "on which the model is judged at large loads (default: 24; 0: none)",
    )
    p.add_argument(
        "--hold-s",
        type=float,
        default=HOLD_S,
        help="s each step-and-hold pose is held (0: none; docs/guide/calibration.md)",
    )
    p.add_argument(
        "--hold-period-s", type=float, default=HOLD_PERIOD_S, help="s between its readings (0: fastest)"
    )
    p.set_defaults(func=cmd_dataset)
    p = sub.add_parser(
        "calibrate",
        help="fit K, A and the zero from a dataset",
        description="Fit w = K A (b - b0) to the dataset's fit poses, report the validation "
        "RMSE per axis and write the calibration file. Refuses (exit 2), naming the "
        "cause and the fix, data it can tell are wrong; leaves out outlier and repeated "
        "poses, and keeps a weak plan or a part off the model, with a WARNING line each.",
    )
    p.add_argument("dataset", help="dataset file (from `ftsensord dataset` or a real calibration run)")
    p.add_argument("-o", "--output", required=True, help="calibration file to write (JSON)")
    p.add_argument("--report", help="also write a Markdown report (and a PNG plot beside it)")
    p.add_argument("--serial", help="sensor serial to record (default: the dataset's)")
    p.add_argument("--frame", default="sensor", help="name of the sensor frame (default: sensor)")
    p.add_argument(
        "--linear-only",
        action="store_true",
        help="skip the nonlinear estimator's calibration (a few s for 193 poses)",
    )
    p.add_argument(
        "--allow-poor-fit",
        action="store_true",
        help="keep a nonlinear fit that would be refused (a magnet fitted far off, a residual far "
        "above noise), with its warnings in the file and report",
    )
    p.set_defaults(func=cmd_calibrate)


def cmd_dataset(args: argparse.Namespace) -> int:
    from ftsensord.calibration.procedure import simulate_dataset

    sizes = {
        k: getattr(args, k)
        for k in (
            "poses",
            "validation_poses",
            "samples",
            "seed",
            "no_load_poses",
            "check_poses",
            "hold_s",
            "hold_period_s",
        )
    }
    dataset = simulate_dataset(args.scene, args.sensor, args.plan, sweeps=not args.no_sweep, **sizes)
    dataset.save(args.output)
    print(
        f"wrote {args.output}: {len(dataset)} poses ({args.plan}), {args.samples} samples each, "
        f"{int(dataset.saturated.any(axis=1).sum())} with a saturated chip"
        + (f"; a step-and-hold of {len(dataset.hold.times_s)} readings" if dataset.hold is not None else "")
    )
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from ftsensord.calibration.dataset import Dataset
    from ftsensord.calibration.nlfit import FitProgress
    from ftsensord.calibration.procedure import calibrate, summary
    from ftsensord.calibration.report import write_report
    from ftsensord.errors import CalibrationError

    dataset = Dataset.load(args.dataset)

    def progress(p: FitProgress) -> None:
        print(
            f"nonlinear fit: iteration {p.step}/{p.steps}, residual {p.rms_residual_t * 1e6:.2f} uT RMS, "
            f"{p.elapsed_s:.1f} s",
            file=sys.stderr,
            flush=True,
        )

    try:
        cal, result = calibrate(
            dataset,
            serial=args.serial,
            frame=args.frame,
            nonlinear=not args.linear_only,
            progress=progress,
            allow_poor_fit=args.allow_poor_fit,
        )
    except CalibrationError as exc:
        if "nonlinear fit is refused" not in str(exc):
            raise
        # Nothing is written: the user chooses between the linear part alone and a poor fit.
        raise CalibrationError(
            f"{exc}\nNo file written. To write the linear calibration alone: "
            f"ftsensord calibrate {args.dataset} -o {args.output} --linear-only; to keep "
            "this nonlinear fit with its warnings: add --allow-poor-fit"
        ) from exc
    cal.save(args.output)
    print(summary(cal))
    print(f"wrote {args.output}")
    if args.report:
        command = "ftsensord calibrate " + " ".join(args.argv)
        write_report(
            args.report, result.model, cal.report, dataset.select(dataset.split == "validation"), command
        )
        print(f"wrote {args.report}")
    return 0
