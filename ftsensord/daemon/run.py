"""`ftsensord run`: open the configured bus and sockets, run the daemon, clean up.

Signals become loop events: SIGTERM (and SIGINT) finish the cycle, put the
chips back to idle and exit 0; SIGHUP reloads calibration and configuration.
"""

from __future__ import annotations

import fcntl
import functools
import logging
import os
import signal
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zmq

from ftsensord.acquire.bus import open_bus, parse_bus_spec
from ftsensord.chip.i2c import Bus
from ftsensord.config.file import Config
from ftsensord.daemon.connections import ConnectionCap, raise_descriptor_limit
from ftsensord.daemon.control import MAX_PER_CYCLE, MAX_REQUEST
from ftsensord.daemon.daemon import Daemon
from ftsensord.daemon.host import HostGuard
from ftsensord.daemon.realtime import Scheduling, request_fifo
from ftsensord.daemon.ros2child import BridgeWatch, ros2_beside
from ftsensord.daemon.runtime import RuntimeFiles
from ftsensord.daemon.sdnotify import Notifier
from ftsensord.errors import ConfigError, FtsensordError
from ftsensord.processing.accuracy import apply_accuracy
from ftsensord.protocol.endpoints import is_loopback, needs_ipv6
from ftsensord.protocol.orientation import open_receiver
from ftsensord.protocol.paths import ensure_private_dir

if TYPE_CHECKING:
    from ftsensord.sim import MonotonicClock, VirtualClock

log = logging.getLogger("ftsensord")

#: Messages queued per subscriber before the newest are dropped (libzmq's default). A
#: recorder loses nothing while it, or the daemon's own ZeroMQ I/O thread (not FIFO outside
#: the unit), is held off the CPU for up to 2 s (5 streams at 100 Hz); 8, as before, lost
#: samples to a 20 ms hiccup. A haptic loop's freshness is its CONFLATE socket's job, and
#: the kernel's socket buffer already holds ~1000 samples of any backlog. Cost: a message
#: is shared by every queue, so 127 stalled subscribers pin 2.2 MiB more than with 8
#: (docs/design/reliability.md, "Subscribers nobody reads").
PUB_HWM = 1000
#: Control requests queued before more are dropped (a flood cannot eat memory).
CONTROL_HWM = 100
#: Replies queued per control client: four cycles' worth (MAX_PER_CYCLE each), so a client
#: that reads, if late, loses none even when libzmq's I/O thread is slow to take them; one
#: that does not read pins at most this many (a `status` is about 5.4 KB: 700 KB), the
#: rest are dropped and counted (`Control.dropped`).
REPLY_HWM = 4 * MAX_PER_CYCLE
#: A connection that has not finished ZeroMQ's handshake by then is closed (ms; libzmq's
#: default is 30 s): one that never speaks frees its place under the cap (`ConnectionCap`)
#: within a second; a real client's handshake takes well under a millisecond.
HANDSHAKE_MS = 1000


def open_configured_bus(config: Config, clock: MonotonicClock | VirtualClock | None = None) -> Bus:
    """The configured bus; a simulated one spends real wire time at ``bus_hz`` (or runs
    on ``clock``, a `sim.VirtualClock` for a benchmark). A real one is locked for the
    daemon alone (``scan`` and ``doctor`` then refuse it); the daemon measures its costs
    at start (`Daemon.start`, `acquire.board.know_board`)."""
    kind, _ = parse_bus_spec(config.bus)
    if kind == "sim":
        from ftsensord.sim import MonotonicClock

        return open_bus(config.bus, clock=clock or MonotonicClock(), bus_hz=config.bus_hz, seed=None)
    return open_bus(config.bus, exclusive=True)


def _ipc_path(endpoint: str) -> Path | None:
    return Path(endpoint[len("ipc://") :]) if endpoint.startswith("ipc://") else None


def bind(socket: zmq.Socket, endpoint: str, files: RuntimeFiles | None = None) -> None:
    """Bind, creating an ipc socket's folder (0700) and refusing one another user could
    tamper with (`ensure_private_dir`); the socket file gets mode 0660 (the service's
    group may connect, nobody else) and is recorded in ``files`` (watched, removed at exit)."""
    path = _ipc_path(endpoint)
    if path is not None:
        ensure_private_dir(path.parent)
    if needs_ipv6(endpoint):
        socket.setsockopt(zmq.IPV6, 1)
    socket.bind(endpoint)
    if path is not None:
        os.chmod(path, 0o660)
        if files is not None:
            files.made(path)


