"""Choose a bus by one string.

``i2c:N`` (or ``i2c:/dev/i2c-N``) opens the Linux I2C adapter with smbus2;
``sim`` opens the simulated bus with the default scene, ``sim:<scene file>``
with the named one. A simulated bus takes URL-style options for the board it
stands for: ``sim?adapter=bcm2835&ioctl_us=80&clock_hz=250000`` (`SIM_OPTIONS`;
the defaults are a Raspberry Pi 4's). Whatever comes back has
``i2c_rdwr(*msgs)``, ``close()``, ``sleep(s)`` and ``monotonic()``, so nothing
above this module knows which it has.

On a real bus the daemon takes an exclusive lock (``flock``) on the device, so
that a probing tool (``scan``, ``doctor``) refuses to disturb it unless forced.
"""

from __future__ import annotations

import fcntl
import logging
import math
import time
from dataclasses import dataclass, field

from smbus2 import SMBus, i2c_msg

from ftsensord.chip.i2c import ADAPTER_RULES, Bus, BusTiming
from ftsensord.errors import ConfigError, FtsensordError

log = logging.getLogger("ftsensord")

ACCEPTED_FORMS = (
    "'i2c:<N>' (e.g. i2c:1), 'i2c:/dev/i2c-<N>', 'sim', or 'sim:<scene file>'; "
    "a sim form may end in options '?adapter=permissive|bcm2835|designware&ioctl_us=<us>&clock_hz=<Hz>'"
)
#: The options of a simulated bus: what each accepts.
SIM_OPTIONS = {
    "adapter": " or ".join(ADAPTER_RULES),
    "ioctl_us": "a number of microseconds from 0 to 100000 (the fixed cost of one ioctl)",
    "clock_hz": "a number of Hz from 1000 to 3400000 (the clock the wire really runs at)",
}


class BusBusyError(FtsensordError, OSError):
    """Another process (a running daemon) holds the bus's lock."""


class BusUnavailableError(FtsensordError, OSError):
    """The I2C device is missing or not permitted: the message says how a board gets it."""


def _unavailable(path: str, exc: OSError) -> BusUnavailableError:
    """What to do about ``exc`` opening ``path``: the first thing a Pi user meets."""
    import glob

    if isinstance(exc, PermissionError):
        how = (
            "permission denied: add the user to the device's group (`sudo usermod -aG i2c $USER`, then "
            "log in again; the systemd unit has SupplementaryGroups=i2c)"
        )
    else:
        present = sorted(glob.glob("/dev/i2c-*"))
        how = (
            "it does not exist: I2C is off or the i2c-dev module is not loaded. On a Raspberry Pi: "
            "`sudo raspi-config nonint do_i2c 0` (or dtparam=i2c_arm=on in /boot/firmware/config.txt) and "
            "reboot; elsewhere `sudo modprobe i2c-dev` (and i2c-dev in /etc/modules). "
            + (f"Adapters here: {', '.join(present)}" if present else "No /dev/i2c-* exists here")
        )
    error = BusUnavailableError(f"{path}: {how}")  # not (errno, text): "[Errno 2]" helps no one here
    error.errno = exc.errno
    return error


@dataclass(frozen=True)
class BusSpec:
    """A parsed bus string: kind ('i2c' or 'sim'), its argument, and a simulated
    bus's board (`SIM_OPTIONS`: only those given are in ``options``)."""

    kind: str
    arg: str | None
    options: dict[str, object] = field(default_factory=dict)

    @property
    def timing(self) -> BusTiming:
        """What the string says of the board: a simulated bus's adapter, ioctl cost and
        wire clock (defaults: a Pi 4's, the configured clock); nothing for a real bus."""
        if self.kind != "sim":
            return BusTiming()
        from ftsensord.sim.bus import DEFAULT_ADAPTER, DEFAULT_IOCTL_S

        ioctl_us = self.options.get("ioctl_us")
        return BusTiming(
            str(self.options.get("adapter", DEFAULT_ADAPTER)),
            DEFAULT_IOCTL_S if ioctl_us is None else float(ioctl_us) * 1e-6,  # type: ignore[arg-type]
            self.options.get("clock_hz"),  # type: ignore[arg-type]
        )


