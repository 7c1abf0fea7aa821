"""Floor 6, calibration: from recorded flux and known loads to a calibration file.

Owns datasets (`dataset`), recording them on a rig or in simulation (`rig`),
the linear fit with its identifiability checks (`fit`), the silicone's relaxation from a
step-and-hold segment (`creep`), the nonlinear model's
fit (`nlfit`), the versioned calibration file (`calfile`) and the Markdown
report (`report`).

May import: `model`, `chip`, `sim` (to simulate a calibration run),
`docfile`, `errors`. Not acquire's schedulers or the service.
"""
