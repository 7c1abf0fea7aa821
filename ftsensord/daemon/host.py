"""What the host and its clients may take from the daemon, looked after between cycles:
the connections' caps (`connections.ConnectionCap`, drained while control is served),
the memory departed clients held, and the runtime folder's files (`runtime.RuntimeFiles`)."""

from __future__ import annotations

import ctypes
import time
from collections.abc import Callable, Sequence

from ftsensord.daemon.connections import ConnectionCap
from ftsensord.daemon.runtime import RuntimeFiles

#: After connections close, memory is given back this long after the last one (s): libzmq
#: frees a gone peer's queues in its I/O thread after the event, and a burst of closes
#: then costs one trim, not one each.
TRIM_AFTER_S = 1.0


class MemoryReturn:
    """Gives the heap's free pages back to the system once connections have closed.

    glibc keeps freed memory in its arenas (libzmq's I/O thread has its own), so the
    queues of clients gone stay in the RSS until malloc_trim; a daemon under MemoryMax
    must give back what departed clients held. Without glibc (musl), nothing to do.
    """

    def __init__(self, caps: list[ConnectionCap], clock: Callable[[], float]):
        self.caps, self.clock = caps, clock
        self._left = 0
        self._since: float | None = None
        try:
            self._trim: Callable[[int], int] | None = ctypes.CDLL(None).malloc_trim
        except AttributeError:
            self._trim = None

    def check(self) -> None:
        """Called between cycles, after the caps' `drain`."""
        left = sum(c.left for c in self.caps)
        now = self.clock()
        if left != self._left:
            self._left, self._since = left, now
        elif self._since is not None and now - self._since >= TRIM_AFTER_S:
            self._since = None
            if self._trim is not None:
                self._trim(0)


class HostGuard:
    """The caps, the memory and the runtime files of one daemon (none: a daemon in a test)."""

    def __init__(self, caps: Sequence[ConnectionCap] = (), runtime: RuntimeFiles | None = None):
        self.caps = list(caps)
        self.memory = MemoryReturn(self.caps, time.monotonic)  # real time: a trim's cost is real
        self.runtime = runtime

    def between_cycles(self) -> str | None:
        """Give memory back if due; returns why the daemon must exit (its files gone), or None."""
        self.memory.check()
        return self.runtime.lost() if self.runtime is not None else None
