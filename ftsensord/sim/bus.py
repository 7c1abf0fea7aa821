"""A simulated I2C bus with smbus2's ``i2c_rdwr(*msgs)`` surface (and the SMBus byte and
block calls that public MLX90393 scripts use, carried out as the kernel does).

Like the kernel's ``I2C_RDWR`` ioctl it takes up to 42 messages in one call;
what else one call may hold is the adapter driver's rule (`ADAPTER_RULES`):
``permissive`` takes any mix of addresses and reads, ``bcm2835`` (the
Raspberry Pi 0-4, the default) only a read that is last, ``designware`` only
one address. A refused call raises ``OSError`` with the driver's errno. A
message to an address where no chip answers aborts the call with ``OSError``
(the messages before it have already happened on the wire, as on a real bus,
but as in i2c-dev no read buffer is filled). With a clock (``bus_hz``, or
``clock_hz`` where the wire really runs at another one) it spends per call a
fixed ``ioctl_s`` (the kernel's and the driver's work) and the wire time of
the transfer: 9 clock bits per byte (8 data + ACK) plus one for each start,
repeated start and the final stop.

Fault hooks (`BusFaults`, and the chips' own) let tests and scenes break it.
"""

from __future__ import annotations

import ctypes
import errno
from collections.abc import Iterable
from typing import Protocol

import numpy as np
from smbus2 import i2c_msg
from smbus2.smbus2 import I2C_M_RD, I2C_SMBUS_BLOCK_MAX

from ftsensord.chip.i2c import ADAPTER_RULES, BITS_PER_BYTE, I2C_RDWR_MAX_MSGS, BusTiming
from ftsensord.sim.chip import EmulatedMLX90393, FieldSource, NoiseModel
from ftsensord.sim.clock import MonotonicClock, VirtualClock
from ftsensord.sim.faults import BusFaults, FaultScript
from ftsensord.sim.imu import EmulatedMPU6050

#: Default adapter: the most likely board is a Raspberry Pi 4 with its own driver.
DEFAULT_ADAPTER = "bcm2835"
#: Default cost of one I2C_RDWR ioctl on a Pi 4 (s): syscall, copying the messages,
#: starting the controller, its interrupts and waking the caller. A Pi Zero (ARM11,
#: 1 GHz) was measured at 1.1 kHz doing write() then read() of 1 and 14 bytes at
#: 400 kHz (raspberrypi.stackexchange.com q. 109657): 909 us, of which 393 us on the
#: wire, so about 250 us a syscall; the Pi 4's Cortex-A72 runs such kernel paths about
#: 4x faster, hence 60 us. `acquire.board` measures it.
DEFAULT_IOCTL_S = 60e-6


class Device(Protocol):
    """What the bus needs of a device at an address (an `EmulatedMLX90393` is one)."""

    address: int

    def acks(self, now: float, reading: bool = False) -> bool: ...

    def read(self, length: int, now: float) -> bytes: ...

    def write(self, data: bytes, now: float) -> None: ...


