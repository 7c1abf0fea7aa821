"""Floor 2, the model: pure maths and physics, in the paper's names.

Owns SO(3)/SE(3) (`se3`), point-set registration (`registration`), magnet
fields (`magnet`: dipole, exact cylinder, the cylinder's octupole, remanence
against temperature), the silicone's laws (`silicone`) and memory (`viscoelastic`: a Prony
series, its creep and the recursive filters both ways), the sensor's
chip and magnet layout (`geometry`), the linear `K A` estimator with its degraded
form and the tip wrench (`linear`), and the nonlinear flux-model estimator
(`nonlinear`) with its forward model (`fluxmodel`),
and the same solve compiled (`nlcompiled`: `_nlsolve.c`, plain C, called through ctypes). Units are SI: tesla,
metres, newtons, newton-metres.

May import: numpy and `ftsensord.errors`. Nothing of the package above.
"""
