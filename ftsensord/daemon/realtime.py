"""Real-time scheduling, asked for by the daemon itself and said when the host refuses it.

The systemd unit used to set ``CPUSchedulingPolicy=fifo``: systemd then applies it before
exec, and a refusal is fatal (``status=214/SETSCHEDULER``, restarted for ever). Kernels
built with RT group scheduling (``CONFIG_RT_GROUP_SCHED``: Armbian's and several vendor
kernels, Amazon Linux) refuse SCHED_FIFO to any process whose cpu cgroup has no real-time
budget, which is every service's once systemd puts it under the cpu controller. So the
daemon asks (`ftsensord run --realtime 50`, allowed without privileges by the unit's
``LimitRTPRIO=50``), and on a refusal logs why and runs at the normal priority: the rate
may then suffer on a busy board, but the service runs, and `status` says so.

It must be asked before the first ZeroMQ socket: libzmq's I/O and reaper threads inherit
the policy of the thread that makes them, then set it again, and abort the process if
that is refused (src/thread.cpp); asked later, they would stay at the normal priority.
"""

from __future__ import annotations

import os
import resource
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ftsensord.errors import ConfigError

#: SCHED_FIFO's priorities (sched(7)).
FIFO_PRIORITIES = range(1, 100)

_POLICIES = {
    os.SCHED_OTHER: "other",
    os.SCHED_FIFO: "fifo",
    os.SCHED_RR: "rr",
    getattr(os, "SCHED_BATCH", -1): "batch",
    getattr(os, "SCHED_IDLE", -2): "idle",
}


@dataclass(frozen=True)
class Scheduling:
    """What the daemon asked for (``asked``: a SCHED_FIFO priority, 0 for none) and, when
    the kernel refused, why (``refused``)."""

    asked: int = 0
    refused: str | None = None

    def status(self) -> dict[str, Any]:
        """The calling thread's policy now, beside what was asked (the `status` reply)."""
        policy = os.sched_getscheduler(0)
        return {
            "policy": _POLICIES.get(policy, str(policy)),
            "priority": os.sched_getparam(0).sched_priority,
            "asked": self.asked,
            "refused": self.refused,
        }


def request_fifo(priority: int) -> Scheduling:
    """Put the calling thread (and the threads it makes from now on) under SCHED_FIFO at
    ``priority``; 0 asks nothing. A refusal is returned with its likely cause, not raised."""
    if priority == 0:
        return Scheduling()
    if priority not in FIFO_PRIORITIES:
        raise ConfigError(
            f"--realtime: expected a SCHED_FIFO priority from 1 to 99 (0: none), got {priority}"
        )
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError as exc:
        return Scheduling(priority, f"{exc.strerror}: {refusal_cause(priority)}")
    return Scheduling(priority)


def refusal_cause(priority: int) -> str:
    """Why SCHED_FIFO at ``priority`` is refused here, as far as the process can tell."""
    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    if os.geteuid() != 0 and soft != resource.RLIM_INFINITY and soft < priority:
        return (
            f"the real-time priority limit is {soft} (the unit's LimitRTPRIO={priority} raises it "
            f"where the service manager may: it needs CAP_SYS_RESOURCE)"
        )
    budget = _cgroup_rt_runtime_us()
    if budget == 0:
        return (
            "the kernel schedules real-time tasks by cgroup (CONFIG_RT_GROUP_SCHED) and this "
            "process's cpu cgroup has no real-time budget (cpu.rt_runtime_us = 0); running at the "
            'normal priority (docs/design/reliability.md, "The systemd unit")'
        )
    return "refused by the kernel or a security policy (seccomp, SELinux)"


def _cgroup_rt_runtime_us() -> int | None:
    """The real-time budget of this process's cgroup v1 cpu controller, or None (none, or v2)."""
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        _, controllers, path = line.split(":", 2)
        if "cpu" in controllers.split(","):
            try:
                return int(Path("/sys/fs/cgroup/cpu", path.lstrip("/"), "cpu.rt_runtime_us").read_text())
            except (OSError, ValueError):
                return None
    return None
