"""`set --accuracy` off the loop's critical path: the plan in a worker thread, applied between cycles.

Planning over every conversion of the chips (`processing.accuracy.plan`) takes a few tenths
of a second, tens of cycles at 100 Hz if the loop did it. `Plans` runs it in a thread of
its own (the interpreter's switch interval kept short, as `reloads.Reloads` sets it, so the
loop does not wait for the worker's Python code) and hands the plan to the loop, which
applies it between two cycles (writing a conversion to the chips: 36 ms for 16 chips on
the simulated 400 kHz bus, 48 ms in burst, which waits a conversion more) and answers the
request. One plan at a time: a request while one runs is refused at once.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from ftsensord.errors import FtsensordError

log = logging.getLogger("ftsensord")


class Plans:
    """One plan under way at most: ``work`` in a worker thread, ``finish`` of its outcome (or
    the FtsensordError it raised) in the loop's thread (`poll`), whose result, or the
    FtsensordError or ValueError it raises, ``answer`` sends to the request's envelope."""

    def __init__(self, answer: Callable[[list[bytes], dict[str, Any]], None]):
        self.answer = answer
        self._worker: threading.Thread | None = None
        self._envelope: list[bytes] = []
        self._finish: Callable[[Any], dict[str, Any]] = lambda outcome: {}
        self._outcome: Any = None

    def request(
        self, envelope: list[bytes], work: Callable[[], Any], finish: Callable[[Any], dict[str, Any]]
    ) -> None:
        """Start ``work``; ValueError when a plan is under way (the client asks again after its reply)."""
        if self._worker is not None:
            raise ValueError("accuracy: another is being planned: wait for its reply")
        self._envelope, self._finish, self._outcome = envelope, finish, None

        def run() -> None:
            try:
                self._outcome = work()
            except FtsensordError as exc:
                self._outcome = exc
            except Exception as exc:  # a bug must not leave the request unanswered: logged, said
                log.exception("accuracy planning failed")
                self._outcome = FtsensordError(f"internal error (logged by the daemon): {type(exc).__name__}")

        self._worker = threading.Thread(target=run, name="ftsensord-plan", daemon=True)
        self._worker.start()

    def poll(self) -> None:
        """Between cycles: apply a finished plan and answer its request."""
        if self._worker is None or self._worker.is_alive():
            return
        self._worker = None
        try:
            if isinstance(self._outcome, FtsensordError):
                raise self._outcome
            reply: dict[str, Any] = {"ok": True, "result": self._finish(self._outcome)}
        except (FtsensordError, ValueError) as exc:
            reply = {"ok": False, "error": str(exc)}
        except Exception:  # a bug must not stop the loop: log it, answer, go on (as `Control`)
            log.exception("applying an accuracy plan failed")
            reply = {"ok": False, "error": "internal error (logged by the daemon)"}
        self.answer(self._envelope, reply)

    def wait(self, timeout_s: float | None = None) -> None:
        """Until the plan under way is made (tests; the loop never waits)."""
        if self._worker is not None:
            self._worker.join(timeout_s)
