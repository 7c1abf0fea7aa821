"""`ftsensord run`: open the configured bus and sockets, run the daemon, clean up.

Signals become loop events: SIGTERM (and SIGINT) finish the cycle, put the
chips back to idle and exit 0; SIGHUP reloads calibration and configuration.
"""

from __future__ import annotations

import logging
import os
import signal
from pathlib import Path

import zmq

from ..acquire.bus import open_bus, parse_bus_spec
from ..chip.i2c import Bus
from ..errors import ConfigError
from .config import Config, is_loopback
from .control import MAX_REQUEST
from .daemon import Daemon
from .sdnotify import Notifier

log = logging.getLogger("ftsensord")

#: Samples queued per subscriber before the newest are dropped: a haptic loop
#: wants the latest value, never a backlog of stale ones.
PUB_HWM = 8
#: Control requests queued before more are dropped (a flood cannot eat memory).
CONTROL_HWM = 100


def open_configured_bus(config: Config) -> Bus:
    """The configured bus; a simulated one spends real wire time at ``bus_hz``."""
    kind, _ = parse_bus_spec(config.bus)
    if kind == "sim":
        from ..sim import MonotonicClock
        return open_bus(config.bus, clock=MonotonicClock(), bus_hz=config.bus_hz, seed=None)
    return open_bus(config.bus)


def _ipc_path(endpoint: str) -> Path | None:
    return Path(endpoint[len("ipc://"):]) if endpoint.startswith("ipc://") else None


def bind(socket: zmq.Socket, endpoint: str) -> None:
    """Bind, creating an ipc socket's folder; the socket file gets mode 0660
    (the service's group may connect, nobody else)."""
    path = _ipc_path(endpoint)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o750)
    socket.bind(endpoint)
    if path is not None:
        os.chmod(path, 0o660)


def secure_control(context: zmq.Context, control: zmq.Socket, config: Config) -> object | None:
    """CURVE on the control socket when configured: the server's secret key, and a ZAP
    handler that lets in only the clients whose public certificates are in the folder.
    Returns the authenticator (stop it at exit)."""
    security = config.security
    if security.curve:
        from zmq.auth import load_certificate
        from zmq.auth.thread import ThreadAuthenticator

        auth = ThreadAuthenticator(context)
        auth.start()
        auth.configure_curve(domain="*", location=str(security.curve_clients_dir))
        public, secret = load_certificate(str(security.curve_server_cert))
        if secret is None:
            raise ConfigError(f"{security.curve_server_cert}: no secret key in this certificate")
        control.curve_secretkey = secret
        control.curve_publickey = public
        control.curve_server = True
        return auth
    if not is_loopback(config.control):
        log.warning("SECURITY: control endpoint %s is reachable beyond this host WITHOUT authentication "
                    "(allow_insecure_control = true)", config.control)
    return None


def make_sockets(context: zmq.Context, config: Config) -> tuple[zmq.Socket, zmq.Socket, object | None]:
    """The publisher, the control socket, and the CURVE authenticator (None without CURVE)."""
    publisher = context.socket(zmq.PUB)
    publisher.setsockopt(zmq.SNDHWM, PUB_HWM)
    publisher.setsockopt(zmq.LINGER, 0)
    for endpoint in config.publish:
        bind(publisher, endpoint)
    control = context.socket(zmq.ROUTER)
    control.setsockopt(zmq.MAXMSGSIZE, MAX_REQUEST)
    control.setsockopt(zmq.RCVHWM, CONTROL_HWM)
    control.setsockopt(zmq.LINGER, 0)
    auth = secure_control(context, control, config)
    bind(control, config.control)
    return publisher, control, auth


def run(config: Config) -> int:
    bus = open_configured_bus(config)
    context = zmq.Context()
    publisher, control, auth = make_sockets(context, config)
    daemon = Daemon(config, bus, publisher, control, notifier=Notifier())

    def stop(signum: int, frame: object) -> None:
        daemon.stop_requested = True

    def reload(signum: int, frame: object) -> None:
        daemon.reload_requested = True

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGHUP, reload)
    log.info("ftsensord on %s: %s; publishing on %s, control on %s", config.bus, config.bound().describe(),
             ", ".join(config.publish), config.control)
    try:
        return daemon.run()
    finally:
        publisher.close()
        if auth is not None:
            auth.stop()  # type: ignore[attr-defined]
        control.close()
        context.term()
        bus.close()
        for endpoint in (*config.publish, config.control):
            path = _ipc_path(endpoint)
            if path is not None and path.exists():
                path.unlink()
