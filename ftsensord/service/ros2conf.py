"""The configuration's ``[ros2]`` table: the streams on the ROS 2 graph (`ftsensord.ros2`).

    [ros2]
    namespace = "ftsensord"   # topics /<namespace>/wrench/<stream>, service /<namespace>/tare
    domain_id = 0             # default: $ROS_DOMAIN_ID, else 0 (ROS's default)
    output = "in-loop"        # or "bridge" (docs/performance.md, "The ROS 2 bridge")

Parsed here. ``output = "bridge"``: `ros2_beside` starts the bridge (`ftsensord ros2`) for
`ftsensord run` as a process of its own, by its command line: nothing of the bridge is
imported here. ``output = "in-loop"``: the daemon's loop thread writes to DDS itself, after
each cycle's ZeroMQ sends (`ftsensord.ros2.inloop`, handed to `run` by the command line). A
``[ros2]`` table without the ``ros2`` extra installed is refused at load, naming the extra,
so the daemon never starts believing it is on the graph.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.util
import logging
import os
import re
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from ..docfile import Table
from ..errors import ConfigError

log = logging.getLogger("ftsensord")
#: How long a stopped bridge may take to exit before it is killed (s): its DDS participant's
#: goodbye takes well under one.
BRIDGE_EXIT_S = 10.0

#: A ROS 2 name's tokens (design.ros2.org, Topic and Service names): a letter or underscore
#: first, then letters, digits, underscores; no empty token, no "__".
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
#: DDS's RTPS port mapping leaves 0-232 for domain ids (ROS 2 docs, "The ROS_DOMAIN_ID").
MAX_DOMAIN_ID = 232
#: Where the DDS writes are made: a bridge process fed by ZeroMQ, or the daemon's loop thread.
OUTPUTS = ("in-loop", "bridge")


@dataclass(frozen=True)
class Ros2Config:
    namespace: str = "ftsensord"  # without slashes at either end
    domain_id: int = 0
    output: str = "in-loop"  # one of OUTPUTS: in-loop measured better (docs/performance.md)


def default_domain_id(environ: dict[str, str] | None = None) -> int:
    """ROS_DOMAIN_ID, else 0 (what ROS 2 nodes default to); ConfigError when it is set to
    anything but a number in 0-232 (the bridge would sit on another domain than the nodes)."""
    text = (os.environ if environ is None else environ).get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    return check_domain_id("ROS_DOMAIN_ID (environment)", int(text) if text.isdigit() else text)


def check_domain_id(where: str, value: object) -> int:
    """``value`` as a DDS domain id; ConfigError naming ``where`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_DOMAIN_ID:
        raise ConfigError(f"{where}: expected a DDS domain id, an integer from 0 to {MAX_DOMAIN_ID}, got {value!r}")
    return value


def parse_ros2(doc: Table, path: Path) -> Ros2Config | None:
    """``[ros2]`` of ``doc`` (the file ``path``), None when absent; ConfigError naming the
    file and key for a bad value, or naming the extra when cyclonedds is not installed."""
    if "ros2" not in doc.doc:
        return None
    t = doc.table("ros2")
    t.only({"namespace", "domain_id", "output"})
    namespace = t.string("namespace", "ftsensord").strip("/")
    if not is_ros_name(namespace):
        raise t.fail("namespace", "a ROS 2 name: tokens of letters, digits and underscores separated by /, "
                                  "none starting with a digit", namespace)
    domain_id = t.integer("domain_id", 0 if "domain_id" in t.doc else default_domain_id(), low=0, high=MAX_DOMAIN_ID,
                          what=f"a DDS domain id, 0 to {MAX_DOMAIN_ID}")
    output = t.string("output", Ros2Config.output)
    if output not in OUTPUTS:
        raise t.fail("output", " or ".join(f'"{o}"' for o in OUTPUTS), output)
    needs_cyclonedds(f"{path}: ros2: the ROS 2 output", " (or remove the [ros2] table)")
    return Ros2Config(namespace, domain_id, output)


def is_ros_name(name: str) -> bool:
    """Whether ``name`` (no slash at either end) is a ROS 2 name's tokens joined by /."""
    return all(_TOKEN.fullmatch(token) and "__" not in token for token in name.split("/"))


def needs_cyclonedds(who: str, hint: str = "") -> None:
    """ConfigError naming the extra when Cyclone DDS's Python binding is not installed."""
    if importlib.util.find_spec("cyclonedds") is None:
        raise ConfigError(f"{who} needs Eclipse Cyclone DDS's Python binding: pip install 'ftsensord[ros2]'{hint}")


#: The bridge's forwarding thread's SCHED_FIFO priority under a real-time daemon: the lowest,
#: above every normal process (the subscribers it competes with on a busy host) and below the
#: loop and anything else made real-time (docs/performance.md, "The ROS 2 bridge").
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
    return [sys.executable, "-m", "ftsensord", "ros2", "--config", str(config_path),
            *(["--realtime", str(realtime)] if realtime else [])]


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
            log.warning("the ROS 2 bridge (pid %d) did not stop within %g s: killed", child.pid, BRIDGE_EXIT_S)
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
        log.warning("the ROS 2 bridge (pid %d) exited with status %d: its topics, /diagnostics and the tare "
                    "from ROS have stopped (the ZeroMQ streams go on); restart the service to start it again",
                    self.child.pid, self.child.returncode)

    def status(self) -> dict[str, int | None] | None:
        return None if self.child is None else {"pid": self.child.pid, "exit_status": self.child.poll()}
