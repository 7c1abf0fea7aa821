"""`ftsensord guide` in a real terminal (a pseudo-terminal, as a person's shell gives it): the
prompts appear, one key records a step, Ctrl-C and q stop the run with the poses kept, and
the same command run again resumes and writes the calibration."""

from __future__ import annotations

import json
import os
import pty
import re
import select
import signal
import sys
import time
from pathlib import Path

import pytest

from ftsensord.calibration import fixture as fx

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="a pseudo-terminal needs fork (POSIX)")

#: How long a prompt may take to appear (s): a pose of 10 readings on the simulator, and the
#: interpreter's start, on a loaded 2-core machine; a hang fails the test, slowness does not.
PROMPT_WAIT_S = 120.0
PROMPT = "done? Enter to record, q to stop:"


class Terminal:
    """A command run in a pseudo-terminal: its output as the terminal shows it, keys typed."""

    def __init__(self, argv: list[str], cwd: Path):
        pid, fd = pty.fork()
        if pid == 0:  # the child: the pty is its controlling terminal (Ctrl-C reaches it)
            try:
                os.chdir(cwd)
                os.execv(sys.executable, [sys.executable, *argv])
            finally:
                os._exit(127)
        self.pid, self.fd, self.text, self.status = pid, fd, "", None

    def expect(self, pattern: str, timeout: float = PROMPT_WAIT_S, start: int = 0) -> re.Match[str]:
        """Read until ``pattern`` appears in the output past ``start``."""
        deadline = time.monotonic() + timeout
        while True:
            found = re.compile(pattern).search(self.text, start)
            if found:
                return found
            left = deadline - time.monotonic()
            if left <= 0 or not self._read(left):
                raise AssertionError(f"{pattern!r} not seen; the terminal showed:\n{self.text[-3000:]}")

    def _read(self, timeout: float) -> bool:
        ready, _, _ = select.select([self.fd], [], [], timeout)
        if not ready:
            return False
        try:
            chunk = os.read(self.fd, 4096)
        except OSError:  # EIO: the child closed the terminal
            return False
        self.text += chunk.decode(errors="replace").replace("\r\n", "\n")
        return bool(chunk)

    def type(self, keys: str) -> None:
        os.write(self.fd, keys.encode())

    def wait(self, timeout: float = PROMPT_WAIT_S) -> int:
        """The exit code, once the output is read to its end."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self._read(deadline - time.monotonic()):
            pass
        _, status = os.waitpid(self.pid, 0)
        os.close(self.fd)
        return os.waitstatus_to_exitcode(status)

    def prompts(self) -> int:
        return self.text.count(PROMPT)


def guide_argv(out: Path) -> list[str]:
    return [
        "-m",
        "ftsensord",
        "guide",
        "--sim",
        "--quick",
        "--linear-only",
        "--samples",
        "10",
        "-o",
        str(out),
    ]


def test_keys_stop_and_resume_in_a_terminal(tmp_path):
    out = tmp_path / "cal.json"
    progress = tmp_path / "cal.json.progress.json"
    steps = fx.guided_plan(every=2, no_load=8, validation=6)  # --quick's plan

    # A first run: the plan and the first step's prompt; one key (no Enter) records it, then
    # Ctrl-C at the third prompt stops the run with what was kept.
    term = Terminal(guide_argv(out), tmp_path)
    term.expect(rf"plan: {len(steps)} steps")
    term.expect(r"step 1: face 1 down, hook arm off\n.*" + re.escape(PROMPT))
    term.type(" ")
    at = term.expect(r"  kept\n").end()
    term.expect(r"step 2: .*\n.*" + re.escape(PROMPT), start=at)
    term.type("\r")
    at = term.expect(r"  kept\n", start=at).end()
    term.expect(re.escape(PROMPT), start=at)
    term.type("\x03")  # Ctrl-C, as the terminal's line discipline sends SIGINT
    term.expect(r"stopped: 2 of \d+ steps kept")
    assert term.wait() == 3
    assert "Traceback" not in term.text
    assert json.loads(progress.read_text())["kept"] == [0, 1]

    # Again: the run resumes at step 3; a key that means nothing is ignored; q stops it.
    term = Terminal(guide_argv(out), tmp_path)
    term.expect(rf"resuming: 2 of {len(steps)} steps kept")
    at = term.expect(r"step 3: .*\n.*" + re.escape(PROMPT)).end()
    assert "step 1:" not in term.text and "step 2:" not in term.text
    term.type("x")
    term.type("\r")
    at = term.expect(r"  kept\n", start=at).end()
    term.expect(re.escape(PROMPT), start=at)
    term.type("q")
    term.expect(r"stopped: 3 of \d+ steps kept")
    assert term.wait() == 3
    assert json.loads(progress.read_text())["kept"] == [0, 1, 2]
    assert not out.exists()

    # And once more: every step confirmed by a key until the calibration is written.
    term = Terminal(guide_argv(out), tmp_path)
    term.expect(rf"resuming: 3 of {len(steps)} steps kept")
    seen = 0
    while True:
        found = term.expect(re.escape(PROMPT) + "|" + r"wrote \S+cal\.json\n", start=seen)
        seen = found.end()
        if found.group(0).startswith("wrote"):
            break
        term.type("\r")
    assert term.wait() == 0
    assert term.prompts() >= len(steps) - 3  # one a step at least (a refused step is asked again)
    assert "expected accuracy (held-out 100 g poses)" in term.text
    report = json.loads(out.read_text())["fit_report"]
    assert report["guided"]["steps"] == len(steps)


def test_ctrl_c_while_reading_keeps_what_was_kept(tmp_path):
    # Ctrl-C while a pose is read (--yes: no prompt): the pose under way is dropped, those
    # before it kept; the progress file and the dataset agree (the run resumes).
    out = tmp_path / "cal.json"
    term = Terminal([*guide_argv(out), "--yes"], tmp_path)
    term.expect(r"step 3: ")
    os.kill(term.pid, signal.SIGINT)
    found = term.expect(r"stopped: (\d+) of \d+ steps kept")
    assert term.wait() == 3
    kept = json.loads((tmp_path / "cal.json.progress.json").read_text())["kept"]
    assert len(kept) == int(found.group(1)) >= 2
    from ftsensord.calibration.dataset import Dataset

    assert len(Dataset.load(tmp_path / "cal.json.poses.json")) == len(kept)
