"""The ``[[sensor]]`` tables: each sensor's chips, calibration, frame, estimator and
stray-field stage, validated against its calibration file (read once, again only
when the file changes).
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from ftsensord.calibration.calfile import Calibration
from ftsensord.calibration.dataset import parse_addresses
from ftsensord.config.accuracy import EXPECTED, Accuracy, parse_accuracies
from ftsensord.config.frames import MAX_FRAME_NAME, TIP
from ftsensord.docfile import Table
from ftsensord.errors import ConfigError
from ftsensord.model.linear import LinearModel
from ftsensord.protocol.paths import resolve_file

ESTIMATORS = ("linear", "nonlinear")
#: A sensor's name is in its streams' topics (ASCII on the wire), ROS 2 names and orientation
#: messages (`MAX_FRAME_NAME`): one token, as ROS 2 names take it.
SENSOR_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
#: Beside the deflection: the room's field; its gradient's parts a ring tells apart; a world-fixed
#: gradient (`processing.stray`).
STRAY_FIELDS = ("uniform", "gradient", "world")


@dataclass
class SensorConfig:
    name: str
    addresses: tuple[int, ...]
    calibration_path: Path
    calibration: Calibration
    frame: str  # the frame its wrench is expressed in (default: the calibration's)
    estimator: str = "linear"  # "linear" (K A) or "nonlinear" (the flux model, docs/results/tradeoff.md)
    stray_field: str = "uniform"  # `STRAY_FIELDS`
    table: Table | None = field(
        default=None, repr=False, compare=False
    )  # where it was read: for errors naming it
    #: The accuracy asked for ("0.02N", "0.5mNm": `config.accuracy`): the daemon chooses the
    #: conversion, averaging and rate that meet it at start (`processing.accuracy.plan`); () none.
    accuracy: tuple[Accuracy, ...] = ()

    @property
    def model(self) -> LinearModel:  # the run time's: the calibration's, `LinearModel.with_gradient` if asked
        return (
            self.calibration.model.with_gradient()
            if self.stray_field == "gradient"
            else self.calibration.model
        )


class Calibrations:
    """Calibration files by path, read again only when changed: a reload that changes a
    rate reuses the checked calibrations (and their pipelines' precomputed checks) instead
    of parsing them again, so it fits between two cycles. Changed means another size,
    modification time or inode: an editor or `ftsensord calibrate -o` changes them all."""

    def __init__(self) -> None:
        self._seen: dict[Path, tuple[tuple[int, ...], Calibration]] = {}

    @staticmethod
    def _signature(path: Path) -> tuple[int, ...]:
        st = path.stat()
        return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns

    def remember(self, sensors: Iterable[SensorConfig]) -> Calibrations:
        """Take the ``sensors``' calibrations as their files are now; returns self."""
        for s in sensors:
            self._seen[s.calibration_path] = (self._signature(s.calibration_path), s.calibration)
        return self

    def load(self, path: Path) -> Calibration:
        seen = self._seen.get(path)
        try:
            signature = self._signature(path)
        except OSError:
            signature = ()  # Calibration.load names the file and the error
        if seen is not None and seen[0] == signature:
            return seen[1]
        calibration = Calibration.load(path)
        if signature:
            self._seen[path] = (signature, calibration)
        return calibration


def sensor_tables(doc: Table, calibrations: Calibrations | None = None) -> list[SensorConfig]:
    """``doc``'s ``[[sensor]]`` tables, checked against each other and their calibrations
    (``calibrations``: files already read, reused where unchanged)."""
    sensors: list[SensorConfig] = []
    seen: set[int] = set()
    for t in doc.tables("sensor"):
        t.only({"name", "addresses", "calibration", "frame", "estimator", "stray_field", "accuracy"})
        addresses = parse_addresses(t, "addresses")
        for a in addresses:
            if a in seen:
                raise t.fail("addresses", "addresses no other sensor uses", f"0x{a:02X}")
            seen.add(a)
        cal_path = resolve_file(t, "calibration", t.string("calibration"))
        calibration = calibrations.load(cal_path) if calibrations is not None else Calibration.load(cal_path)
        if calibration.addresses != addresses:
            raise t.fail(
                "calibration",
                f"a calibration for the chips {[f'0x{a:02X}' for a in addresses]} in this order",
                f"{cal_path} (for {[f'0x{a:02X}' for a in calibration.addresses]})",
            )
        name = t.string("name")
        if not SENSOR_NAME.fullmatch(name) or len(name) > MAX_FRAME_NAME or name == TIP:
            raise t.fail(
                "name",
                f"a name of letters, digits and underscores, not starting with a digit, at most "
                f"{MAX_FRAME_NAME} characters, not {TIP} (the tool's: wrench/{TIP})",
                name,
            )
        if any(s.name == name for s in sensors):
            raise t.fail("name", "a name no other sensor has", name)
        estimator = t.string("estimator", "linear", choices=ESTIMATORS)
        if estimator == "nonlinear" and calibration.nonlinear is None:
            raise t.fail(
                "estimator",
                f'"linear": {cal_path} has no nonlinear calibration '
                "(make one with `ftsensord calibrate` without --linear-only)",
                estimator,
            )
        stray_field = t.string("stray_field", "uniform", choices=STRAY_FIELDS)
        accuracy: tuple[Accuracy, ...] = ()
        if "accuracy" in t.doc:
            try:
                accuracy = tuple(parse_accuracies(t.get("accuracy")))
            except ConfigError as exc:
                raise t.fail("accuracy", f"{EXPECTED}, or a list of one of each", t.get("accuracy")) from exc
        if stray_field != "uniform" and calibration.model.H is None:
            raise t.fail("stray_field", f'"uniform": {cal_path} has no flux model H', stray_field)
        sensors.append(
            SensorConfig(
                name,
                addresses,
                cal_path,
                calibration,
                t.string("frame", calibration.frame),
                estimator,
                stray_field,
                t,
                accuracy,
            )
        )
    return sensors
