"""The I2C wire's facts and the surface every bus offers.

Bits per byte on the wire, the kernel's message limit per ``I2C_RDWR``, what
the Linux adapters accept in one ``I2C_RDWR`` (`ADAPTER_RULES`), a bus's
timing (`BusTiming`), and `Bus`: smbus2's ``i2c_rdwr`` plus time, which the
driver, the simulator and the schedulers are written against.
"""

from __future__ import annotations

import errno
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
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


#: Read flag of a message (linux/i2c.h I2C_M_RD).
I2C_M_RD = 0x0001


@dataclass(frozen=True)
class AdapterRules:
    """What one ``I2C_RDWR`` may hold on a Linux adapter driver.

    ``reads_last_only``: a read may only be the last message (i2c-bcm2835:
    ``-EOPNOTSUPP`` before the bus is touched). ``one_address``: every message
    to the address of the first (i2c-designware before multi-target support:
    ``-EINVAL`` when the driver reaches the first message to another address;
    the messages before it are already queued to the controller's FIFO).
    ``no_zero_len``: zero-length messages refused by the I2C core
    (``I2C_AQ_NO_ZERO_LEN``, ``-EOPNOTSUPP``). ``nack_errno``: what the driver
    reports for an address nobody ACKs.
    """

    name: str
    reads_last_only: bool = False
    one_address: bool = False
    no_zero_len: bool = False
    nack_errno: int = errno.ENXIO

    def refusal(self, msgs: Sequence[object]) -> tuple[int, int, str] | None:
        """None when the driver takes ``msgs`` (objects with ``addr``, ``flags``,
        ``len``); else (errno, how many leading messages still reach the wire,
        the driver's words)."""
        if self.no_zero_len and any(m.len == 0 for m in msgs):  # type: ignore[attr-defined]
            return errno.EOPNOTSUPP, 0, "adapter quirk: no zero length"
        if self.reads_last_only and any(m.flags & I2C_M_RD for m in msgs[:-1]):  # type: ignore[attr-defined]
            return errno.EOPNOTSUPP, 0, "only one read message supported, has to be last"
        if self.one_address:
            first = msgs[0].addr  # type: ignore[attr-defined]
            for k, m in enumerate(msgs):
                if m.addr != first:  # type: ignore[attr-defined]
                    return errno.EINVAL, k, "invalid target address"
        return None


#: The adapter drivers the simulator models, by the name used in bus strings.
ADAPTER_RULES = {
    "permissive": AdapterRules("permissive"),
    # drivers/i2c/busses/i2c-bcm2835.c: bcm2835_i2c_xfer() refuses a read that is not
    # last; a NACK sets BCM2835_I2C_S_ERR, returned as -EREMOTEIO.
    "bcm2835": AdapterRules("bcm2835", reads_last_only=True, nack_errno=errno.EREMOTEIO),
    # drivers/i2c/busses/i2c-designware-master.c: i2c_dw_xfer_msg() "invalid target
    # address"; i2c_dw_quirks = I2C_AQ_NO_ZERO_LEN; a NACK (TX abort NOACK) is -EREMOTEIO.
    "designware": AdapterRules("designware", one_address=True, no_zero_len=True, nack_errno=errno.EREMOTEIO),
}
#: Errnos that mean "the adapter does not take this shape of transfer" (never a NACK).
SHAPE_REFUSED = (errno.EOPNOTSUPP, errno.EINVAL)


@dataclass(frozen=True)
class BusTiming:
    """What a bus really costs: the adapter's rules (a name of `ADAPTER_RULES`,
    or None when unknown), the fixed cost of one ioctl (s) and the clock the
    wire runs at (Hz; None: unknown, trust the configured one)."""

    adapter: str | None = None
    ioctl_s: float | None = None
    clock_hz: float | None = None


class Bus(Protocol):
    """The surface every bus offers (smbus2's ``i2c_rdwr`` plus time, s)."""

    def i2c_rdwr(self, *i2c_msgs: i2c_msg) -> None: ...

    def close(self) -> None: ...

    def sleep(self, seconds: float) -> None: ...

    def monotonic(self) -> float: ...
