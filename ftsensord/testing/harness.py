"""The daemon for the benchmarks (and the tests): `ftsensord run` as a process, in a runtime
folder of its own, at the systemd unit's priority when asked, handed back once it said
READY=1 (`start_daemon`); or in this process on a virtual clock, stepped a cycle at a
time (`InProcess`)."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import zmq

from ftsensord.config.file import Config, builtin_path
from ftsensord.daemon.daemon import Daemon
from ftsensord.sim import VirtualClock, simulated_bus
from ftsensord.sim.chip import FieldSource


def packaged_config(path: Path, **values: str) -> Path:
    """The packaged simulated configuration written to ``path``, each ``key = value`` line
    named in ``values`` replaced, or a commented-out one put in (values in TOML:
    ``scheduler='"burst"'``), `builtin:` files
    made absolute (the copy is read from elsewhere)."""
    text = builtin_path("sim.toml").read_text()
    for key, value in values.items():
        text, n = re.subn(rf"(?m)^(# )?{key} = .*$", f"{key} = {value}", text)
        if n != 1:
            raise ValueError(f"the packaged configuration has no single {key!r} line to replace")
    path.write_text(text.replace("builtin:", str(builtin_path("")) + "/"))
    return path


def start_daemon(
    config: Path,
    folder: Path,
    *,
    fifo: int = 0,
    nice: int = 0,
    args: Sequence[str] = (),
    env: dict[str, str] | None = None,
    program: Sequence[str] = ("-m", "ftsensord"),
    **popen: Any,
) -> tuple[subprocess.Popen, socket.socket]:
    """`ftsensord run --config CONFIG [ARGS]` with its runtime folder in ``folder``, SCHED_FIFO
    at ``fifo`` (0: not; as `--realtime` asks it, from the start) or at ``nice``;
    ``env``: more variables; ``program``: what Python runs (a script that wraps ftsensord's
    command line); ``popen``: the output's routing (subprocess.Popen's keywords,
    default: discarded). Returned with its notify socket (the caller's from then on:
    WATCHDOG=1 pings arrive there) once it said READY=1; `stop` ends both. The tests start
    the daemon with this too (tests/conftest.py)."""
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(folder / "notify"))
    notify.settimeout(30)  # start-up on a loaded 2-core host takes seconds, never this long
    full_env = {
        **os.environ,
        "XDG_RUNTIME_DIR": str(folder),
        "NOTIFY_SOCKET": str(folder / "notify"),
        **(env or {}),
    }
    full_env.pop("RUNTIME_DIRECTORY", None)
    # chrt: the daemon's threads inherit the policy, as under the unit.
    prefix = (["chrt", "-f", str(fifo)] if fifo else []) + (["nice", "-n", str(nice)] if nice else [])
    popen = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, **popen}
    proc = subprocess.Popen(
        [*prefix, sys.executable, *program, "run", "--config", str(config), *args],
        env=full_env,
        text=True,
        **popen,
    )
    try:
        while not notify.recv(4096).startswith(b"READY=1"):
            pass
    except BaseException:
        proc.kill()
        notify.close()
        raise
    return proc, notify


def cpu_seconds(pid: int) -> float:
    """User and system CPU (s) of process ``pid``, every thread (/proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def stop(proc: subprocess.Popen, notify: socket.socket) -> int:
    """SIGTERM, as systemctl stop; the exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout=10)
    finally:
        notify.close()


class InProcess:
    """A `Daemon` in this process on a virtual clock (CPU free, the bus's time exact) and
    the simulated bus of ``scene`` at 400 kHz: ``sub`` receives what it publishes (topics
    starting with ``subscribe``), ``req`` is a REQ client of its control socket. The caller
    steps it (``daemon.cycle()``, ``daemon.handle_control()``, ``clock.wait_until``).
    ``daemon``: the Daemon's other keywords (notifier, orientation)."""

    def __init__(
        self, config: Config, scene: FieldSource, *, subscribe: bytes = b"", seed: int = 5, **daemon: Any
    ):
        self.config, self.scene, self.clock = config, scene, VirtualClock()
        self.bus = simulated_bus(scene, clock=self.clock, bus_hz=400e3, seed=seed)
        # inproc names are per context, and this module may be loaded twice (by path and by name)
        ctx: zmq.Context = zmq.Context.instance()
        n = uuid.uuid4().hex
        self.pub, self.sub = ctx.socket(zmq.PUB), ctx.socket(zmq.SUB)
        self.pub.bind(f"inproc://pub{n}")
        self.sub.connect(f"inproc://pub{n}")
        self.sub.setsockopt(zmq.SUBSCRIBE, subscribe)
        self.router, self.req = ctx.socket(zmq.ROUTER), ctx.socket(zmq.REQ)
        self.router.bind(f"inproc://ctl{n}")
        self.req.connect(f"inproc://ctl{n}")
        self.req.setsockopt(zmq.RCVTIMEO, 5000)  # a reply that never comes fails, never hangs
        self.daemon = Daemon(
            config,
            self.bus,
            self.pub,
            self.router,
            clock=self.clock.now,
            wall=lambda: 1.7e9 + self.clock.now(),
            **daemon,
        )
        self.daemon.start()

    def close(self) -> None:
        for s in (self.pub, self.sub, self.router, self.req):
            s.close(linger=0)
