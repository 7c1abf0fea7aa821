"""The calibration report: a Markdown page and, where matplotlib is installed,
a plot of applied against measured wrench per axis (the paper's Fig. 9)."""

from __future__ import annotations

from pathlib import Path

from ftsensord.calibration.dataset import AXES, AXIS_UNITS, Dataset
from ftsensord.model.linear import LinearModel

#: The paper's Table II, RMS error per axis (N; mNm for torques).
PAPER_TABLE_II = (0.2338, 0.1136, 0.3775, 4.1e-3, 10.6e-3, 8.5e-3)


def format_rmse(values: dict[str, float] | list[float]) -> str:
    """'Fx 0.0269 N, ... Mz 1.39 mNm' (torques in mNm, as the paper)."""
    vals = list(values.values()) if isinstance(values, dict) else list(values)
    return ", ".join(
        f"{a} {v:.3g} N" if u == "N" else f"{a} {v * 1e3:.3g} mNm" for a, u, v in zip(AXES, AXIS_UNITS, vals)
    )


def rmse_table(rows: list[tuple[str, list[float] | None, str]]) -> str:
    """Markdown table of RMSE rows (label, 6 values or None, note)."""
    out = [
        "| | Fx (N) | Fy (N) | Fz (N) | Mx (mNm) | My (mNm) | Mz (mNm) | |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for label, values, note in rows:
        cells = (
            ["-"] * 6
            if values is None
            else [f"{v:.4f}" if k < 3 else f"{v * 1e3:.2f}" for k, v in enumerate(values)]
        )
        out.append(f"| {label} | " + " | ".join(cells) + f" | {note} |")
    return "\n".join(out)


def plot_validation(model: LinearModel, validation: Dataset, path: Path) -> bool:
    """Applied against measured per axis, as PNG; False when matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    measured = model.wrench(validation.flux_t)
    fig, axes = plt.subplots(2, 3, figsize=(11, 6.5))
    for k, ax in enumerate(axes.flat):
        scale = 1.0 if k < 3 else 1e3
        applied = validation.wrench[:, k] * scale
        ax.plot(applied, label="applied", lw=1.5)
        ax.plot(measured[:, k] * scale, ".", ms=4, label="measured")
        ax.set_title(f"{AXES[k]} ({'N' if k < 3 else 'mNm'})")
        ax.set_xlabel("validation pose")
        ax.grid(alpha=0.3)
    axes.flat[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def write_report(
    path: str | Path, model: LinearModel, report: dict, validation: Dataset, command: str
) -> None:
    """The Markdown report, and its plot beside it (same name, .png)."""
    path = Path(path)
    png = path.with_suffix(".png")
    plotted = len(validation) > 0 and plot_validation(model, validation, png)
    sv, iso = report["singular_values_ka"], report["isotropy"]
    rows: list[tuple[str, list[float] | None, str]] = [
        ("paper, Table II", list(PAPER_TABLE_II), "real sensor")
    ]
    if report["validation_rmse"]:
        rows.append(
            (
                "this calibration",
                list(report["validation_rmse"].values()),
                f"{report['validation_poses']} held-out poses",
            )
        )
    rows.append(("fit residual", list(report["fit_rmse"].values()), f"{report['fit_poses']} fit poses"))
    lines = [
        "# Calibration report",
        "",
        f"Produced by `{command}`.",
        "",
        "## RMS error per axis",
        "",
        rmse_table(rows),
        "",
        "## Error propagation (section VI)",
        "",
        f"- forces: sigma_max(KA) = {sv['forces'][0]:.3g} N/uT, sigma_min = {sv['forces'][-1]:.3g} N/uT, "
        f"isotropy {iso['forces']:.2f} (paper: 6.07e-3, 2.88e-3, 0.47)",
        f"- torques: sigma_max(KA) = {sv['torques'][0]:.3g} Nm/uT, sigma_min = {sv['torques'][-1]:.3g} Nm/uT, "
        f"isotropy {iso['torques']:.2f} (paper: 2.26e-3, 1.48e-3, 0.65)",
        "",
        "## Data",
        "",
        f"- poses: {report['fit_poses']} fit, {report['validation_poses']} validation, "
        f"{report['left_out_saturated']} left out (a chip saturated); {report['samples_per_pose']} samples a pose",
        f"- wrench excitation: condition number {report['wrench_excitation']['condition']:.3g} "
        "(range-scaled, centred)",
        f"- flux directions kept above the noise floor ({report['noise_floor_ut']:.3g} uT): "
        f"{report['flux_rank_above_floor']}",
        f"- position map: {report['position_map']}",
        f"- room field: {_room_line(report.get('room_field'))}",
        "",
    ]
    warnings = (report.get("nonlinear") or {}).get("warnings") or []
    if warnings:
        lines[2:2] = [
            "## WARNING: the nonlinear calibration was kept against its refusal or departs from the part",
            "",
            *[f"- {w}" for w in warnings],
            "",
        ]
    if report.get("warnings"):
        lines[2:2] = [
            "## WARNING: the data had faults, left out or kept as named",
            "",
            *[f"- {w}" for w in report["warnings"]],
            "",
        ]
    if plotted:
        lines += ["## Applied against measured (validation poses)", "", f"![validation]({png.name})", ""]
    elif len(validation):
        lines += ["(No plot: install the `plot` extra, `pip install 'ftsensord[plot]'`, for matplotlib.)", ""]
    path.write_text("\n".join(lines))


def _room_line(room: dict | None) -> str:
    """How the fit treated the room's field, in words."""
    if not room or room.get("mode") == "none":
        return (
            "not rejected (a field-free room assumed: record no-load poses, docs/guide/calibration.md)"
            if room is not None
            else "not recorded"
        )
    text = f"{room['mode']} directions projected out ({room.get('source', '')}; {room['no_load_poses']} no-load poses)"
    if "singular_values_ut" in room:
        text += (
            ": no-load flux singular values "
            + ", ".join(f"{v:.3g}" for v in room["singular_values_ut"])
            + " uT"
        )
    return text
