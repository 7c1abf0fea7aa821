"""Scripted faults: what goes wrong on the simulated bus, and when.

A scene lists faults (``[[fault]]`` in its file); the simulated bus applies
them on its own clock (s since it was made) at the start of every transfer:

| kind | needs | while active |
|---|---|---|
| ``nack`` | address | the chip does not ACK |
| ``detach`` | address | the chip is gone; it comes back at power-on defaults |
| ``io_error`` | | every transfer fails with EIO (a bus-wide fault) |
| ``timeout`` | | every transfer fails with ETIMEDOUT (a hung bus) |
| ``stuck`` | address | the chip returns the same data forever |
| ``saturate`` | address, field_mt | the chip sees that field (mT, on every axis) |
| ``slow`` | factor | the wire is that many times slower than configured |
| ``drift_register`` | address, register, value | once, at ``at_s``: the register changes by itself |
"""

from __future__ import annotations

import errno
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ftsensord.sim.chip import EmulatedMLX90393


@dataclass
class BusFaults:
    """Faults the simulated bus injects; tests and scenes set them.

    ``nack_for[address]`` is how many more transfers touching that address are
    NACKed (None: until cleared, i.e. a permanent fault); ``io_errors`` is how
    many more transfers fail bus-wide with ``io_errno`` (EIO, or ETIMEDOUT for a
    hung bus); ``slowdown`` multiplies the wire time (a bus slower than
    configured: clock stretching, a longer cable, a lower real clock).
    """

    nack_for: dict[int, int | None] = field(default_factory=dict)
    io_errors: int = 0
    io_errno: int = errno.EIO
    slowdown: float = 1.0

    def nack(self, address: int, count: int | None = None) -> None:
        """NACK ``address`` for the next ``count`` transfers (None: until `clear`)."""
        self.nack_for[address] = count

    def io_error(self, count: int = 1, err: int = errno.EIO) -> None:
        """Fail the next ``count`` transfers bus-wide with ``err``."""
        self.io_errors, self.io_errno = count, err

    def clear(self) -> None:
        self.nack_for.clear()
        self.io_errors = 0
        self.slowdown = 1.0

    def take_nack(self, address: int) -> bool:
        """Whether this transfer to ``address`` is NACKed (counts one transfer)."""
        if address not in self.nack_for:
            return False
        remaining = self.nack_for[address]
        if remaining is not None:
            if remaining <= 1:
                del self.nack_for[address]
            else:
                self.nack_for[address] = remaining - 1
        return True


class FaultedBus(Protocol):
    """What a `FaultScript` acts on (`bus.SimulatedBus` is one): its chips by address, its
    bus-wide faults, and a chip taken off and put back."""

    chips: dict[int, EmulatedMLX90393]
    faults: BusFaults

    def detach(self, address: int) -> EmulatedMLX90393: ...

    def attach(self, chip: EmulatedMLX90393) -> None: ...


FAULT_KINDS = ("nack", "detach", "io_error", "timeout", "stuck", "saturate", "slow", "drift_register")
NEEDS_ADDRESS = {"nack", "detach", "stuck", "saturate", "drift_register"}


@dataclass
class Fault:
    kind: str
    at_s: float
    until_s: float = float("inf")
    address: int | None = None
    register: int = 0
    value: int = 0
    factor: float = 1.0
    field_mt: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"fault kind must be one of {FAULT_KINDS}, got {self.kind!r}")
        if self.kind in NEEDS_ADDRESS and self.address is None:
            raise ValueError(f"a {self.kind} fault needs an address")
        if self.until_s <= self.at_s and self.kind != "drift_register":
            raise ValueError(f"a {self.kind} fault must end after it starts")


class FaultScript:
    """Applies `Fault`s to a bus as its time passes; counts what it injected."""

    def __init__(self, faults: list[Fault]):
        self.faults = sorted(faults, key=lambda f: f.at_s)
        self.active: set[int] = set()
        self.detached: dict[int, EmulatedMLX90393] = {}
        self.injected = 0

    def apply(self, bus: FaultedBus, t: float) -> None:
        for i, f in enumerate(self.faults):
            on = f.at_s <= t < f.until_s
            if on and i not in self.active:
                self.active.add(i)
                self.injected += 1
                self._start(bus, f)
            elif not on and i in self.active:
                self.active.discard(i)
                self._end(bus, f)
            if on and f.kind in ("io_error", "timeout"):
                bus.faults.io_error(1, errno.EIO if f.kind == "io_error" else errno.ETIMEDOUT)

    def _chip(self, bus: FaultedBus, f: Fault) -> EmulatedMLX90393 | None:
        if f.address is None:
            return None
        return bus.chips.get(f.address) or self.detached.get(f.address)

    def _start(self, bus: FaultedBus, f: Fault) -> None:
        chip = self._chip(bus, f) if f.address is not None else None
        if f.kind == "nack":
            bus.faults.nack(f.address)  # type: ignore[arg-type]  # a nack names its chip (NEEDS_ADDRESS)
        elif f.kind == "detach" and f.address in bus.chips:
            self.detached[f.address] = bus.detach(f.address)
        elif f.kind == "stuck" and chip:
            chip.stuck = True
        elif f.kind == "saturate" and chip:
            chip.field_override = np.full(3, f.field_mt * 1e-3)
        elif f.kind == "slow":
            bus.faults.slowdown = f.factor
        elif f.kind == "drift_register" and chip:
            chip.registers[f.register] = f.value

    def _end(self, bus: FaultedBus, f: Fault) -> None:
        chip = self._chip(bus, f) if f.address is not None else None
        if f.kind == "nack":
            bus.faults.nack_for.pop(f.address, None)  # type: ignore[arg-type]  # as in _start
        elif f.kind == "detach" and f.address in self.detached:
            returning = self.detached.pop(f.address)
            returning.power_on()  # it lost power: back at its power-on registers
            bus.attach(returning)
        elif f.kind == "stuck" and chip:
            chip.stuck = False
        elif f.kind == "saturate" and chip:
            chip.field_override = None
        elif f.kind == "slow":
            bus.faults.slowdown = 1.0
        elif f.kind in ("io_error", "timeout"):
            bus.faults.io_errors = 0


def random_faults(
    addresses: list[int],
    duration_s: float,
    rng: np.random.Generator,
    *,
    per_minute: float = 6.0,
    mean_length_s: float = 3.0,
    start_s: float = 2.0,
) -> list[Fault]:
    """A random schedule for a soak: faults of every kind on random chips, one at a
    time on average ``per_minute``, each lasting about ``mean_length_s``."""
    faults: list[Fault] = []
    t = start_s
    if per_minute <= 0:
        return faults
    kinds = ("nack", "detach", "io_error", "timeout", "stuck", "saturate", "slow", "drift_register")
    while True:
        t += rng.exponential(60.0 / per_minute)
        if t >= duration_s:
            return faults
        kind = str(rng.choice(kinds))
        length = float(rng.exponential(mean_length_s)) + 0.05
        if kind in ("io_error", "timeout"):
            length = min(length, 0.2)  # a bus-wide glitch, not an outage
        address = int(rng.choice(addresses))
        faults.append(
            Fault(
                kind,
                t,
                t + length,
                address if kind in NEEDS_ADDRESS else None,
                register=2,
                value=0,
                factor=1.5,
                field_mt=60.0,
            )
        )
