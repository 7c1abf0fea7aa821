"""Scenes: what the emulated chips measure.

A scene gives, per chip address, the flux density in the chip's frame (T) and
the die temperature (degC) at any time. This module holds the simple static
scene (a given field per chip) and the scene file loader; the physical scene
(magnets, stiffness, loads) plugs in behind the same two methods.

Scene file (TOML)::

    version = 1
    kind = "static"
    temperature_c = 25.0          # optional default for every chip

    [[chip]]
    address = 0x0C
    field_ut = [0.0, 0.0, 1676.0] # uT, chip frame
    temperature_c = 26.0          # optional
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import mlx90393 as mlx
from ..errors import ConfigError

SCENE_VERSION = 1

#: mu_0 / (4 pi), in T m / A.
MU0_OVER_4PI = 1e-7

#: The paper's magnet, K&J D101-N52: 1/16" diameter, 1/32" thick, Br about 1.45 T.
D101_DIAMETER_M = 1.5875e-3
D101_THICKNESS_M = 0.79375e-3
D101_BR_T = 1.45
#: The magnet sits 6 mm from its chip along the chip's z axis (paper, III-B).
MAGNET_GAP_M = 6e-3


def d101_moment_am2() -> float:
    """Dipole moment of one D101-N52, m = Br V / mu_0, in A m^2."""
    volume = math.pi * (D101_DIAMETER_M / 2) ** 2 * D101_THICKNESS_M
    return D101_BR_T * volume / (4 * math.pi * MU0_OVER_4PI)


def on_axis_dipole_t(moment_am2: float, distance_m: float) -> float:
    """Field on a dipole's axis, B = (mu_0 / 4 pi) 2 m / r^3, in T."""
    return MU0_OVER_4PI * 2 * moment_am2 / distance_m**3


@dataclass
class StaticScene:
    """A fixed field (T, chip frame) and temperature (degC) per chip address.

    Tests change a chip's field with `set_field`; the change is seen by every
    conversion that finishes after it.
    """

    fields_t: dict[int, np.ndarray]
    temperatures_c: dict[int, float] = field(default_factory=dict)
    default_temperature_c: float = 25.0

    @property
    def addresses(self) -> tuple[int, ...]:
        return tuple(sorted(self.fields_t))

    def field_t(self, address: int, t: float) -> np.ndarray:
        return self.fields_t[address]

    def temperature_c(self, address: int, t: float) -> float:
        return self.temperatures_c.get(address, self.default_temperature_c)

    def set_field(self, address: int, field_t: np.ndarray | list[float]) -> None:
        self.fields_t[address] = np.asarray(field_t, dtype=float)


def default_scene() -> StaticScene:
    """Two sensors of 8 chips (0x0C-0x13 and 0x14-0x1B), each chip seeing its
    D101 magnet on its z axis at the nominal 6 mm gap, no load."""
    bz = on_axis_dipole_t(d101_moment_am2(), MAGNET_GAP_M)
    return StaticScene({a: np.array([0.0, 0.0, bz]) for a in range(mlx.ADDRESS_MIN, mlx.ADDRESS_MAX + 1)})


def _expect(cond: bool, path: Path, key: str, expected: str, got: Any) -> None:
    if not cond:
        raise ConfigError(f"{path}: {key}: expected {expected}, got {got!r}")


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def load_scene(path: str | Path) -> StaticScene:
    """Read a scene file; errors name the file, the key and what was expected."""
    path = Path(path)
    try:
        with path.open("rb") as f:
            doc = tomllib.load(f)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read scene file: {exc.strerror or exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    known = {"version", "kind", "temperature_c", "chip"}
    for key in doc:
        _expect(key in known, path, key, f"one of {sorted(known)}", key)
    _expect(doc.get("version") == SCENE_VERSION, path, "version", str(SCENE_VERSION), doc.get("version"))
    _expect(doc.get("kind") == "static", path, "kind", '"static"', doc.get("kind"))
    default_t = doc.get("temperature_c", 25.0)
    _expect(_number(default_t), path, "temperature_c", "a finite number (degC)", default_t)
    chips = doc.get("chip")
    _expect(isinstance(chips, list) and len(chips) > 0, path, "chip", "a non-empty array of [[chip]] tables", chips)
    fields: dict[int, np.ndarray] = {}
    temps: dict[int, float] = {}
    for i, chip in enumerate(chips):
        where = f"chip[{i}]"
        _expect(isinstance(chip, dict), path, where, "a table", chip)
        for key in chip:
            _expect(key in {"address", "field_ut", "temperature_c"}, path, f"{where}.{key}",
                    "one of address, field_ut, temperature_c", key)
        addr = chip.get("address")
        _expect(isinstance(addr, int) and not isinstance(addr, bool)
                and mlx.ADDRESS_MIN <= addr <= mlx.ADDRESS_MAX,
                path, f"{where}.address", "an address in 0x0C-0x1B", addr)
        _expect(addr not in fields, path, f"{where}.address", "an address not used before", addr)
        vec = chip.get("field_ut")
        _expect(isinstance(vec, list) and len(vec) == 3 and all(_number(v) for v in vec),
                path, f"{where}.field_ut", "3 finite numbers (uT, chip frame)", vec)
        fields[addr] = np.array(vec, dtype=float) * 1e-6
        if "temperature_c" in chip:
            _expect(_number(chip["temperature_c"]), path, f"{where}.temperature_c",
                    "a finite number (degC)", chip["temperature_c"])
            temps[addr] = float(chip["temperature_c"])
    return StaticScene(fields, temps, float(default_t))