class SimulatedBus:
    """Emulated MLX90393s on one bus, reached through ``i2c_rdwr``.

    ``clock`` is shared by every chip (a `VirtualClock` for tests, a
    `MonotonicClock` for benchmarks); ``bus_hz`` None spends no wire time.
    Chips and scenes see time since the bus was made (s), so a scene's
    "step at 1 s" means 1 s after start whatever the clock's origin.
    ``adapter`` names the driver's rules (`ADAPTER_RULES`); ``nack_errno`` is
    what it reports for an address nobody ACKs (None: the driver's own, the
    kernel's documented ENXIO for ``permissive``, EREMOTEIO for the others).
    ``clock_hz`` is the clock the wire really runs at (None: ``bus_hz``), what
    a Pi whose core clock drops under load gives. ``ioctl_s`` is spent per
    call, refused ones included, whenever the bus spends time at all.
    ``transfers`` counts calls, ``refused`` those the adapter refused.
    """

    def __init__(
        self,
        chips: Iterable[EmulatedMLX90393],
        *,
        clock: VirtualClock | MonotonicClock | None = None,
        bus_hz: float | None = None,
        nack_errno: int | None = None,
        script: FaultScript | None = None,
        adapter: str = DEFAULT_ADAPTER,
        ioctl_s: float = DEFAULT_IOCTL_S,
        clock_hz: float | None = None,
    ):
        if adapter not in ADAPTER_RULES:
            raise ValueError(f"adapter: expected one of {', '.join(ADAPTER_RULES)}, got {adapter!r}")
        self.chips: dict[int, EmulatedMLX90393] = {}
        #: Other devices on the bus (an IMU: `sim.imu`), reached the same way.
        self.devices: dict[int, Device] = {}
        for chip in chips:
            self.attach(chip)
        self.clock = clock if clock is not None else VirtualClock()
        self.epoch = self.clock.now()
        self.bus_hz = bus_hz
        self.clock_hz = clock_hz
        self.ioctl_s = ioctl_s
        self.rules = ADAPTER_RULES[adapter]
        self.nack_errno = self.rules.nack_errno if nack_errno is None else nack_errno
        self.faults = BusFaults()
        self.script = script
        self.transfers = 0
        self.refused = 0
        self.closed = False

    @property
    def adapter(self) -> str:
        return self.rules.name

    @property
    def wire_hz(self) -> float | None:
        """The clock the wire runs at (Hz), None for an ideal bus that spends no time."""
        return self.clock_hz if self.clock_hz is not None else self.bus_hz

    @property
    def timing(self) -> BusTiming:
        """What this bus really costs, as `acquire.board` would measure it on a board."""
        return BusTiming(self.adapter, self.ioctl_s if self.wire_hz is not None else 0.0, self.wire_hz)

    # --- the smbus2 surface ----------------------------------------------------
    def i2c_rdwr(self, *msgs: i2c_msg) -> None:
        """Run one combined transfer, like ``ioctl(fd, I2C_RDWR, ...)``."""
        if self.closed:
            raise OSError(errno.EBADF, "bus is closed")
        if not 1 <= len(msgs) <= I2C_RDWR_MAX_MSGS:
            raise OSError(errno.EINVAL, f"I2C_RDWR takes 1 to {I2C_RDWR_MAX_MSGS} messages, got {len(msgs)}")
        self.transfers += 1
        start = self.clock.now() - self.epoch
        if self.script is not None:
            self.script.apply(self, start)
        wire_hz = self.wire_hz
        bit_s = 0.0 if wire_hz is None else self.faults.slowdown / wire_hz
        # The kernel's fixed cost, spent before the first clock edge (syscall, setup).
        start += 0.0 if wire_hz is None else self.ioctl_s
        refusal = self.rules.refusal(msgs)
        if refusal is not None:
            self.refused += 1
            err, reached, words = refusal
            if reached == 0:  # refused before the bus is touched
                self.clock.wait_until(self.epoch + start)
                raise OSError(err, f"{self.adapter}: {words} ({errno.errorcode[err]})")
            msgs = msgs[:reached]  # designware: what was queued before the check ran goes out
        if self.faults.io_errors > 0:
            self.faults.io_errors -= 1
            err = self.faults.io_errno
            self.clock.wait_until(self.epoch + start)
            raise OSError(err, errno.errorcode.get(err, "I/O error"))
        bits = 0
        replies: list[tuple[i2c_msg, bytes]] = []
        try:
            for msg in msgs:
                bits += 1 + BITS_PER_BYTE  # (repeated) start and the address byte
                now = start + bits * bit_s
                chip: Device | None = self.chips.get(msg.addr) or self.devices.get(msg.addr)
                if (
                    chip is None
                    or self.faults.take_nack(msg.addr)
                    or not chip.acks(now, reading=bool(msg.flags & I2C_M_RD))
                ):
                    raise OSError(
                        self.nack_errno, f"no ACK from 0x{msg.addr:02X} ({errno.errorcode[self.nack_errno]})"
                    )
                bits += BITS_PER_BYTE * msg.len
                now = start + bits * bit_s
                if msg.flags & I2C_M_RD:
                    replies.append((msg, chip.read(msg.len, now)))
                else:
                    chip.write(bytes(msg), now)
            if refusal is not None:
                raise OSError(refusal[0], f"{self.adapter}: {refusal[2]} ({errno.errorcode[refusal[0]]})")
            # Like i2c-dev, read buffers are filled only when the whole transfer succeeded.
            for msg, data in replies:
                ctypes.memmove(msg.buf, data, msg.len)
        finally:
            self.clock.wait_until(self.epoch + start + (bits + 1) * bit_s)

    # --- smbus2's SMBus calls an MLX90393 script uses, as the kernel carries them out ----------
    # (I2C_SMBUS on an adapter without SMBus support: i2c_smbus_xfer_emulated's messages)
    def write_byte(self, i2c_addr: int, value: int, force: bool | None = None) -> None:
        self.i2c_rdwr(i2c_msg.write(i2c_addr, bytes([value])))

    def read_byte(self, i2c_addr: int, force: bool | None = None) -> int:
        read = i2c_msg.read(i2c_addr, 1)
        self.i2c_rdwr(read)
        return bytes(read)[0]

    def write_i2c_block_data(
        self, i2c_addr: int, register: int, data: list[int], force: bool | None = None
    ) -> None:
        if len(data) > I2C_SMBUS_BLOCK_MAX:
            raise ValueError(f"Data length cannot exceed {I2C_SMBUS_BLOCK_MAX} bytes")
        self.i2c_rdwr(i2c_msg.write(i2c_addr, bytes([register, *data])))

    def read_i2c_block_data(
        self, i2c_addr: int, register: int, length: int, force: bool | None = None
    ) -> list[int]:
        if length > I2C_SMBUS_BLOCK_MAX:
            raise ValueError(f"Desired block length over {I2C_SMBUS_BLOCK_MAX} bytes")
        write, read = i2c_msg.write(i2c_addr, bytes([register])), i2c_msg.read(i2c_addr, length)
        self.i2c_rdwr(write, read)  # repeated start, as the kernel's emulation
        return list(bytes(read))

    def close(self) -> None:
        self.closed = True

    def __enter__(self) -> SimulatedBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- time, shared with drivers ------------------------------------------------
    def sleep(self, seconds: float) -> None:
        self.clock.sleep(seconds)

    def monotonic(self) -> float:
        return self.clock.now()

    # --- chips coming and going -----------------------------------------------
    def attach(self, chip: EmulatedMLX90393) -> None:
        """Connect a chip (it answers from the next transfer on)."""
        if chip.address in self.chips:
            raise ValueError(f"address 0x{chip.address:02X} is already on the bus")
        self.chips[chip.address] = chip

    def attach_device(self, device: Device) -> None:
        """Connect another device (an IMU), answering from the next transfer on."""
        if device.address in self.chips or device.address in self.devices:
            raise ValueError(f"address 0x{device.address:02X} is already on the bus")
        self.devices[device.address] = device

    def detach(self, address: int) -> EmulatedMLX90393:
        """Disconnect a chip: its address NACKs until it is attached again.

        A chip that comes back after losing power should be ``power_on()``-ed
        before `attach`: it then holds its power-on registers, as a real one does.
        """
        return self.chips.pop(address)