#: The lock file in each folder holding the daemon's ipc sockets.
LOCK_NAME = "ftsensord.lock"


def endpoints(config: Config) -> list[str]:
    """Every endpoint the daemon binds: the streams', control's, the orientation stream's."""
    orientation = config.orientation_endpoint
    return [*config.publish, config.control, *([orientation] if orientation else [])]


def lock_runtime(config: Config, files: RuntimeFiles | None = None) -> list[int]:
    """Take the exclusive lock (flock) in every folder of the configured ipc endpoints;
    refuse, naming the first daemon's pid, when another daemon holds one. Returns the
    open descriptors: the locks last while they stay open (the kernel drops them at exit,
    even after kill -9). Each lock file is recorded in ``files`` (watched, kept at exit)."""
    folders = sorted({p.parent for p in map(_ipc_path, endpoints(config)) if p is not None})
    held: list[int] = []
    try:
        for folder in folders:
            ensure_private_dir(folder)
            held.append(_lock(folder / LOCK_NAME))
            if files is not None:
                files.made(folder / LOCK_NAME, held[-1], remove=False)
    except BaseException:
        for fd in held:
            os.close(fd)
        raise
    return held


def _lock(path: Path) -> int:
    # O_NOFOLLOW: a symlink planted as the lock file is refused, not written through.
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        pid = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
        os.close(fd)
        raise ConfigError(
            f"{path.parent}: another ftsensord (pid {pid}) runs here; stop it first "
            "(or give this one other endpoints)"
        ) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def secure_control(context: zmq.Context, control: zmq.Socket, config: Config) -> object | None:
    """CURVE on the control socket when configured: the server's secret key, and a ZAP
    handler that lets in only the clients whose public certificates are in the folder.
    Returns the authenticator (stop it at exit)."""
    security = config.security
    if security.curve:
        from zmq.auth import load_certificate
        from zmq.auth.thread import ThreadAuthenticator

        public, secret = load_certificate(str(security.curve_server_cert))  # before a thread is started
        if secret is None:
            raise ConfigError(f"{security.curve_server_cert}: no secret key in this certificate")
        auth = ThreadAuthenticator(context)
        auth.start()
        auth.configure_curve(domain="*", location=str(security.curve_clients_dir))
        control.curve_secretkey = secret
        control.curve_publickey = public
        control.curve_server = True
        return auth
    if not is_loopback(config.control):
        log.warning(
            "SECURITY: control endpoint %s is reachable beyond this host WITHOUT authentication "
            "(allow_insecure_control = true)",
            config.control,
        )
    return None


def make_sockets(
    context: zmq.Context, config: Config, files: RuntimeFiles | None = None
) -> tuple[zmq.Socket, zmq.Socket, object | None]:
    """The publisher, the control socket, and the CURVE authenticator (None without CURVE);
    ``files``: where the ipc sockets made are recorded."""
    context.setsockopt(zmq.HANDSHAKE_IVL, HANDSHAKE_MS)  # every socket made from here on
    publisher = context.socket(zmq.PUB)
    publisher.setsockopt(zmq.SNDHWM, PUB_HWM)
    publisher.setsockopt(zmq.RCVHWM, CONTROL_HWM)  # subscription messages: bounded like requests
    publisher.setsockopt(zmq.LINGER, 0)
    for endpoint in config.publish:
        bind(publisher, endpoint, files)
    control = context.socket(zmq.ROUTER)
    control.setsockopt(zmq.MAXMSGSIZE, MAX_REQUEST)
    control.setsockopt(zmq.RCVHWM, CONTROL_HWM)
    control.setsockopt(zmq.SNDHWM, REPLY_HWM)
    control.setsockopt(zmq.ROUTER_MANDATORY, 1)  # a reply that cannot go raises, so it is counted
    control.setsockopt(zmq.LINGER, 0)
    auth = secure_control(context, control, config)
    try:
        bind(control, config.control, files)
    except BaseException:
        if auth is not None:  # its thread's socket: the caller's context.destroy must not race it
            auth.stop()  # type: ignore[attr-defined]
        raise
    return publisher, control, auth


class Signals:
    """SIGTERM and SIGINT ask the daemon to stop, SIGHUP to reload, from the start of `run`
    on; one that comes before the daemon exists is kept, and handed to it (`attach`)."""

    def __init__(self, early: Iterable[int] = ()) -> None:
        self.stop = self.reload = False
        self.daemon: Daemon | None = None
        for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            signal.signal(signum, self.handle)
        for early_signal in early:
            self.handle(early_signal, None)

    def handle(self, signum: int, frame: object = None) -> None:
        if signum == signal.SIGHUP:
            self.reload = True
        else:
            self.stop = True
        if self.daemon is not None:
            self.attach(self.daemon)

    def attach(self, daemon: Daemon) -> None:
        self.daemon = daemon
        daemon.stop_requested |= self.stop
        daemon.reload_requested |= self.reload
        self.reload = False  # handed over: the daemon clears its own


