"""The silicone layer's laws: how its stiffness changes with temperature.

The sensor's compliance is a platinum silicone (Ecoflex 00-30 class) far above its glass
transition (about -120 degC for silicones), in its rubbery plateau, where elasticity is
entropic: a network's shear modulus is G = n k_B T (Treloar, The Physics of Rubber
Elasticity, 3rd ed., 1975, ch. 4), proportional to the absolute temperature. The stiffness
K of the layer scales with it. docs/design/physics.md ("Temperature") says what was taken and why.
"""

from __future__ import annotations

#: Relative stiffness change per K from 25 degC: G proportional to T in kelvin gives
#: K(T) = K(25 degC) (1 + (T - 25) / 298.15 K), exactly linear; warm silicone is stiffer.
STIFFNESS_TEMPCO_PER_K = 1.0 / 298.15


def stiffness_factor(delta_k: float) -> float:
    """K(T) / K(25 degC) for a silicone ``delta_k`` kelvin above 25 degC."""
    return 1.0 + STIFFNESS_TEMPCO_PER_K * delta_k
