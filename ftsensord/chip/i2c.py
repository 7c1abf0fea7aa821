"""The I2C wire's facts and the surface every bus offers.

Bits per byte on the wire, the kernel's message limit per ``I2C_RDWR``, and
`Bus`: smbus2's ``i2c_rdwr`` plus time, which the driver, the simulator and
the schedulers are written against.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Protocol

from smbus2 import i2c_msg

#: The kernel's limit of messages in one I2C_RDWR ioctl (I2C_RDWR_IOCTL_MAX_MSGS).
I2C_RDWR_MAX_MSGS = 42
#: Bits on the wire per byte: 8 data bits and the ACK/NACK bit.
BITS_PER_BYTE = 9


def wire_bits(msgs: Iterable[i2c_msg]) -> int:
    """Clock bits a combined transfer takes: per message a (repeated) start, the
    address byte and the data bytes; one stop at the end."""
    return sum(1 + BITS_PER_BYTE * (1 + m.len) for m in msgs) + 1


class Bus(Protocol):
    """The surface every bus offers (smbus2's ``i2c_rdwr`` plus time, s)."""

    def i2c_rdwr(self, *i2c_msgs: i2c_msg) -> None: ...

    def close(self) -> None: ...

    def sleep(self, seconds: float) -> None: ...

    def monotonic(self) -> float: ...