def run(config: Config, early: Iterable[int] = (), realtime: int = 0, ros2_in_loop: Any = None) -> int:
    """Serve ``config`` until SIGTERM; ``early``: signals that came before (`__main__.EARLY_SIGNALS`);
    ``realtime``: the SCHED_FIFO priority to ask for (0: none; a refusal is logged, not fatal);
    ``ros2_in_loop(daemon, ros2)``: the output for ``[ros2] output = "in-loop"`` (`ros2.inloop.InLoop`,
    handed in by the command line: the service does not import DDS's floor)."""
    if config.ros2 is not None and config.ros2.output == "in-loop" and ros2_in_loop is None:
        raise ConfigError(
            f'{config.path}: ros2.output: "in-loop" needs the ROS 2 output, which this caller '
            "of daemon.run does not hand in (`ftsensord run` does)"
        )
    signals = Signals(early)
    if signals.stop:  # stopped while starting: nothing made yet, nothing to undo
        log.info("stopped before starting")
        return 0
    raise_descriptor_limit()
    scheduling = request_fifo(realtime)  # before any ZeroMQ thread exists (`realtime`)
    if scheduling.refused:
        log.warning("real-time scheduling (SCHED_FIFO %d) refused: %s", realtime, scheduling.refused)
    planned = apply_accuracy(config)  # a sensor's accuracy: the conversion, rate and averaging
    if planned is not None:
        log.info("accuracy: %s; %s", planned.describe(), config.choice)
    notifier = Notifier()
    notifier.check_rate(config.rate_hz, f"{config.path}: rate_hz")
    files = RuntimeFiles()
    locks = lock_runtime(config, files)  # before the bus: a second daemon must not touch the chips
    try:
        try:
            bus = open_configured_bus(config)
        except (OSError, FtsensordError) as exc:
            raise ConfigError(f"{config.path}: bus: cannot open {config.bus!r}: {exc}") from exc
        with ros2_beside(config.ros2, config.path) as bridge:  # [ros2]: DDS in a process of its own
            return _serve(
                config, bus, notifier, files, signals, scheduling, BridgeWatch(bridge), ros2_in_loop
            )
    finally:
        for fd in locks:
            os.close(fd)


def _serve(
    config: Config,
    bus: Bus,
    notifier: Notifier,
    files: RuntimeFiles,
    signals: Signals,
    scheduling: Scheduling,
    bridge: BridgeWatch,
    ros2_in_loop: Any = None,
) -> int:
    context = zmq.Context()
    caps: list[ConnectionCap] = []
    auth = None
    try:
        publisher, control, auth = make_sockets(context, config, files)
        endpoint = config.orientation_endpoint
        orientation = (
            open_receiver(context, endpoint, functools.partial(bind, files=files)) if endpoint else None
        )
        caps = [
            ConnectionCap(publisher, "publish"),
            ConnectionCap(control, "control"),
            *([ConnectionCap(orientation, "orientation")] if orientation is not None else []),
        ]
        daemon = Daemon(
            config,
            bus,
            publisher,
            control,
            notifier=notifier,
            orientation=orientation,
            guard=HostGuard(caps, files),
            background_reload=True,
            scheduling=scheduling,
        )
        daemon.bridge = bridge
        if config.ros2 is not None and config.ros2.output == "in-loop":
            try:
                daemon.outputs.append(ros2_in_loop(daemon, config.ros2))
            except FtsensordError as exc:  # as when the bridge process exits: ROS 2 is off, ZeroMQ goes on
                log.error("the ROS 2 output did not start: %s; the ZeroMQ streams go on without it", exc)

        signals.attach(daemon)
        log.info(
            "ftsensord on %s: %s; publishing on %s, control on %s",
            config.bus,
            config.bound().describe(),
            ", ".join(config.publish),
            config.control,
        )
        return daemon.run()
    finally:
        for cap in caps:
            cap.close()
        if auth is not None:
            auth.stop()  # type: ignore[attr-defined]  # its socket is its thread's: closed there, first
        # Every socket still open (also those of a start that failed half-way) closed now: a context
        # left to the garbage collector can wait in term() for sockets the same collection closes.
        context.destroy(linger=0)
        bus.close()
        files.remove_own()