class LinuxI2CBus:
    """``/dev/i2c-N`` through smbus2: only the combined transfer is used.

    ``exclusive``: take ``flock(LOCK_EX | LOCK_NB)`` on the device, refusing
    (`BusBusyError`) when another process holds it, unless ``force`` (then it
    goes on unlocked and says it will disturb the holder). ``timing`` is what
    `acquire.board` measured (None until then).
    """

    def __init__(
        self, device: int | str, smbus: SMBus | None = None, *, exclusive: bool = False, force: bool = False
    ):
        self.device = device
        try:
            self.smbus = smbus if smbus is not None else SMBus(device)
        except (FileNotFoundError, PermissionError) as exc:
            raise _unavailable(self.path, exc) from exc
        self.timing: BusTiming | None = None
        self.locked = False
        if exclusive:
            self._lock(force)

    def _lock(self, force: bool) -> None:
        try:
            assert self.smbus.fd is not None  # SMBus(device) opened it
            fcntl.flock(self.smbus.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            self.locked = True
        except BlockingIOError as exc:
            if not force:
                self.smbus.close()
                raise BusBusyError(
                    exc.errno,
                    f"{self.path} is in use by another process (a running ftsensord?): "
                    "stop it first, or pass --force to disturb it",
                ) from exc
            log.warning(
                "%s is in use by another process: going on unlocked (--force); "
                "its transfers and ours will interleave",
                self.path,
            )

    @property
    def path(self) -> str:
        return self.device if isinstance(self.device, str) else f"/dev/i2c-{self.device}"

    @property
    def number(self) -> int | None:
        """N of /dev/i2c-N (None when the path does not say)."""
        tail = self.path.rsplit("-", 1)[-1]
        return int(tail) if tail.isdigit() else None

    def i2c_rdwr(self, *i2c_msgs: i2c_msg) -> None:
        self.smbus.i2c_rdwr(*i2c_msgs)

    def close(self) -> None:
        self.smbus.close()  # closing the descriptor releases the lock

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)

    def monotonic(self) -> float:
        return time.monotonic()

    def __repr__(self) -> str:
        return f"LinuxI2CBus({self.device!r})"


def _option(spec: str, name: str, value: str) -> object:
    if name == "adapter":
        if value in ADAPTER_RULES:
            return value
    else:
        low, high = (0.0, 1e5) if name == "ioctl_us" else (1e3, 3.4e6)
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if low <= number <= high:  # NaN and inf fail here too
            return number
    raise ConfigError(f"bus {spec!r}: option {name}={value!r}: expected {SIM_OPTIONS[name]}")


def parse_bus(spec: str) -> BusSpec:
    """Parse a bus string (`ACCEPTED_FORMS`); raises `ConfigError` naming what is wrong."""
    if not isinstance(spec, str):
        raise ConfigError(f"bus: expected a string, one of {ACCEPTED_FORMS}; got {spec!r}")
    base, has_query, query = spec.partition("?")
    kind, sep, arg = base.partition(":")
    options: dict[str, object] = {}
    if has_query:
        if kind != "sim":
            raise ConfigError(
                f"bus {spec!r}: options apply to the simulated bus only; accepted forms: {ACCEPTED_FORMS}"
            )
        for item in query.split("&"):
            name, eq, value = item.partition("=")
            if name not in SIM_OPTIONS:
                raise ConfigError(
                    f"bus {spec!r}: unknown option {name!r}; accepted options: "
                    + "; ".join(f"{k} ({v})" for k, v in SIM_OPTIONS.items())
                )
            if not eq or name in options:
                raise ConfigError(f"bus {spec!r}: option {name} needs one value: {SIM_OPTIONS[name]}")
            options[name] = _option(spec, name, value)
    if kind == "sim":
        if sep and not arg:
            raise ConfigError(f"bus {spec!r}: 'sim:' needs a scene file; accepted forms: {ACCEPTED_FORMS}")
        return BusSpec("sim", arg or None, options)
    if kind == "i2c" and arg and (arg.isdigit() or arg.startswith("/dev/")):
        return BusSpec("i2c", arg)
    raise ConfigError(f"bus {spec!r} is not understood; accepted forms: {ACCEPTED_FORMS}")


def parse_bus_spec(spec: str) -> tuple[str, str | None]:
    """Split a bus specification into (kind, argument); kind is 'i2c' or 'sim'."""
    parsed = parse_bus(spec)
    return parsed.kind, parsed.arg


def open_bus(spec: str, *, exclusive: bool = False, force: bool = False, **sim_options: object) -> Bus:
    """Open the bus ``spec`` names.

    ``exclusive``/``force`` are for a real bus (`LinuxI2CBus`); a simulated
    bus has no other user. ``sim_options`` go to `ftsensord.sim.simulated_bus`
    (clock, bus_hz, seed, noise; the string's own options win over nothing:
    giving one both ways is refused) and are refused for a real bus. Raises
    `ConfigError` for a bad spec or scene file, `BusBusyError` when another
    process holds the bus, ``OSError`` when the device cannot be opened.
    """
    parsed = parse_bus(spec)
    if parsed.kind == "i2c":
        assert parsed.arg is not None  # parse_bus gives i2c an argument
        if sim_options:
            raise ConfigError(f"bus {spec!r}: options {sorted(sim_options)} apply to the simulated bus only")
        return LinuxI2CBus(
            int(parsed.arg) if parsed.arg.isdigit() else parsed.arg, exclusive=exclusive, force=force
        )
    from ftsensord import sim  # the simulator is only imported when asked for

    timing = parsed.timing
    board = {"adapter": timing.adapter, "ioctl_s": timing.ioctl_s, "clock_hz": timing.clock_hz}
    clash = sorted(set(board) & set(sim_options))
    if clash:
        raise ConfigError(f"bus {spec!r}: {clash} come from the bus string's options, not from arguments")
    scene = sim.load_scene(parsed.arg) if parsed.arg else sim.default_scene()
    return sim.simulated_bus(scene, **board, **sim_options)  # type: ignore[arg-type]