def simulated_bus(
    scene: FieldSource,
    *,
    clock: VirtualClock | MonotonicClock | None = None,
    bus_hz: float | None = None,
    seed: int | None = 0,
    noise: NoiseModel = NoiseModel(),
    adapter: str = DEFAULT_ADAPTER,
    ioctl_s: float = DEFAULT_IOCTL_S,
    clock_hz: float | None = None,
) -> SimulatedBus:
    """A bus with one emulated chip per address of ``scene``, each drifting with its die
    temperature as the scene's part says (`PhysicalScene.chip_drift`; a static scene's do not).

    ``seed`` makes the chips' noise repeatable (None: fresh entropy); each chip
    gets its own stream, so adding a chip does not change another's noise.
    ``adapter``, ``ioctl_s`` (s per ioctl) and ``clock_hz`` (the wire's real
    clock, None: ``bus_hz``) are the board's (`SimulatedBus`); the defaults are
    a Raspberry Pi 4's.
    """
    addresses = scene.addresses
    streams = np.random.SeedSequence(seed).spawn(len(addresses))
    drift = getattr(scene, "chip_drift", None)  # a physical scene's parts drift with heat
    chips = [
        EmulatedMLX90393(
            address,
            scene,
            rng=np.random.default_rng(stream),
            noise=noise,
            drift=None if drift is None else drift(address),
        )
        for address, stream in zip(addresses, streams)
    ]
    faults = getattr(scene, "faults", [])
    bus = SimulatedBus(
        chips,
        clock=clock,
        bus_hz=bus_hz,
        script=FaultScript(faults) if faults else None,
        adapter=adapter,
        ioctl_s=ioctl_s,
        clock_hz=clock_hz,
    )
    # A sensor's IMU (`sim.imu`): its noise from streams after the chips' (theirs unchanged).
    imus = [(s.name, s.imu_address) for s in getattr(scene, "sensors", []) if s.imu_address is not None]
    more = np.random.SeedSequence(seed).spawn(len(addresses) + len(imus))[len(addresses) :]
    for (name, address), stream in zip(imus, more):
        bus.attach_device(EmulatedMPU6050(address, scene, name, np.random.default_rng(stream)))
    return bus
