"""What an emulated MLX90393's conversion reads: the scene's field, saturated, drifted,
noisy, quantised and coded as the chip's registers say (`Conversions`, a part of
`chip.EmulatedMLX90393` kept apart so that each class stays readable), and the reading
noise (`NoiseModel`)."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ftsensord.chip import mlx90393 as mlx
from ftsensord.sim.heat import ChipDrift


class FieldSource(Protocol):
    """What the chips need of a scene: the field each sees and its temperature."""

    @property
    def addresses(self) -> tuple[int, ...]:
        """The chip addresses the scene has a field for."""
        ...

    def field_t(self, address: int, t: float) -> np.ndarray:
        """Flux density at the chip, in tesla, in the chip's frame, at time ``t`` (s)."""
        ...

    def temperature_c(self, address: int, t: float) -> float:
        """Die temperature in degC at time ``t`` (s)."""
        ...


@dataclass(frozen=True)
class NoiseModel:
    """Reading noise: ``sigma = sigma_ref * sqrt(t_ref / TCONVM)`` per axis, Z noisier.

    The defaults are the estimate in `ftsensord.mlx90393` (`mlx.noise_ut`);
    a scene may scale them.
    """

    sigma_ref_xy_ut: float = mlx.NOISE_REF_XY_UT
    t_ref_us: float = mlx.NOISE_REF_TCONVM_US
    z_factor: float = mlx.NOISE_Z_FACTOR
    temperature_sigma_c: float = 0.05

    def sigma_ut(self, axis: str, tconvm_us: float) -> float:
        sigma = self.sigma_ref_xy_ut * math.sqrt(self.t_ref_us / tconvm_us)
        return sigma * self.z_factor if axis == "z" else sigma


NOISELESS = NoiseModel(sigma_ref_xy_ut=0.0, temperature_sigma_c=0.0)


class Conversions:
    """The conversion and RM reply of `chip.EmulatedMLX90393`."""

    address: int
    scene: FieldSource
    drift: ChipDrift | None
    noise: NoiseModel
    rng: np.random.Generator
    tref: int
    registers: list[int]
    _conv_setup: tuple[mlx.Settings, tuple[int, ...]] | None
    field_override: np.ndarray | None

    def settings(self) -> mlx.Settings:
        raise NotImplementedError

    def _status(self, *, error: bool = False, d: int | None = None, rs: bool = False) -> bytes:
        raise NotImplementedError

    def _reply_words(self, items: tuple[str, ...], words: dict[str, int]) -> bytes:
        out = bytearray(self._status(d=mlx.d_for_items(len(items))))
        for item in items:
            out += words[item].to_bytes(2, "big")
        return bytes(out)

    def _convert(self, t: float) -> dict[str, int]:
        """Quantised words of a conversion finishing at time ``t``, coded with the settings and
        OFFSET registers it started with (``_conv_setup``; None: the registers now)."""
        s, offsets = self._conv_setup or (self.settings(), tuple(self.registers[r] for r in mlx.REG_OFFSETS))
        field = (
            self.field_override
            if self.field_override is not None
            else np.asarray(self.scene.field_t(self.address, t), dtype=float)
        )
        temp = self.scene.temperature_c(self.address, t)
        if temp != mlx.TEMPERATURE_REF_C and self.drift is not None:  # at 25 degC nothing drifts
            # The element saturates first; its sensitivity and offset drift act on what it sees.
            field = self.drift.reading(
                np.clip(field, -mlx.HALL_SATURATION_T, mlx.HALL_SATURATION_T),
                temp - mlx.TEMPERATURE_REF_C,
                s.tcmp_en,
            )
        words: dict[str, int] = {}
        for i, (axis, sigma, sensitivity, fmt) in enumerate(_axes(s, self.noise)):
            # The Hall element saturates near 50 mT whatever the gain.
            b_ut = min(max(float(field[i]), -mlx.HALL_SATURATION_T), mlx.HALL_SATURATION_T) * 1e6
            if sigma > 0:
                b_ut += self.rng.normal(0.0, sigma)
            counts = round(b_ut / sensitivity)
            words[axis] = _tcmp_word(counts, offsets[i]) if s.tcmp_en else mlx.counts_to_raw(counts, fmt)
        if self.noise.temperature_sigma_c > 0:
            temp += self.rng.normal(0.0, self.noise.temperature_sigma_c)
        words["t"] = mlx.celsius_to_raw(temp, self.tref)
        return words


def _tcmp_word(counts: int, offset: int) -> int:
    """The word of ``counts`` with TCMP_EN on: referenced to the axis's OFFSET register,
    so zero field reads ``offset``; only at 0x8000 (`mlx.OFFSET_TCMP_ZERO`) is this the
    unsigned coding the decoder assumes. The chip's arithmetic past 16 bits is not
    documented: the counts clamp to the signed 16-bit range (as at 0x8000, where the word
    then clamps to 0..0xFFFF) and the sum wraps, so at the power-on OFFSET 0 every field
    decodes to nearly the full span with the wrong sign: garbage, flagged saturated only
    within a count of zero field, as users see on real chips (tedyapo/arduino-MLX90393
    issue 26, "strange results when temperature compensation enabled")."""
    return (max(-0x8000, min(0x7FFF, counts)) + offset) & 0xFFFF


@functools.lru_cache(maxsize=256)
def _axes(settings: mlx.Settings, noise: NoiseModel) -> tuple[tuple[str, float, float, mlx.RawFormat], ...]:
    """Per axis X, Y, Z at ``settings``: its noise (uT), uT per count and word coding."""
    return tuple(
        (a, noise.sigma_ut(a, settings.tconvm_us()), settings.sensitivity_ut(a), settings.raw_format(a))
        for a in "xyz"
    )
