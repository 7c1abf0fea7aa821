"""Where is the point dipole good enough? Writes docs/results/field-model.png and prints a table.

Compares the dipole with the exact cylinder field of the paper's D101-N52
magnet against distance, in three directions, and marks the chip's reading
noise and the distances that occur in the sensor (the own magnet at the gap,
the nearest neighbour magnets). Run:

    python -m benchmarks.accuracy.field_models            # needs the plot extra (matplotlib)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import RESULTS
from ftsensord.chip import mlx90393 as mlx
from ftsensord.model.geometry import SensorGeometry
from ftsensord.model.magnet import cylinder_field, dipole_field
from ftsensord.sim.chip import NoiseModel


def errors(distances: np.ndarray, theta: float, g: SensorGeometry) -> np.ndarray:
    direction = np.array([np.sin(theta), 0.0, np.cos(theta)])
    r = distances[:, None] * direction
    exact = cylinder_field(r, g.magnet_radius_m, g.magnet_length_m, g.magnet_br_t)
    dipole = dipole_field(r, np.array([0.0, 0.0, g.magnet_moment_am2]))
    return np.linalg.norm(exact - dipole, axis=1)


def neighbour_distances(g: SensorGeometry) -> np.ndarray:
    d = np.linalg.norm(g.chip_p[:, None, :] - g.magnet_p[None, :, :], axis=2)
    return np.sort(d[~np.eye(g.n_chips, dtype=bool)])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=RESULTS, help="folder for field-model.png")
    args = parser.parse_args(argv)
    g = SensorGeometry.ring()
    noise = NoiseModel().sigma_ut("x", mlx.Settings().tconvm_us())
    distances = np.geomspace(2e-3, 30e-3, 200)
    angles = {"on axis": 0.0, "45 deg": np.pi / 4, "equator": np.pi / 2}
    curves = {name: errors(distances, th, g) * 1e6 for name, th in angles.items()}
    gap = float(np.linalg.norm(g.magnet_in_chip()[0]))
    near = neighbour_distances(g)
    print("| distance (mm) | worst |B_dipole - B_cylinder| (uT) |")
    print("|---|---|")
    for d in (3e-3, gap, 8e-3, near[0], 12e-3, 15e-3, 20e-3):
        worst = max(errors(np.array([d]), th, g)[0] for th in np.linspace(0, np.pi / 2, 19)) * 1e6
        print(f"| {d * 1e3:.1f} | {worst:.2f} |")
    print(
        f"reading noise (one reading, X/Y, paper settings): {noise:.2f} uT; "
        f"averaged over 100: {noise / 10:.2f} uT"
    )
    print(
        f"own magnet at {gap * 1e3:.1f} mm; other magnets from {near[0] * 1e3:.1f} mm "
        f"to {near[-1] * 1e3:.1f} mm"
    )
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is missing (pip install 'ftsensord[plot]'): no figure written", file=sys.stderr)
        return 1
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    for name, err in curves.items():
        ax.loglog(distances * 1e3, err, label=f"dipole error, {name}")
    ax.axhline(noise, color="k", ls="--", lw=1, label=f"reading noise, one reading ({noise:.1f} uT)")
    ax.axhline(noise / 10, color="k", ls=":", lw=1, label="reading noise, mean of 100")
    ax.axvline(gap * 1e3, color="tab:red", lw=1)
    ax.text(gap * 1e3 * 1.02, 3e3, "own magnet", color="tab:red", rotation=90, va="top")
    ax.axvspan(
        near[0] * 1e3, near[-1] * 1e3, color="tab:green", alpha=0.12, label="other magnets (crosstalk)"
    )
    ticks = [2, 3, 4, 6, 8, 10, 15, 20, 30]
    ax.set_xticks(ticks, [str(t) for t in ticks])
    ax.set_xlabel("distance from the magnet's centre (mm)")
    ax.set_ylabel("|B_dipole - B_cylinder| (uT)")
    ax.set_title('D101-N52 (1/16" x 1/32", Br 1.45 T): point dipole against the exact cylinder')
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    out = args.out / "field-model.png"
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
