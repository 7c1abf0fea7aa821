"""systemd's notify protocol, without a dependency: datagrams to $NOTIFY_SOCKET.

With ``Type=notify`` the daemon says ``READY=1`` once its first cycle has
published, ``WATCHDOG=1`` as cycles complete (at most every half of
$WATCHDOG_USEC, so a stuck loop stops the pings and systemd restarts it), and
``STATUS=...`` for ``systemctl status``. Outside systemd it does nothing.
Pings never come from anywhere but a completed cycle, so a rate too slow for
the watchdog is refused (`Notifier.check_rate`) rather than pinged between cycles.
"""

from __future__ import annotations

import os
import socket
import time

from ftsensord.errors import ConfigError


class Notifier:
    def __init__(self, environ: dict[str, str] | None = None, clock=time.monotonic):
        env = os.environ if environ is None else environ
        address = env.get("NOTIFY_SOCKET", "")
        # A leading "@" is Linux's abstract namespace, spelt with a NUL byte.
        self.address = "\0" + address[1:] if address.startswith("@") else address
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        mine = not pid or pid == str(os.getpid())
        self.watchdog_interval_s = int(usec) / 2e6 if usec.isdigit() and int(usec) > 0 and mine else None
        self.clock = clock
        self._last_ping = -float("inf")
        self._socket: socket.socket | None = None

    @property
    def enabled(self) -> bool:
        return bool(self.address)

    def notify(self, message: str) -> bool:
        """Send one notification; False when not under systemd or the send failed."""
        if not self.enabled:
            return False
        try:
            if self._socket is None:
                self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            # Non-blocking: a unix datagram queue holds only net.unix.max_dgram_qlen
            # (10) messages and then blocks the sender; a busy systemd must never
            # stall the loop, so a notification that finds the queue full is dropped.
            self._socket.sendto(message.encode(), socket.MSG_DONTWAIT, self.address)
        except OSError:
            return False  # systemd gone or its queue full: the service goes on regardless
        return True

    def ready(self, status: str = "") -> bool:
        return self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={text}")

    def watchdog(self) -> bool:
        """Ping the watchdog if it is due (call after every completed cycle)."""
        if self.watchdog_interval_s is None:
            return False
        now = self.clock()
        if now - self._last_ping < self.watchdog_interval_s:
            return False
        self._last_ping = now
        return self.notify("WATCHDOG=1")

    def check_rate(self, rate_hz: float, where: str = "rate_hz") -> None:
        """Refuse a loop rate whose period is longer than half the watchdog interval.

        Pings follow completed cycles only (a ping from anywhere else would keep a stuck
        loop alive), so a cycle must complete at least twice per WatchdogSec: one late
        cycle must not restart the service. Outside a watchdog, any rate goes."""
        if self.watchdog_interval_s is None:
            return
        watchdog_s = 2 * self.watchdog_interval_s
        if 1.0 / rate_hz > self.watchdog_interval_s:
            raise ConfigError(
                f"{where}: {rate_hz:g} Hz is a cycle every {1 / rate_hz:g} s, too slow for the "
                f"watchdog (WatchdogSec={watchdog_s:g} s wants a cycle at least every "
                f"{self.watchdog_interval_s:g} s): use at least {1 / self.watchdog_interval_s:g} Hz "
                "or raise WatchdogSec in the unit"
            )

    def stopping(self) -> bool:
        return self.notify("STOPPING=1")

    def reloading(self) -> bool:
        return self.notify("RELOADING=1")

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None
