"""An accuracy a user asks for: a force or a torque, written with its unit ("0.02N", "0.5mNm").

`ftsensord set --accuracy` and a sensor table's ``accuracy`` key take one or more of them; the
settings that meet them are chosen by `processing.accuracy.plan`. A target bounds every axis
of its kind: "0.02N" asks each of fx, fy and fz to have a predicted 1-sigma of at most 0.02 N
at rest, "0.5mNm" each of mx, my and mz at most 0.0005 Nm.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from ftsensord.errors import ConfigError

#: Units accepted, their factor to SI and the kind they bound: forces in N, torques in Nm.
UNITS = {
    "N": (1.0, "force"),
    "mN": (1e-3, "force"),
    "uN": (1e-6, "force"),
    "Nm": (1.0, "torque"),
    "mNm": (1e-3, "torque"),
    "uNm": (1e-6, "torque"),
}
_FORM = re.compile(r"\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([a-zA-Z]+)\s*")
#: What a target looks like, for the errors.
EXPECTED = "a positive number and its unit, N, mN or uN for a force, Nm, mNm or uNm for a torque (e.g. 0.02N, 0.5mNm)"


@dataclass(frozen=True)
class Accuracy:
    """A target 1-sigma (``value``: N or Nm) for every axis of ``kind`` ("force" or "torque");
    ``text`` as the user wrote it."""

    value: float
    kind: str
    text: str

    @property
    def axes(self) -> slice:
        """The wrench's axes it bounds: fx fy fz, or mx my mz."""
        return slice(0, 3) if self.kind == "force" else slice(3, 6)

    @property
    def unit(self) -> str:
        return "N" if self.kind == "force" else "Nm"


def parse_accuracy(text: object, where: str = "accuracy") -> Accuracy:
    """``text`` ("0.02N", "20 mN", "0.5mNm") as an `Accuracy`; ConfigError naming ``where`` and
    the form expected otherwise."""
    found = _FORM.fullmatch(text) if isinstance(text, str) else None
    if found is None or found.group(2) not in UNITS:
        raise ConfigError(f"{where}: expected {EXPECTED}, got {text!r}")
    number = float(found.group(1))
    if not (number > 0 and math.isfinite(number)):
        raise ConfigError(f"{where}: expected {EXPECTED}, got {text!r}")
    factor, kind = UNITS[found.group(2)]
    return Accuracy(number * factor, kind, str(text).strip())


def parse_accuracies(value: object, where: str = "accuracy") -> list[Accuracy]:
    """One target or a list of them (at most one force and one torque)."""
    items = value if isinstance(value, list) else [value]
    if not items:
        raise ConfigError(f"{where}: expected {EXPECTED}, or a list of them, got an empty list")
    targets = [parse_accuracy(item, where) for item in items]
    kinds = [t.kind for t in targets]
    if len(set(kinds)) != len(kinds):
        raise ConfigError(f"{where}: expected at most one force and one torque target, got {value!r}")
    return targets
