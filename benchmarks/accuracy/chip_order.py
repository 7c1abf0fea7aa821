"""How much of each chip's response the nominal model leaves on as-built parts: the figure
the chip-order check (`calibration.screening.MISMATCH_LIMIT`) refuses above.

    python -m benchmarks.accuracy.chip_order --seeds 1-60     # one line per part, then the spread

Each part: the default scene's sensor1 tolerances with that seed, in the Earth's field,
the six-axis plan's 193 fit poses at 10 readings a pose (`simulate_dataset`), fitted as
`ftsensord calibrate --linear-only` does. A refused part prints its three largest shares.
"""

from __future__ import annotations

import argparse
import re
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import part_table
from ftsensord.calibration.procedure import calibrate, simulate_dataset
from ftsensord.calibration.screening import MISMATCH_LIMIT
from ftsensord.errors import CalibrationError


def mismatch(seed: int, folder: Path) -> float:
    """The part's largest share (0-1), or, refused, the largest its message names."""
    scene = folder / f"part{seed}.toml"
    scene.write_text(part_table(seed))
    ds = simulate_dataset(
        scene, "sensor1", "six-axis", poses=193, validation_poses=4, samples=10, seed=seed, sweeps=False
    )
    try:
        cal, _ = calibrate(ds, serial=f"part{seed}", frame="sensor1", nonlinear=False)
    except CalibrationError as exc:
        shares = re.findall(r"(\d+) %", str(exc))
        if "respond to the loads" not in str(exc) or not shares:
            raise
        return float(shares[0]) / 100
    return float(cal.report["chip_response_mismatch"])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-60", help="a range of part seeds, FIRST-LAST (default 1-60)")
    args = ap.parse_args(argv)
    first, last = (int(x) for x in args.seeds.split("-"))
    shares = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(first, last + 1):
            shares.append(mismatch(seed, Path(tmp)))
            print(
                f"part {seed}: {shares[-1]:.3f}" + ("  (refused)" if shares[-1] > MISMATCH_LIMIT else ""),
                flush=True,
            )
    s = np.array(shares)
    print(
        f"{len(s)} parts: largest share {s.min():.2f}-{s.max():.2f}, median {np.median(s):.2f}; "
        f"{int((s > MISMATCH_LIMIT).sum())} above the limit {MISMATCH_LIMIT}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
