"""A chip configuration (`Settings`) field by field, checked against the datasheet, to and
from register values."""

from __future__ import annotations

from dataclasses import dataclass

from ftsensord.chip.mlx90393.conversion import RawFormat, raw_format, sensitivity_ut
from ftsensord.chip.mlx90393.protocol import (
    BURST_DATA_RATE,
    BURST_SEL,
    DIG_FILT,
    GAIN_SEL,
    HALLCONF,
    OSR,
    OSR2,
    POWER_ON_DEFAULTS,
    REG_CONF1,
    REG_CONF2,
    REG_CONF3,
    RES_X,
    RES_Y,
    RES_Z,
    TCMP_EN,
    ZYXT_XYZ,
)
from ftsensord.chip.mlx90393.timing import (
    FORBIDDEN_OSR_DIG_FILT,
    burst_interval_us,
    noise_ut,
    single_measurement_us,
    tconvm_us,
)
from ftsensord.errors import ForbiddenSettingError


# --- Settings ------------------------------------------------------------------
@dataclass(frozen=True)
class Settings:
    """A chip configuration, field by field (datasheet names, lower case).

    The defaults are the paper's choice: GAIN_SEL 0 and RES 3 (the widest range,
    6.009 / 9.680 uT/LSB), OSR 1 with DIG_FILT 2 (TCONVM 835 us).
    """

    gain_sel: int = 0
    hallconf: int = 0xC
    res_x: int = 3
    res_y: int = 3
    res_z: int = 3
    osr: int = 1
    dig_filt: int = 2
    osr2: int = 0
    tcmp_en: bool = False
    burst_sel: int = ZYXT_XYZ
    burst_data_rate: int = 0

    def validate(self) -> Settings:
        """Raise `ForbiddenSettingError` (or ValueError for a value out of range); return self."""
        for field, value in (
            (GAIN_SEL, self.gain_sel),
            (HALLCONF, self.hallconf),
            (RES_X, self.res_x),
            (RES_Y, self.res_y),
            (RES_Z, self.res_z),
            (OSR, self.osr),
            (DIG_FILT, self.dig_filt),
            (OSR2, self.osr2),
            (BURST_SEL, self.burst_sel),
            (BURST_DATA_RATE, self.burst_data_rate),
        ):
            if not isinstance(value, int) or not 0 <= value <= field.max:
                raise ForbiddenSettingError(f"{field.name} takes 0..{field.max}, got {value!r}")
        if self.hallconf not in (0x0, 0xC):
            raise ForbiddenSettingError(
                f"HALLCONF 0x{self.hallconf:X} is not supported: use 0xC (default) or 0x0"
            )
        if self.hallconf == 0xC and (self.osr, self.dig_filt) in FORBIDDEN_OSR_DIG_FILT:
            raise ForbiddenSettingError(
                f"OSR {self.osr} with DIG_FILT {self.dig_filt} is not permitted at HALLCONF 0xC "
                f"(forbidden: {sorted(FORBIDDEN_OSR_DIG_FILT)}); raise OSR or DIG_FILT"
            )
        if self.tcmp_en and max(self.res_x, self.res_y, self.res_z) >= 2:
            raise ForbiddenSettingError("TCMP_EN = 1 allows only RES 0 and 1 on every axis")
        return self

    def res(self, axis: str) -> int:
        return {"x": self.res_x, "y": self.res_y, "z": self.res_z}[axis]

    def sensitivity_ut(self, axis: str) -> float:
        return sensitivity_ut(self.gain_sel, self.res(axis), axis, self.hallconf)

    def raw_format(self, axis: str) -> RawFormat:
        return raw_format(self.res(axis), self.tcmp_en)

    def noise_ut(self, axis: str) -> float:
        """RMS reading noise of one axis, uT (an estimate: `noise_ut`)."""
        return noise_ut(axis, self.tconvm_us())

    def tconvm_us(self) -> float:
        return tconvm_us(self.osr, self.dig_filt)

    @property
    def conversion(self) -> str:
        """The conversion's settings as a person reads them: "OSR 1, DIG_FILT 2"."""
        return f"OSR {self.osr}, DIG_FILT {self.dig_filt}"

    def single_measurement_us(self, zyxt: int = ZYXT_XYZ) -> float:
        return single_measurement_us(zyxt, self.osr, self.dig_filt, self.osr2)

    def burst_interval_us(self, zyxt: int | None = None) -> float:
        return burst_interval_us(
            self.burst_sel if zyxt is None else zyxt, self.osr, self.dig_filt, self.osr2, self.burst_data_rate
        )

    def to_registers(self, current: dict[int, int] | None = None) -> dict[int, int]:
        """Register words for CONF1..CONF3, keeping other bits of ``current`` as read."""
        current = current or {}
        conf1 = current.get(REG_CONF1, POWER_ON_DEFAULTS[REG_CONF1])
        conf2 = current.get(REG_CONF2, 0)
        conf3 = current.get(REG_CONF3, 0)
        conf1 = HALLCONF.set(GAIN_SEL.set(conf1, self.gain_sel), self.hallconf)
        conf2 = TCMP_EN.set(conf2, int(self.tcmp_en))
        conf2 = BURST_SEL.set(conf2, self.burst_sel)
        conf2 = BURST_DATA_RATE.set(conf2, self.burst_data_rate)
        for field, value in (
            (OSR2, self.osr2),
            (RES_Z, self.res_z),
            (RES_Y, self.res_y),
            (RES_X, self.res_x),
            (DIG_FILT, self.dig_filt),
            (OSR, self.osr),
        ):
            conf3 = field.set(conf3, value)
        return {REG_CONF1: conf1, REG_CONF2: conf2, REG_CONF3: conf3}

    @classmethod
    def from_registers(cls, regs: dict[int, int]) -> Settings:
        """Decode CONF1..CONF3 (not validated: the chip may hold anything)."""
        c1, c2, c3 = regs[REG_CONF1], regs[REG_CONF2], regs[REG_CONF3]
        return cls(
            gain_sel=GAIN_SEL.get(c1),
            hallconf=HALLCONF.get(c1),
            res_x=RES_X.get(c3),
            res_y=RES_Y.get(c3),
            res_z=RES_Z.get(c3),
            osr=OSR.get(c3),
            dig_filt=DIG_FILT.get(c3),
            osr2=OSR2.get(c3),
            tcmp_en=bool(TCMP_EN.get(c2)),
            burst_sel=BURST_SEL.get(c2),
            burst_data_rate=BURST_DATA_RATE.get(c2),
        )
