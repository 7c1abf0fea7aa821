"""The ROS 2 bridge beside the daemon: with ``[ros2] output = "bridge"``, `ftsensord run`
starts ``ftsensord ros2`` as a process of its own (by its command line: nothing of the
bridge is imported here), watches it, and stops it when the daemon stops."""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

from ftsensord.config.ros2conf import Ros2Config

log = logging.getLogger("ftsensord")
#: How long a stopped bridge may take to exit before it is killed (s): its DDS participant's
#: goodbye takes well under one.
BRIDGE_EXIT_S = 10.0

#: The bridge's forwarding thread's SCHED_FIFO priority under a real-time daemon: the lowest,
#: above every normal process (the subscribers it competes with on a busy host) and below the
#: loop and anything else made real-time (docs/results/performance.md, "ROS 2").
BRIDGE_FIFO = 1

#: prctl(2)'s PR_SET_PDEATHSIG: the signal the child gets when its parent dies.
PR_SET_PDEATHSIG = 1


def _child_setup() -> None:
    """In the child before exec: SIGTERM when the daemon dies (even by SIGKILL: no bridge left
    serving a dead daemon's name), and the default policy, not the real-time one the daemon
    has (``run --realtime``): DDS's own threads never compete with the loop (the forwarding
    thread alone asks for `BRIDGE_FIFO`, `bridge_command`)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass  # no prctl (not Linux): the daemon's own exit still stops the bridge
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        pass  # not lowered: the bridge then runs at the daemon's policy; nothing else changes


def bridge_command(config_path: Path, realtime: int) -> list[str]:
    """``ftsensord ros2 --config CONFIG``, with ``--realtime PRIORITY`` for its forwarding thread
    when ``realtime`` is not 0."""
    return [
        sys.executable,
        "-m",
        "ftsensord",
        "ros2",
        "--config",
        str(config_path),
        *(["--realtime", str(realtime)] if realtime else []),
    ]


def bridge_priority() -> int:
    """`BRIDGE_FIFO` when this process runs real-time above it, else 0 (the bridge at the
    daemon's normal priority: never above the loop)."""
    policy = os.sched_getscheduler(0)
    rt = policy in (os.SCHED_FIFO, os.SCHED_RR) and os.sched_getparam(0).sched_priority > BRIDGE_FIFO
    return BRIDGE_FIFO if rt else 0


@contextlib.contextmanager
def ros2_beside(ros2: Ros2Config | None, config_path: Path) -> Iterator[subprocess.Popen | None]:
    """With a ``[ros2]`` table whose output is ``"bridge"``, ``ftsensord ros2 --config CONFIG``
    as a child of the daemon at the default scheduling policy (its forwarding thread at
    `BRIDGE_FIFO` under a real-time daemon), stopped (SIGTERM) when the block ends; else
    nothing. Entered before the daemon has a thread (preexec_fn runs between fork and exec)."""
    if ros2 is None or ros2.output != "bridge":
        yield None
        return
    child = subprocess.Popen(bridge_command(config_path, bridge_priority()), preexec_fn=_child_setup)
    try:
        yield child
    finally:
        child.terminate()
        try:
            child.wait(timeout=BRIDGE_EXIT_S)
        except subprocess.TimeoutExpired:  # hung (stopped, or stuck in DDS): not left behind
            log.warning(
                "the ROS 2 bridge (pid %d) did not stop within %g s: killed", child.pid, BRIDGE_EXIT_S
            )
            child.kill()
            child.wait()


class BridgeWatch:
    """The bridge as the daemon sees it (None: no ``[ros2]``): `check`, once a second, logs its
    exit once (its ROS 2 topics, /diagnostics and tare stop; the ZeroMQ side goes on);
    `status` for the `status` reply."""

    def __init__(self, child: subprocess.Popen | None = None):
        self.child, self.reported = child, False

    def check(self) -> None:
        if self.child is None or self.reported or self.child.poll() is None:
            return
        self.reported = True
        log.warning(
            "the ROS 2 bridge (pid %d) exited with status %d: its topics, /diagnostics and the tare "
            "from ROS have stopped (the ZeroMQ streams go on); restart the service to start it again",
            self.child.pid,
            self.child.returncode,
        )

    def status(self) -> dict[str, int | None] | None:
        return None if self.child is None else {"pid": self.child.pid, "exit_status": self.child.poll()}
