"""An emulated MPU-6050 (`chip.mpu6050`) fixed to a scene's sensor: its accelerometer reads
the specific force in the sensor's frame {0}, -g turned by the sensor's orientation in the
world at the moment of the read (the orientation a simulated person set down, seating error
and all), through the part's own zero-g offset and sensitivity, with the datasheet's noise.

Registers as the register map has them: the pointer set by a write's first byte, the bytes
after it written from there on, reads from the pointer on, auto-incrementing; PWR_MGMT_1
resets to SLEEP (the data registers then hold 0); WHO_AM_I reads 0x68. Only the accelerometer
is emulated: the gyroscope's and temperature registers read 0.
"""

from __future__ import annotations

import numpy as np

from ftsensord.chip import mpu6050 as mpu

#: Gravity's direction in the world (z up).
DOWN = np.array([0.0, 0.0, -1.0])


class EmulatedMPU6050:
    """The MPU-6050 at ``address``, its axes along {0} of ``sensor`` in ``scene`` (an object
    with ``orientation_of(sensor, t)`` giving R_w0). The part's zero-g offset (g) and
    sensitivity (a share, 1 = nominal) are drawn from ``rng`` within the datasheet's initial
    calibration tolerances unless given."""

    def __init__(
        self,
        address: int,
        scene: object,
        sensor: str,
        rng: np.random.Generator,
        *,
        offset_g: np.ndarray | None = None,
        sensitivity: np.ndarray | None = None,
    ):
        self.address, self.scene, self.sensor, self.rng = address, scene, sensor, rng
        zero_g = np.array(mpu.ZERO_G_MG) * 1e-3
        self.offset_g = (
            rng.uniform(-zero_g, zero_g) if offset_g is None else np.asarray(offset_g, dtype=float)
        )
        self.sensitivity = (
            1.0 + rng.uniform(-mpu.SENSITIVITY_TOLERANCE, mpu.SENSITIVITY_TOLERANCE, 3)
            if sensitivity is None
            else np.asarray(sensitivity, dtype=float)
        )
        self.power_on()

    def power_on(self) -> None:
        self.registers = bytearray(128)
        self.registers[mpu.PWR_MGMT_1] = mpu.PWR_MGMT_1_RESET
        self.registers[mpu.WHO_AM_I] = mpu.WHO_AM_I_VALUE
        self.pointer = 0

    def acks(self, now: float, reading: bool = False) -> bool:
        return True

    def write(self, data: bytes, now: float) -> None:
        if not data:
            return
        self.pointer = data[0] & 0x7F
        for value in data[1:]:
            if self.pointer == mpu.PWR_MGMT_1 and value & mpu.DEVICE_RESET:
                self.power_on()  # DEVICE_RESET: every register to its reset value, the bit clears itself
            elif self.pointer != mpu.WHO_AM_I:  # read-only
                self.registers[self.pointer] = value
            self.pointer = (self.pointer + 1) & 0x7F

    def read(self, length: int, now: float) -> bytes:
        self._sample(now)
        out = bytes(self.registers[(self.pointer + k) & 0x7F] for k in range(length))
        self.pointer = (self.pointer + length) & 0x7F
        return out

    def specific_force_g(self, now: float) -> np.ndarray:
        """What a perfect accelerometer reads at ``now`` (g, {0}): minus gravity's direction."""
        rotation = self.scene.orientation_of(self.sensor, now)  # type: ignore[attr-defined]
        return -(np.asarray(rotation).T @ DOWN)

    def _sample(self, now: float) -> None:
        """A fresh sample in ACCEL_*OUT each read (the reads are at least an output period
        apart), or 0 while asleep."""
        if self.registers[mpu.PWR_MGMT_1] & mpu.SLEEP:
            values = np.zeros(3)
        else:
            afs_sel = (self.registers[mpu.ACCEL_CONFIG] & mpu.AFS_SEL_MASK) >> mpu.AFS_SEL_SHIFT
            a = self.sensitivity * self.specific_force_g(now) + self.offset_g
            a = a + self.rng.normal(0.0, mpu.noise_g(), 3)
            values = np.clip(np.round(a * mpu.SENSITIVITY_LSB_PER_G[afs_sel]), -32768, 32767)
        for k, v in enumerate(values.astype(int)):
            self.registers[mpu.ACCEL_XOUT_H + 2 * k : mpu.ACCEL_XOUT_H + 2 * k + 2] = int(v).to_bytes(
                2, "big", signed=True
            )
