"""The project's exceptions: one root, small leaves.

Every leaf also subclasses the built-in a caller would naturally catch
(``ValueError`` for bad input, ``OSError`` for a device that misbehaves), so
code that knows nothing of ftsensord still handles them sensibly.
"""

from __future__ import annotations


class FtsensordError(Exception):
    """Root of every error ftsensord raises on purpose."""


class ConfigError(FtsensordError, ValueError):
    """A setting, specification or file is not acceptable.

    The message names what was wrong and what was expected.
    """


class ForbiddenSettingError(ConfigError):
    """A chip setting the MLX90393 datasheet does not permit (e.g. OSR 0, DIG_FILT 0)."""


class ChipError(FtsensordError, OSError):
    """An MLX90393 (or another ``device`` on the bus: an IMU) did not do what was asked.
    ``address`` is its 7-bit I2C address."""

    def __init__(self, address: int, message: str, *, device: str = "MLX90393"):
        super().__init__(f"{device} at 0x{address:02X}: {message}")
        self.address = address


class ChipNotRespondingError(ChipError):
    """The bus transaction failed (NACK, bus I/O error): the chip did not answer.

    ``errno`` carries the kernel's errno from the underlying ``OSError``.
    """

    def __init__(self, address: int, message: str, errno: int | None = None, *, device: str = "MLX90393"):
        super().__init__(address, message, device=device)
        self.errno = errno


class ChipRefusedError(ChipError):
    """The chip answered with ERROR set in its status byte: the command was refused.

    ``status`` is the decoded status byte, ``command`` the refused command's name
    (an "RM" refused means no new data; anything else, a chip in the wrong state).
    """

    def __init__(self, address: int, message: str, status: object, command: str = ""):
        super().__init__(address, message)
        self.status = status
        self.command = command


class ChipProtocolError(ChipError):
    """The chip's reply is inconsistent (byte count against D1:D0, a mode bit missing)."""


class RegisterVerifyError(ChipError):
    """A register read back differs from the value just written."""


class CalibrationError(FtsensordError, ValueError):
    """A dataset cannot give a trustworthy calibration; the message says what
    is missing and what to add to the calibration plan."""


class WireError(FtsensordError, ValueError):
    """A published frame that is not an ftsensord sample of this version."""


class DaemonNotAnswering(FtsensordError, TimeoutError):
    """No daemon answered on the control endpoint in time."""


class ControlError(FtsensordError, RuntimeError):
    """The daemon answered a control request with an error."""
