"""Floor 7, stages: what acts on a sensor's flux before its estimator and on its wrench
after, beside the estimators themselves (`model`), and apart from the service's loop and
control. A stage owns one physical effect the calibration did not see.

- `thermal`: the chips' temperatures against the calibration's: the magnets' remanence,
  the chips' sensitivity and the silicone's stiffness compensated by their laws (and each
  channel's drift, when the calibration measured it), samples beyond the span flagged.
- `stray`: a motor's field gradient across the ring, fixed in the world, learnt from the
  two parts the ring tells from a load as the tool turns; the three it cannot tell then
  taken out of the flux (`stray_field = "world"`).
- `silicone`: the silicone's creep undone on the wrench, per axis, from the series the
  calibration identified (a recursive inverse; restarted by a tare, a rate change or a
  flagged sample).

May import: `calibration`, `model`, `chip` (and the floors below); never `service`.
"""

from .silicone import CreepCompensation  # noqa: F401
from .stray import WorldGradient  # noqa: F401
from .thermal import ThermalCompensation  # noqa: F401
