"""Shared fixtures: a noiseless simulated bus on a virtual clock."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import weakref
from collections.abc import Callable, Hashable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq

from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.sim import (
    NOISELESS,
    SimulatedBus,
    StaticScene,
    VirtualClock,
    simulated_bus,
)

ADDR = 0x0C

# A shell without job control starts a background command (`pytest ... &`) with SIGINT ignored,
# and every command a test starts would inherit that: Ctrl-C, or the SIGINT a test sends,
# would not reach them (the guide's and echo's tests). The test process takes it back.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

#: Every zmq.Context made in this process (weakly held), for `no_zmq_context_left_open`.
_CONTEXTS: weakref.WeakSet[zmq.Context] = weakref.WeakSet()
_context_init = zmq.Context.__init__


def _tracked_init(self: zmq.Context, *args: Any, **kwargs: Any) -> None:
    _context_init(self, *args, **kwargs)
    _CONTEXTS.add(self)


zmq.Context.__init__ = _tracked_init  # type: ignore[method-assign]


@pytest.fixture(autouse=True)
def no_zmq_context_left_open() -> Iterator[None]:
    """A test fails if it leaves a context of its own (not the singleton) unterminated: left to
    the garbage collector, `Context.__del__` -> term() waits forever for sockets that the same
    collection was to close, and a later test hangs (the suite hung once in test_heat_scene).
    The context is destroyed here, so the rest of the suite runs on."""
    yield
    left = [c for c in list(_CONTEXTS) if not c.closed and not c._shadow and c is not type(c)._instance]
    named = repr(left)  # with their open sockets, before they are closed
    for c in left:
        c.destroy(linger=0)
    assert not left, f"zmq contexts left unterminated (use the zmq_context fixture): {named}"


@pytest.fixture
def zmq_context() -> Iterator[zmq.Context]:
    """A context of the test's own, destroyed at teardown with any socket still open (linger 0),
    whether the test passed or failed half-way (see `no_zmq_context_left_open`)."""
    ctx = zmq.Context()
    yield ctx
    ctx.destroy(linger=0)


@pytest.fixture
def ipv6_loopback() -> None:
    """Skips a test where this host has no IPv6 loopback (a container without ::1)."""
    import socket

    try:
        with socket.socket(socket.AF_INET6) as s:
            s.bind(("::1", 0))
    except OSError as exc:
        pytest.skip(f"no IPv6 loopback here ({exc})")


def assert_names_file_and_key(load, path, key: str, expected: str) -> None:
    """``load(path)`` refuses the file with a ConfigError naming the file, the key and
    what was expected: the contract for every file the project reads."""
    from ftsensord.errors import ConfigError

    with pytest.raises(ConfigError) as exc:
        load(path)
    msg = str(exc.value)
    assert str(path) in msg and key in msg and expected in msg, msg


@pytest.fixture
def scene() -> StaticScene:
    """Two chips with distinct fields (T, chip frame)."""
    return StaticScene(
        {0x0C: np.array([100e-6, -200e-6, 1500e-6]), 0x14: np.array([-50e-6, 25e-6, -800e-6])}, {0x0C: 31.5}
    )


@pytest.fixture
def bus(scene: StaticScene) -> SimulatedBus:
    return simulated_bus(scene, clock=VirtualClock(), noise=NOISELESS)


@pytest.fixture
def chip(bus: SimulatedBus) -> MLX90393:
    """A driver for 0x0C, reset and configured with the paper's settings."""
    drv = MLX90393(bus, ADDR, sleep=bus.sleep)
    drv.reset()
    drv.configure(mlx.Settings())
    return drv


ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="session")
def regenerated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder `python -m benchmarks regenerate --quick` wrote every generated page into:
    run once for the session, the tests of each page read it (the structure, not the figures)."""
    out = tmp_path_factory.mktemp("results")
    done = subprocess.run(
        [sys.executable, "-m", "benchmarks", "regenerate", "--quick", "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    return out


# `start_daemon`: `ftsensord run --config CONFIG` in a subprocess, its runtime folder in
# ``folder``, returned with its notify socket once it said READY=1; `InProcess`: a `Daemon`
# in this process on a virtual clock. ftsensord.testing.harness: the one way the project
# starts the daemon for a run.
from ftsensord.testing.harness import InProcess, start_daemon  # noqa: E402,F401


class StreamRecorder(threading.Thread):
    """Every sample of ``streams`` the Python client receives on ``endpoint``, by ``key(sample)``
    (the reference an outside reader's values are compared with)."""

    def __init__(self, endpoint: str, streams: list[str], key: Callable[[Any], Hashable]):
        super().__init__(daemon=True)
        self.endpoint, self.streams, self.key = endpoint, streams, key
        self.samples: dict[Hashable, Any] = {}
        self.stop = threading.Event()

    def run(self) -> None:
        from ftsensord.client import Subscriber

        with Subscriber(self.endpoint, self.streams) as sub:
            while not self.stop.is_set():
                s = sub.receive(timeout_s=0.05)
                if s is not None:
                    self.samples[self.key(s)] = s
