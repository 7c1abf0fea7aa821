"""Reloads off the loop's critical path: the file work in a worker thread, the swap between cycles.

A reload reads the configuration and any changed calibration and builds new pipelines
(about 10 ms with two sensors, unchanged files included: the pipelines' precomputed
checks), a cycle at 100 Hz if the loop did it. `Reloads` does that work in a thread
of its own and hands the result to the loop, which swaps it in between two cycles
(`Daemon.apply_reload`, well under a millisecond). Requests that come while one runs
are answered together by the next, which starts after they were made (so it sees the
files as they left them), at most one every `RELOAD_EVERY_S`: a flood of reloads (SIGHUP
or control) costs the loop one swap and the worker one reload per interval.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from ftsensord.errors import FtsensordError

log = logging.getLogger("ftsensord")

#: Shortest time between two reloads' starts (s): a person editing a file reloads far less
#: often; a flood is served at twice a second.
RELOAD_EVERY_S = 0.5
#: How long the interpreter lets one thread run before another waiting for the GIL gets it
#: (s; Python's default is 5 ms): the loop thread must not wait half a period for the
#: worker's Python code. 0.5 ms costs the worker a few more switches, nothing to the loop.
SWITCH_INTERVAL_S = 0.5e-3


class Reloads:
    """Reload requests coalesced, prepared by ``prepare`` in a worker thread; ``finish``
    takes what it made, or the FtsensordError it raised, in the loop's thread (`poll`) and
    returns the reply each waiting client then gets by ``answer``. ``clock``: real time (s)."""

    def __init__(
        self,
        prepare: Callable[[], Any],
        finish: Callable[[Any], dict[str, Any]],
        answer: Callable[[list[bytes], dict[str, Any]], None],
        clock: Callable[[], float] = time.monotonic,
    ):
        self.prepare, self.finish, self.answer, self.clock = prepare, finish, answer, clock
        self.waiting: list[list[bytes] | None] = []  # envelopes (None: SIGHUP), for the next reload
        self.started_at = -float("inf")
        self._worker: threading.Thread | None = None
        self._batch: list[list[bytes] | None] = []
        self._outcome: Any = None
        self.done = 0
        sys.setswitchinterval(SWITCH_INTERVAL_S)

    def request(self, envelope: list[bytes] | None) -> None:
        """A reload asked by a client (its envelope) or by SIGHUP (None); answered by `poll`."""
        self.waiting.append(envelope)

    def poll(self) -> None:
        """Between cycles: apply a finished reload and answer its requests; start the next."""
        if self._worker is not None and not self._worker.is_alive():
            self._worker = None
            reply = self.finish(self._outcome)
            self.done += 1
            for envelope in self._batch:
                if envelope is not None:
                    self.answer(envelope, reply)
        if self._worker is None and self.waiting and self.clock() - self.started_at >= RELOAD_EVERY_S:
            self._batch, self.waiting = self.waiting, []
            self.started_at = self.clock()
            self._worker = threading.Thread(target=self._work, name="ftsensord-reload", daemon=True)
            self._worker.start()

    def wait(self, timeout_s: float | None = None) -> None:
        """Until the reload under way has finished its file work (tests; the loop never waits)."""
        if self._worker is not None:
            self._worker.join(timeout_s)

    def _work(self) -> None:
        try:
            self._outcome = self.prepare()
        except FtsensordError as exc:
            self._outcome = exc
        except Exception as exc:  # a bug must not leave the request unanswered: logged, said
            log.exception("reload failed")
            self._outcome = FtsensordError(f"internal error (logged by the daemon): {type(exc).__name__}")
