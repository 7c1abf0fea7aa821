"""Who may reach the daemon's endpoints: ipc:// and loopback TCP by default; beyond
this host only with ``[security]`` (CURVE for control, `public_stream` for the wrenches).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from ftsensord.docfile import Table
from ftsensord.protocol.paths import resolve_file


@dataclass
class Security:
    """Who may reach the endpoints when they leave loopback (docs/reference/protocol.md)."""

    curve_server_cert: Path | None = None  # zmq certificate with the server's secret key
    curve_clients_dir: Path | None = None  # public certificates of the clients allowed to control
    allow_insecure_control: bool = False  # control off loopback without CURVE: logged loudly
    public_stream: bool = False  # the (read-only) wrench stream may leave loopback

    @property
    def curve(self) -> bool:
        return self.curve_server_cert is not None


LOOPBACK = ("127.0.0.1", "localhost", "[::1]")
#: An ipc socket's path is a sockaddr_un's sun_path: 108 bytes with its NUL (libzmq refuses more at bind).
MAX_IPC_PATH_BYTES = 107
#: A host is a name, an IPv4 address, * (every interface) or [an IPv6 address]; libzmq takes
#: more (tcp://0.0.0.0:5555:1) and refuses it at bind.
_TCP = re.compile(r"tcp://(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.*-]+):(?P<port>[0-9]{1,5})")


def needs_ipv6(endpoint: str) -> bool:
    """An IPv6 address (tcp://[::1]:PORT): libzmq binds or reaches it only with ZMQ_IPV6 set."""
    return endpoint.startswith("tcp://[")


def is_loopback(endpoint: str) -> bool:
    return not endpoint.startswith("tcp://") or endpoint[len("tcp://") :].rsplit(":", 1)[0] in LOOPBACK


def endpoint(table: Table, key: str, default: str, *, off_loopback: bool = False, why: str = "") -> str:
    """An ipc:// or tcp:// endpoint; TCP only on loopback unless ``off_loopback``."""
    value = table.string(key, default)
    if not value.startswith(("ipc://", "tcp://")):
        raise table.fail(key, "an ipc:// or tcp:// endpoint", value)
    if value.startswith("ipc://@"):  # Linux's abstract namespace: no file, so no mode, group or lock
        raise table.fail(
            key,
            "an ipc:// endpoint with a path (an abstract socket, ipc://@name, has no file "
            "permissions: anyone on the host could connect)",
            value,
        )
    problem = _malformed(value)
    if problem:
        raise table.fail(key, problem, value)
    if not off_loopback and not is_loopback(value):
        raise table.fail(key, f"a loopback TCP endpoint (127.0.0.1, localhost or [::1]); {why}", value)
    return value


def _malformed(value: str) -> str | None:
    """What is wrong with an endpoint libzmq would bind elsewhere than written (it takes
    port 99999 as 34463, -1 as 65535, 5e3 as 5, * or 0 as any) or refuse at bind time."""
    if value.startswith("tcp://"):
        match = _TCP.fullmatch(value)
        if match is None or not 1 <= int(match["port"]) <= 65535:
            return (
                "tcp://HOST:PORT (a name, an IPv4 address, * or [an IPv6 address]) with a port from 1 to "
                "65535 (digits only: no wildcard, no path)"
            )
        return None
    path = value[len("ipc://") :]
    if not path.startswith("/") or len(path.encode()) > MAX_IPC_PATH_BYTES:
        return f"ipc:// and an absolute path of at most {MAX_IPC_PATH_BYTES} bytes (a socket file's limit)"
    return None


def security_table(doc: Table) -> Security:
    """The ``[security]`` table of ``doc`` (none: everything on this host only)."""
    if "security" not in doc.doc:
        return Security()
    t = doc.table("security")
    t.only({"curve_server_cert", "curve_clients_dir", "allow_insecure_control", "public_stream"})
    cert = (
        resolve_file(t, "curve_server_cert", t.string("curve_server_cert"))
        if "curve_server_cert" in t.doc
        else None
    )
    clients = None
    if "curve_clients_dir" in t.doc:
        clients = Path(t.string("curve_clients_dir")).expanduser()
        clients = clients if clients.is_absolute() else t.path.parent / clients
        if not clients.is_dir():
            raise t.fail(
                "curve_clients_dir",
                "a folder of the allowed clients' public certificates",
                t.get("curve_clients_dir"),
            )
    if (cert is None) != (clients is None):
        raise t.fail(
            "curve_server_cert" if cert is None else "curve_clients_dir",
            "both curve_server_cert and curve_clients_dir, or neither",
            "only one of them",
        )
    flags = {}
    for key in ("allow_insecure_control", "public_stream"):
        value = t.get(key, False)
        if not isinstance(value, bool):
            raise t.fail(key, "true or false", value)
        flags[key] = value
    return Security(cert, clients, **flags)
