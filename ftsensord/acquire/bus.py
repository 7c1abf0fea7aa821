"""Choose a bus by one string.

``i2c:N`` (or ``i2c:/dev/i2c-N``) opens the Linux I2C adapter with smbus2;
``sim`` opens the simulated bus with the default scene, ``sim:<scene file>``
with the named one. Whatever comes back has ``i2c_rdwr(*msgs)``, ``close()``,
``sleep(s)`` and ``monotonic()``, so nothing above this module knows which it
has.
"""

from __future__ import annotations

import time

from smbus2 import SMBus, i2c_msg

from ..chip.i2c import Bus
from ..errors import ConfigError

ACCEPTED_FORMS = "'i2c:<N>' (e.g. i2c:1), 'i2c:/dev/i2c-<N>', 'sim', or 'sim:<scene file>'"


class LinuxI2CBus:
    """``/dev/i2c-N`` through smbus2: only the combined transfer is used."""

    def __init__(self, device: int | str, smbus: SMBus | None = None):
        self.device = device
        self.smbus = smbus if smbus is not None else SMBus(device)

    def i2c_rdwr(self, *i2c_msgs: i2c_msg) -> None:
        self.smbus.i2c_rdwr(*i2c_msgs)

    def close(self) -> None:
        self.smbus.close()

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)

    def monotonic(self) -> float:
        return time.monotonic()

    def __repr__(self) -> str:
        return f"LinuxI2CBus({self.device!r})"


def parse_bus_spec(spec: str) -> tuple[str, str | None]:
    """Split a bus specification into (kind, argument); kind is 'i2c' or 'sim'."""
    if not isinstance(spec, str):
        raise ConfigError(f"bus: expected a string, one of {ACCEPTED_FORMS}; got {spec!r}")
    kind, sep, arg = spec.partition(":")
    if kind == "sim":
        if sep and not arg:
            raise ConfigError(f"bus {spec!r}: 'sim:' needs a scene file; accepted forms: {ACCEPTED_FORMS}")
        return "sim", arg or None
    if kind == "i2c" and arg:
        if arg.isdigit() or arg.startswith("/dev/"):
            return "i2c", arg
    raise ConfigError(f"bus {spec!r} is not understood; accepted forms: {ACCEPTED_FORMS}")


def open_bus(spec: str, **sim_options: object) -> Bus:
    """Open the bus ``spec`` names.

    ``sim_options`` go to `ftsensord.sim.simulated_bus` (clock, bus_hz, seed,
    noise) and are refused for a real bus. Raises `ConfigError` for a bad spec
    or scene file, ``OSError`` when the device cannot be opened.
    """
    kind, arg = parse_bus_spec(spec)
    if kind == "i2c":
        assert arg is not None  # parse_bus_spec gives i2c an argument
        if sim_options:
            raise ConfigError(f"bus {spec!r}: options {sorted(sim_options)} apply to the simulated bus only")
        return LinuxI2CBus(int(arg) if arg.isdigit() else arg)
    from .. import sim  # the simulator is only imported when asked for

    scene = sim.load_scene(arg) if arg else sim.default_scene()
    return sim.simulated_bus(scene, **sim_options)  # type: ignore[arg-type]
