"""The scene's silicone with a memory: a sensor's load history drives its deflection through
the Prony series of `model.viscoelastic`, when the scene asks for it (``[sensor.silicone]``,
docs/design/scenes.md); a scene without it pays nothing (`SimSensor.memory` is None).

The series' default and its sources are in docs/design/physics.md ("The silicone's memory").
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ftsensord.docfile import Table
from ftsensord.model.viscoelastic import MAX_TERMS, CreepFilter, Relaxation

#: The default series (fraction, time in s): 2.5 % relaxing in about 0.2 s, 5 % over half a
#: minute. The fast term is fitted to the published cyclic loss of Ecoflex 00-30 at 0.1-1 Hz
#: (Romano et al. 2024, Table 2; docs/design/physics.md, "The silicone's memory"); the slow
#: term, the minutes-long creep the relaxation papers describe, is a stated choice.
DEFAULT_RELAXATION = ((0.025, 0.21), (0.05, 30.0))


#: A reading asked this many steps (1 s) before the state is a scene read again by a new
#: clock (a bus built afresh starts its time at 0): the memory starts afresh too.
RESTART_STEPS = 1000


class SiliconeMemory:
    """One sensor's creep state on the scene's time grid (``step_s``): `effective` gives
    w_eff at grid step ``k`` from the load's history, each step's load held over it.

    The state moves forwards only: a chip's reading asked for an earlier step than the last
    (chips of one cycle finish within a step or two of each other) gets the latest state,
    at most one step's creep (tens of ppm of the load at a 1 s time) away. The first step
    asked, and one asked more than `RESTART_STEPS` back, starts from its load long in place
    (`CreepFilter.settle`)."""

    def __init__(self, relaxation: Relaxation, step_s: float):
        self.filter = CreepFilter(relaxation, step_s)
        self.step_s = step_s
        self.k: int | None = None  # the grid step the state stands at (loads before it integrated)

    @property
    def relaxation(self) -> Relaxation:
        return self.filter.relaxation

    def effective(self, k: int, wrench: Callable[[float], np.ndarray], constant: bool) -> np.ndarray:
        """w_eff (N, Nm) at grid step ``k``; ``wrench(t)`` is the load, ``constant`` says it
        never changes (one exact update however long the gap)."""
        h = self.step_s
        if self.k is None or k < self.k - RESTART_STEPS:  # the first reading, or a new clock from 0
            self.filter.settle(wrench(k * h))
            self.k = k
        elif k > self.k:
            if constant:
                self.filter.advance(wrench(k * h), k - self.k)
            else:
                for j in range(self.k, k):
                    self.filter.advance(wrench(j * h))
            self.k = k
        return self.filter.output(wrench(max(k, self.k) * h))


def parse_silicone(t: Table) -> Relaxation:
    """A sensor's ``[sensor.silicone]`` table: ``relaxation = [[fraction, time_s], ...]``
    (default `DEFAULT_RELAXATION`)."""
    t.only({"relaxation"})
    rows = t.get("relaxation", [list(r) for r in DEFAULT_RELAXATION])
    expected = (
        f"1 to {MAX_TERMS} pairs [fraction, time_s]: fractions > 0 summing below 0.9, distinct times > 0 s "
        "(a Prony series of the stiffness, docs/design/scenes.md)"
    )
    if (
        not isinstance(rows, list)
        or not rows
        or not all(isinstance(r, list) and len(r) == 2 and all(_number(v) for v in r) for r in rows)
    ):
        raise t.fail("relaxation", expected, rows)
    try:
        return Relaxation.from_pairs(rows)
    except ValueError as exc:
        raise t.fail("relaxation", f"{expected}; {exc}", rows) from exc


def _number(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
