"""Know the board: the adapter's driver, its configured clock, and what the bus really costs.

The configured clock comes from the device tree where the kernel exposes it
(``/sys/class/i2c-adapter/i2c-N/of_node/clock-frequency``, 4 bytes big-endian),
the driver from ``.../device/driver`` (or the adapter's ``name``). The cost of
one ioctl and the clock the wire really runs at are measured by timing two
known transfers to one chip (`measure_bus`): a short one, and one with many
more bytes; the difference is wire time alone. A simulated bus has the same
measurable costs, so all of this is tested without a board.

On a Raspberry Pi 0-4 the I2C clock is divided from the core clock, which
drops under load unless fixed, so the measured clock can be below the
configured one (250 kHz measured for 400 kHz set has been reported): `BoardReport`
then warns, naming the figure and the fix.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass, field
from pathlib import Path

from ftsensord.acquire.bus import parse_bus
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.i2c import I2C_RDWR_MAX_MSGS, Bus, BusTiming, wire_bits

#: Where the kernel lists I2C adapters.
SYSFS_I2C = Path("/sys/class/i2c-adapter")
#: A measured clock this far below the configured one is reported: a real bus loses a
#: little to the time between messages (start and stop setup, the driver refilling its
#: FIFO), which the measurement counts as a slower clock; a core clock that dropped
#: loses 20 % or more (250 MHz to 200 MHz on a Pi 4, 400 to 250 MHz on a Pi 3).
CLOCK_TOLERANCE = 0.10
#: Driver (or adapter) names and the rules they follow (`chip.i2c.ADAPTER_RULES`).
DRIVER_KINDS = (
    ("bcm2835", "bcm2835"),
    ("designware", "designware"),
    ("dw_i2c", "designware"),
    ("dw-i2c", "designware"),
)


def adapter_kind(name: str | None) -> str | None:
    """The `ADAPTER_RULES` name for a driver or adapter name; None: unknown."""
    low = (name or "").lower()
    return next((kind for key, kind in DRIVER_KINDS if key in low), None)


@dataclass(frozen=True)
class SysfsAdapter:
    """What the kernel says of /dev/i2c-N without touching the bus."""

    number: int
    driver: str | None  # e.g. "i2c-bcm2835", or the adapter's name when no driver link
    configured_hz: float | None  # the device tree's clock-frequency

    @classmethod
    def read(cls, number: int, root: Path = SYSFS_I2C) -> SysfsAdapter:
        folder = root / f"i2c-{number}"
        driver = None
        link = folder / "device" / "driver"
        try:
            driver = link.resolve(strict=True).name
        except OSError:
            try:
                driver = (folder / "name").read_text().strip() or None
            except OSError:
                driver = None
        configured = None
        try:
            raw = (folder / "of_node" / "clock-frequency").read_bytes()
            if len(raw) == 4:  # one big-endian u32 cell, as the device tree stores it
                configured = float(int.from_bytes(raw, "big"))
        except OSError:
            configured = None
        return cls(number, driver, configured)

    @property
    def adapter(self) -> str | None:
        return adapter_kind(self.driver)


def bus_timing(spec: str, root: Path = SYSFS_I2C) -> BusTiming:
    """What is known of a bus before it is opened: a simulated board's options, or
    a real adapter's rules from its driver's name (costs unknown until measured)."""
    parsed = parse_bus(spec)
    if parsed.kind == "sim":
        return parsed.timing
    assert parsed.arg is not None
    tail = parsed.arg.rsplit("-", 1)[-1]
    if not tail.isdigit():
        return BusTiming()
    return BusTiming(SysfsAdapter.read(int(tail), root).adapter)


@dataclass(frozen=True)
class Measured:
    """The bus's measured costs: one ioctl (s) and the wire's clock (Hz)."""

    ioctl_s: float
    clock_hz: float


#: RR of TREF: harmless in every mode.
RR_TREF = bytes([mlx.CMD_RR, mlx.REG_TREF << 2])


def measure_bus(bus: Bus, address: int, repeats: int = 21) -> Measured:
    """Time a short and a long transfer to the chip at ``address``; their medians'
    difference is wire time alone (known bits), the rest the ioctl's fixed cost.

    Short: RR of TREF (write 2 bytes, read 3). Long: the same with 40 more RR
    writes before the read: only writes then one read to one address, which
    every adapter takes. The median over ``repeats`` rejects the scheduler's
    odd late wake-up. Raises ``OSError`` when the chip does not answer.
    """
    from smbus2 import i2c_msg

    def timed(n_writes: int) -> tuple[float, int]:
        times = []
        for _ in range(repeats):
            msgs = [i2c_msg.write(address, RR_TREF) for _ in range(n_writes)] + [i2c_msg.read(address, 3)]
            t0 = bus.monotonic()
            bus.i2c_rdwr(*msgs)
            times.append(bus.monotonic() - t0)
        return statistics.median(times), wire_bits(msgs)

    short_s, short_bits = timed(1)
    long_s, long_bits = timed(I2C_RDWR_MAX_MSGS - 1)
    if long_s <= short_s:
        raise ValueError("the long transfer took no longer than the short one: the bus spends no time")
    clock_hz = (long_bits - short_bits) / (long_s - short_s)
    return Measured(max(0.0, short_s - short_bits / clock_hz), clock_hz)


@dataclass
class BoardReport:
    """What is known of the board: driver and rules, configured and measured figures, warnings."""

    driver: str | None
    adapter: str | None
    configured_hz: float | None  # what the kernel was told (device tree), None: not exposed
    wanted_hz: float  # what ftsensord's configuration asks (bus_hz)
    measured: Measured | None
    warnings: list[str] = field(default_factory=list)

    @property
    def timing(self) -> BusTiming:
        m = self.measured
        return BusTiming(self.adapter, None if m is None else m.ioctl_s, None if m is None else m.clock_hz)

    def check(self) -> None:
        """Warn where the clock is below what was asked, naming the figure and the fix."""
        self.warnings.clear()
        if self.configured_hz is not None and self.configured_hz < self.wanted_hz * (1 - CLOCK_TOLERANCE):
            self.warnings.append(
                f"the kernel runs this I2C adapter at {self.configured_hz / 1e3:.0f} kHz (device tree "
                f"clock-frequency) where {self.wanted_hz / 1e3:.0f} kHz is configured: on a Raspberry Pi add "
                f"dtparam=i2c_arm_baudrate={self.wanted_hz:.0f} to config.txt and reboot"
            )
        expected = self.configured_hz or self.wanted_hz
        m = self.measured
        if m is not None and m.clock_hz < expected * (1 - CLOCK_TOLERANCE):
            self.warnings.append(
                f"the I2C clock measures {m.clock_hz / 1e3:.0f} kHz where {expected / 1e3:.0f} kHz is set: on a "
                "Raspberry Pi 0-4 it is divided from the core clock, which drops under load; fix the core "
                "clock in config.txt (core_freq_min equal to core_freq, e.g. core_freq=500 and "
                "core_freq_min=500 on a Pi 4, or force_turbo=1). The bound uses the measured clock"
            )


def know_board(bus: Bus, address: int | None, wanted_hz: float, root: Path = SYSFS_I2C) -> BoardReport:
    """Driver, configured clock and measured costs of ``bus``; measured through the
    chip at ``address`` (None: not measured). A `LinuxI2CBus` keeps the measured
    timing (``bus.timing``) for the reader and the bound."""
    number = getattr(bus, "number", None)
    if number is not None:  # a real adapter: ask the kernel
        sysfs = SysfsAdapter.read(number, root)
        driver, adapter, configured = sysfs.driver, sysfs.adapter, sysfs.configured_hz
    else:  # a simulated board: it says what it stands for
        timing = getattr(bus, "timing", BusTiming())
        driver, adapter = timing.adapter, timing.adapter
        configured = getattr(bus, "bus_hz", None)
    measured = None
    if address is not None:
        try:
            measured = measure_bus(bus, address)
        except (OSError, ValueError):
            measured = None
    report = BoardReport(driver, adapter, configured, wanted_hz, measured)
    report.check()
    if number is not None and measured is not None:
        bus.timing = report.timing  # type: ignore[attr-defined]
    return report
