"""Floor 9, processing: one sensor's way from a cycle's chip results to a flagged,
filtered wrench, and what acts on it.

- `pipeline`: flux, usable chips, the estimate (linear or nonlinear), flags, overload,
  filter; the tip's wrench from the sensors'.
- `redundancy`: which chips agree with one deflection, sample by sample.
- `temperature`, `stray`, `creep`: the stages, each one physical effect the calibration
  did not see (a warm sensor; a motor's gradient, fixed in the world; the silicone's
  creep), applied by the pipeline, each of one shape (`stage.Stage`).
- `filters`: averaging and the low-pass; `tare`: a new zero from no-load samples;
  `gravity`: the tool's weight taken out as it turns.

May import: `config` (a sensor's table), `protocol` (flags), `calibration`, `acquire`
(chip results), `chip`, `model`, `errors`. Never `daemon`: nothing here knows of sockets,
the loop's timing or control.
"""
