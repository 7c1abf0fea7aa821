"""The MPU-6050's accelerometer: its facts and a driver (InvenSense PS-MPU-6000A-00 rev. 3.4,
"Product Specification", and RM-MPU-6000A-00 rev. 4.2, "Register Map and Descriptions").

An MPU-6050 on the sensor's bus, fixed to the printed holder, tells the guided calibration
which way gravity points at each pose instead of trusting the face the user was asked for.
Only the accelerometer is used. At rest it measures the specific force, -g: 1 g pointing up;
gravity's direction in its frame is minus the reading, normalised.

Registers (RM 4.2, section 3 and 4): ``WHO_AM_I`` (0x75) reads 0x68 whatever AD0 is;
``PWR_MGMT_1`` (0x6B) resets to 0x40, SLEEP set: the device must be woken; ``ACCEL_CONFIG``
(0x1C) bits 4:3 are AFS_SEL, the full scale (+-2/4/8/16 g); ``ACCEL_XOUT_H`` (0x3B) starts
ACCEL_XOUT, ACCEL_YOUT, ACCEL_ZOUT, each 16 bits, two's complement, high byte first; a
read auto-increments the register address. The 7-bit I2C address is 0b110100 and AD0:
0x68 or 0x69.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence

import numpy as np
from smbus2 import i2c_msg

from ftsensord.chip.i2c import Bus
from ftsensord.errors import ChipNotRespondingError, ChipProtocolError

DEVICE = "MPU-6050"
#: I2C addresses: AD0 low, AD0 high (PS 3.4, section 9.2).
ADDRESSES = (0x68, 0x69)
#: Register addresses (RM 4.2).
ACCEL_CONFIG = 0x1C
ACCEL_XOUT_H = 0x3B
PWR_MGMT_1 = 0x6B
WHO_AM_I = 0x75
#: WHO_AM_I's value: the upper 6 bits of the address, bit 0 reserved (0x68 with AD0 high too).
WHO_AM_I_VALUE = 0x68
#: PWR_MGMT_1 bits: DEVICE_RESET (bit 7), SLEEP (bit 6); its reset value is SLEEP alone.
DEVICE_RESET, SLEEP = 0x80, 0x40
PWR_MGMT_1_RESET = SLEEP
#: ACCEL_CONFIG's AFS_SEL field (bits 4:3).
AFS_SEL_SHIFT, AFS_SEL_MASK = 3, 0x18
#: Sensitivity scale factor by AFS_SEL (LSB/g; PS 3.4, section 6.2).
SENSITIVITY_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
#: PS 3.4, section 6.2: the sensitivity's initial calibration tolerance (+-3 %), cross-axis
#: sensitivity (+-2 %), zero-g output's initial calibration tolerance (mg: X, Y +-50, Z +-80),
#: the noise's power spectral density at AFS_SEL=0 (ug/sqrt(Hz)).
SENSITIVITY_TOLERANCE = 0.03
CROSS_AXIS = 0.02
ZERO_G_MG = (50.0, 50.0, 80.0)
NOISE_UG_PER_RTHZ = 400.0
#: The accelerometer's bandwidth with the digital low-pass filter off (DLPF_CFG = 0, RM 4.2
#: section 4.3): 260 Hz; with the noise density above, 6.4 mg RMS a reading.
BANDWIDTH_HZ = 260.0
#: The output data rate with the filter off (PS 3.4: the accelerometer's is 1 kHz).
ODR_HZ = 1000.0


def noise_g() -> float:
    """One reading's noise (g RMS, each axis), DLPF off: the density over the bandwidth."""
    return NOISE_UG_PER_RTHZ * 1e-6 * math.sqrt(BANDWIDTH_HZ)


class MPU6050:
    """One MPU-6050 at ``address`` on ``bus`` (smbus2's ``i2c_rdwr``; the simulator's too)."""

    def __init__(self, bus: Bus, address: int = ADDRESSES[0], afs_sel: int = 0):
        if address not in ADDRESSES:
            raise ValueError(f"address: expected 0x68 or 0x69, got 0x{address:02X}")
        if afs_sel not in range(4):
            raise ValueError(f"afs_sel: expected 0-3, got {afs_sel}")
        self.bus, self.address, self.afs_sel = bus, address, afs_sel

    def _read(self, register: int, length: int) -> bytes:
        write, read = i2c_msg.write(self.address, [register]), i2c_msg.read(self.address, length)
        try:
            self.bus.i2c_rdwr(write, read)
        except OSError as exc:
            raise ChipNotRespondingError(self.address, str(exc), exc.errno, device=DEVICE) from exc
        return bytes(read)

    def _write(self, register: int, value: int) -> None:
        try:
            self.bus.i2c_rdwr(i2c_msg.write(self.address, [register, value]))
        except OSError as exc:
            raise ChipNotRespondingError(self.address, str(exc), exc.errno, device=DEVICE) from exc

    def who_am_i(self) -> int:
        return self._read(WHO_AM_I, 1)[0]

    def start(self) -> None:
        """Check WHO_AM_I, wake the device (PWR_MGMT_1: SLEEP cleared, the internal 8 MHz
        oscillator) and set the full scale (ACCEL_CONFIG's AFS_SEL); both read back."""
        who = self.who_am_i()
        if who != WHO_AM_I_VALUE:
            raise ChipProtocolError(
                self.address,
                f"WHO_AM_I reads 0x{who:02X}, an MPU-6050's is 0x{WHO_AM_I_VALUE:02X}",
                device=DEVICE,
            )
        self._write(PWR_MGMT_1, 0x00)
        self._write(ACCEL_CONFIG, self.afs_sel << AFS_SEL_SHIFT)
        power, config = self._read(PWR_MGMT_1, 1)[0], self._read(ACCEL_CONFIG, 1)[0]
        if power & SLEEP or (config & AFS_SEL_MASK) >> AFS_SEL_SHIFT != self.afs_sel:
            raise ChipProtocolError(
                self.address,
                f"PWR_MGMT_1 0x{power:02X}, ACCEL_CONFIG 0x{config:02X} read back "
                f"(expected SLEEP clear and AFS_SEL {self.afs_sel})",
                device=DEVICE,
            )

    def read_accel_g(self) -> np.ndarray:
        """ACCEL_XOUT, ACCEL_YOUT, ACCEL_ZOUT (g, the device's axes): one burst read."""
        raw = struct.unpack(">hhh", self._read(ACCEL_XOUT_H, 6))
        return np.array(raw, dtype=float) / SENSITIVITY_LSB_PER_G[self.afs_sel]

    def mean_accel_g(self, samples: int) -> tuple[np.ndarray, np.ndarray]:
        """The mean of ``samples`` readings (g) and its standard error (g), one reading per
        output period (1/ODR, the bus's sleep between reads)."""
        readings = []
        for _ in range(samples):
            readings.append(self.read_accel_g())
            self.bus.sleep(1.0 / ODR_HZ)
        a = np.array(readings)
        sem = a.std(axis=0, ddof=1) / math.sqrt(samples) if samples > 1 else np.full(3, noise_g())
        return a.mean(axis=0), sem


def probe(bus: Bus, addresses: Sequence[int] = ADDRESSES) -> int | None:
    """The first of ``addresses`` where an MPU-6050 answers WHO_AM_I, or None (a scan)."""
    for address in addresses:
        try:
            if MPU6050(bus, address).who_am_i() == WHO_AM_I_VALUE:
                return address
        except ChipNotRespondingError:
            continue
    return None
