"""Floor 7, stages: what acts on a sensor's flux before its estimator and on its wrench
after, beside the estimators themselves (`model`), and apart from the service's loop and
control. A stage owns one physical effect the calibration did not see.

- `thermal`: the chips' temperatures against the calibration's: the magnets' remanence,
  the chips' sensitivity and the silicone's stiffness compensated by their laws (and each
  channel's drift, when the calibration measured it), samples beyond the span flagged.

May import: `calibration`, `model`, `chip` (and the floors below); never `service`.
"""

from .thermal import ThermalCompensation  # noqa: F401
