"""Bounded clients: a cap on the connections each bound socket keeps, and the descriptor
limit raised to the unit's hard limit.

libzmq's ipc listener aborts the whole process when accept() fails with EMFILE
(`src/ipc_listener.cpp`: EMFILE is not among the errors it tolerates), so a daemon
that lets its connections grow to the descriptor limit can be killed by any client
allowed to connect. libzmq has no option to cap connections; its socket monitor
reports each accepted connection's descriptor, and shutting that descriptor down
makes libzmq itself see the peer gone and close it. `ConnectionCap` does so for
every connection beyond its cap, so the daemon's descriptors stay near the caps,
far below the limit, however many connections clients open.
"""

from __future__ import annotations

import resource
import socket
from typing import Any

import zmq
from zmq.utils.monitor import parse_monitor_message

#: Connections kept per bound socket: a lab's clients (haptic loop, recorder, live view,
#: bridge, CLI) are a handful; 128 leaves room for many, and 3 sockets x 128 stay far
#: below the unit's descriptor limit.
MAX_CONNECTIONS = 128


def raise_descriptor_limit() -> None:
    """Raise the soft RLIMIT_NOFILE to the hard one (the unit's `LimitNOFILE=soft:hard`):
    the headroom lets the caps answer a burst of connections before the limit is near."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and soft < hard:  # unlimited: nothing to raise to
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))


class ConnectionCap:
    """Keeps at most ``limit`` connections on a bound ZeroMQ ``sock``; the surplus is shut
    down as soon as `drain` sees it accepted (the client sees its peer close, and, if it
    is a ZeroMQ socket, retries after its reconnect interval). One cap per socket, whatever
    its endpoints: ``name`` says which in `status`."""

    def __init__(self, sock: zmq.Socket, name: str, limit: int = MAX_CONNECTIONS):
        self.name, self.limit = name, limit
        self.monitor = sock.get_monitor_socket(zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED)
        self._sock = sock
        self.open: set[int] = set()  # descriptors of the connections kept
        self.refused = 0
        self.peak = 0
        self.left = 0  # connections closed (by their clients, or refused): queues libzmq frees

    def drain(self) -> None:
        """Handle every event waiting: count a connection kept, or shut down the surplus."""
        while True:
            try:
                event = parse_monitor_message(self.monitor.recv_multipart(zmq.NOBLOCK))
            except zmq.Again:
                return
            fd = int(event["value"])
            if event["event"] == zmq.EVENT_DISCONNECTED:
                self.open.discard(fd)
                self.left += 1
            elif len(self.open) < self.limit:
                self.open.add(fd)
                self.peak = max(self.peak, len(self.open))
            else:
                _shut_down(fd)
                self.refused += 1

    def status(self) -> dict[str, Any]:
        return {"open": len(self.open), "peak": self.peak, "refused": self.refused, "limit": self.limit}

    def close(self) -> None:
        self._sock.disable_monitor()
        self.monitor.close(linger=0)


def _shut_down(fd: int) -> None:
    """shutdown(2) on descriptor ``fd``, libzmq's: it stays libzmq's to close. A descriptor
    libzmq has closed and reused for something else than a stream socket is left alone."""
    try:
        sock = socket.socket(fileno=fd)
    except OSError:
        return  # not a socket (any more): closed and reused by libzmq for a file or eventfd
    try:
        if sock.type == socket.SOCK_STREAM:
            # A stream socket under this number is a connection libzmq accepted (it opens no
            # other): the one refused, or a newer one of the surplus, equally over the cap.
            sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass  # already closed by the peer
    finally:
        sock.detach()
