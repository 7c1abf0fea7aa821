"""The systemd unit's own restrictions on a process started here, without systemd: its
`SystemCallFilter=` installed with seccomp before exec, its resource limits with
setrlimit, its `MemoryMax=` as a memory cgroup where this host lets us make one
(`MemoryGroup`), the `--realtime` its ExecStart= gives the daemon. The tests run the daemon under them
(tests/test_unit_sandbox.py),
because `systemd-analyze verify` and `security` read the unit but never run the program:
a filter that kills the daemon at start passes both.

The filter is what systemd builds from the unit's lines: the first `SystemCallFilter=`
without `~` starts an allow list (with `@default`, which systemd always adds to one), later
lines with `~` take calls out and lines without put them back, and every other call fails
with `SystemCallErrorNumber=`. Groups (`@system-service`, ...) are expanded by this host's
`systemd-analyze syscall-filter`, or, where systemd is not installed, by the copy of
systemd 252's table beside this file; names are turned into this architecture's numbers
by libseccomp, which systemd uses too. Calls this architecture does not have are skipped,
as systemd skips them.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import re
import resource
import shutil
import subprocess
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

GROUPS_FALLBACK = Path(__file__).resolve().parent / "systemd-syscall-groups.txt"

# libseccomp's action words (seccomp.h): ALLOW, and ERRNO with the error in the low 16 bits.
SCMP_ACT_ALLOW = 0x7FFF0000
SCMP_ACT_ERRNO = 0x00050000
PR_SET_NO_NEW_PRIVS = 38
#: What a service gets without LimitNOFILE= (systemd's DefaultLimitNOFILE= since v240).
SYSTEMD_DEFAULT_NOFILE = (1024, 524288)


def parse_groups(text: str) -> dict[str, list[str]]:
    """`systemd-analyze syscall-filter`'s listing: each `@group` line, then its members
    (calls and nested `@groups`), comments (`#`) and blank lines skipped."""
    groups: dict[str, list[str]] = {}
    current: list[str] | None = None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if not raw[:1].isspace() and line.startswith("@"):
            current = groups.setdefault(line, [])
        elif current is not None:
            current.append(line)
    return groups


def syscall_groups() -> dict[str, list[str]]:
    """This host's systemd groups, or systemd 252's (the copy beside this file)."""
    exe = shutil.which("systemd-analyze")
    if exe is not None:
        out = subprocess.run([exe, "syscall-filter"], capture_output=True, text=True, check=True).stdout
        return parse_groups(out)
    return parse_groups(GROUPS_FALLBACK.read_text())


def expand(names: list[str], groups: dict[str, list[str]]) -> set[str]:
    """Calls named, groups expanded recursively (an unknown group is an error: systemd
    refuses the unit then)."""
    out: set[str] = set()
    for name in names:
        if name.startswith("@"):
            if name not in groups:
                raise ValueError(f"unknown system call group {name}")
            out |= expand(groups[name], groups)
        else:
            out.add(name)
    return out


@dataclass
class UnitRestrictions:
    """What a unit's [Service] section restricts, as read from its file."""

    filters: list[str] = field(default_factory=list)  # SystemCallFilter= values, in order
    error_number: str = "EPERM"  # SystemCallErrorNumber=
    limit_nofile: tuple[int, int] = SYSTEMD_DEFAULT_NOFILE  # LimitNOFILE=soft:hard (one value: both)
    memory_max: int | None = None  # MemoryMax=, bytes
    limit_rtprio: int = 0  # LimitRTPRIO=: the SCHED_FIFO priority the process may take itself
    realtime: int = 0  # ExecStart='s `--realtime N`: the priority the daemon asks for (0: none)

    @property
    def run_args(self) -> list[str]:
        """What ExecStart= adds to `ftsensord run --config FILE`."""
        return ["--realtime", str(self.realtime)] if self.realtime else []

    @classmethod
    def from_unit(cls, path: Path) -> UnitRestrictions:
        r = cls()
        for line in path.read_text().splitlines():
            m = re.match(r"^\s*([A-Za-z]+)=(.*)$", line)
            if not m:
                continue
            key, value = m.group(1), m.group(2).strip()
            if key == "SystemCallFilter":
                r.filters.append(value)
            elif key == "SystemCallErrorNumber":
                r.error_number = value
            elif key == "LimitNOFILE":
                soft, _, hard = value.partition(":")
                r.limit_nofile = (int(soft), int(hard or soft))
            elif key == "MemoryMax":
                r.memory_max = _bytes(value)
            elif key == "LimitRTPRIO":
                r.limit_rtprio = int(value)
            elif key == "ExecStart":
                m = re.search(r"--realtime[ =](\d+)", value)
                r.realtime = int(m.group(1)) if m else 0
            elif key.startswith("CPUScheduling"):
                raise ValueError(f"{path}: {key}= is not modelled (the daemon asks for real-time itself)")
        return r

    def allowed_calls(self, groups: dict[str, list[str]]) -> set[str] | None:
        """The calls the filter lets through (None: no allow list, nothing filtered here)."""
        allowed: set[str] | None = None
        for value in self.filters:
            deny = value.startswith("~")
            names = value.lstrip("~").split()
            if allowed is None:
                if deny:
                    return None  # a deny list first: not what this unit does, not modelled
                allowed = expand(["@default"], groups)
            calls = expand(names, groups)
            allowed = allowed - calls if deny else allowed | calls
        return allowed

    def preexec(
        self, groups: dict[str, list[str]] | None = None, memory: MemoryGroup | None = None
    ) -> Callable[[], None]:
        """A `subprocess.Popen` ``preexec_fn`` that applies these restrictions in the child,
        in systemd's order: its cgroup (``memory``, made for `memory_max`) and limits first,
        the system call filter last."""
        allowed = self.allowed_calls(groups if groups is not None else syscall_groups())
        lib = _libseccomp()
        # Resolved here, not in the child: the child should do as little as possible.
        numbers = sorted(
            {n for n in (lib.seccomp_syscall_resolve_name(c.encode()) for c in allowed or ()) if n >= 0}
        )
        err = getattr(errno, self.error_number)
        # A hard limit above this process's own cannot be raised without privilege: kept at ours.
        hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
        nofile = (min(self.limit_nofile[0], hard), min(self.limit_nofile[1], hard))
        rtprio_hard = resource.getrlimit(resource.RLIMIT_RTPRIO)[1]
        rtprio = (
            min(self.limit_rtprio, rtprio_hard)
            if rtprio_hard != resource.RLIM_INFINITY
            else self.limit_rtprio
        )

        def apply() -> None:
            if memory is not None:
                memory.join()
            resource.setrlimit(resource.RLIMIT_NOFILE, nofile)
            resource.setrlimit(resource.RLIMIT_RTPRIO, (rtprio, rtprio))
            if allowed is None:
                return
            if lib.prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0:  # NoNewPrivileges=yes
                raise OSError(ctypes.get_errno(), "prctl(PR_SET_NO_NEW_PRIVS)")
            ctx = lib.seccomp_init(SCMP_ACT_ERRNO | err)
            for n in numbers:
                if lib.seccomp_rule_add(ctx, SCMP_ACT_ALLOW, n, 0) != 0:
                    raise OSError(f"seccomp_rule_add({n}) failed")
            if lib.seccomp_load(ctx) != 0:
                raise OSError("seccomp_load failed")

        return apply


class MemoryGroup:
    """``MemoryMax=`` as systemd applies it: a memory cgroup of its own for the process, whose
    limit the kernel enforces (reclaim, then the OOM killer). Made as a child of this
    process's own group, on cgroup v2 (``memory.max``) or a v1 memory hierarchy
    (``memory.limit_in_bytes``; swap left free, as systemd leaves it without MemorySwapMax=).
    `make` gives None where no such group can be made here (no memory controller for us)."""

    def __init__(self, path: Path, v2: bool):
        self.path, self.v2 = path, v2

    @classmethod
    def make(cls, limit: int, name: str, swap: bool = True) -> MemoryGroup | None:
        """``swap=False`` also keeps the group out of swap (v2 ``memory.swap.max`` 0, v1
        ``memory.memsw.limit_in_bytes``), so a process beyond the limit is killed, not swapped
        out; None then where that cannot be set."""
        for line in Path("/proc/self/cgroup").read_text().splitlines():
            _, controllers, own = line.split(":", 2)
            v2 = controllers == ""
            if not v2 and "memory" not in controllers.split(","):
                continue
            root = _cgroup_mount("cgroup2" if v2 else "memory")
            if root is None:
                continue
            path = root / own.lstrip("/") / name
            try:
                path.mkdir()
            except OSError:
                continue
            group = cls(path, v2)
            try:
                (path / group._limit_file).write_text(str(limit))
                if not swap:  # v1's memsw counts memory and swap together: the same limit
                    (path / ("memory.swap.max" if v2 else "memory.memsw.limit_in_bytes")).write_text(
                        "0" if v2 else str(limit)
                    )
            except OSError:  # v2 without memory delegated to our group, or no swap accounting
                path.rmdir()
                continue
            return group
        return None

    @property
    def _limit_file(self) -> str:
        return "memory.max" if self.v2 else "memory.limit_in_bytes"

    def join(self) -> None:
        """In a ``preexec_fn``: move the calling process into the group (before exec, so all
        the program allocates is counted)."""
        (self.path / "cgroup.procs").write_text("0")

    def peak(self) -> int | None:
        """The most the group has used, bytes (its page cache included, as the limit counts
        it); None where the kernel keeps no peak (cgroup v2 before Linux 5.19)."""
        path = self.path / ("memory.peak" if self.v2 else "memory.max_usage_in_bytes")
        return int(path.read_text()) if path.exists() else None

    def oom_kills(self) -> int:
        """Processes of the group the OOM killer took."""
        text = (self.path / ("memory.events" if self.v2 else "memory.oom_control")).read_text()
        return dict((k, int(v)) for k, v in (line.split() for line in text.splitlines())).get("oom_kill", 0)

    def remove(self) -> None:
        """Delete the group (its processes gone)."""
        self.path.rmdir()


def _cgroup_mount(kind: str) -> Path | None:
    """Where the cgroup2 hierarchy, or the v1 hierarchy with this controller, is mounted."""
    for line in Path("/proc/self/mountinfo").read_text().splitlines():
        pre, _, post = line.partition(" - ")
        fstype, _, options = post.split(" ")[:3]
        if (kind == "cgroup2" and fstype == "cgroup2") or (fstype == "cgroup" and kind in options.split(",")):
            return Path(pre.split(" ")[4])
    return None


def seccomp_available() -> bool:
    """libseccomp loads and the kernel takes filters (not so in some containers)."""
    try:
        _libseccomp()
    except OSError:
        return False
    return Path("/proc/self/status").read_text().find("Seccomp:") >= 0


def _libseccomp() -> ctypes.CDLL:
    name = ctypes.util.find_library("seccomp")
    if name is None:
        raise OSError("libseccomp is not installed")
    lib = ctypes.CDLL(name, use_errno=True)
    lib.seccomp_init.restype = ctypes.c_void_p
    lib.seccomp_init.argtypes = [ctypes.c_uint32]
    lib.seccomp_rule_add.argtypes = [ctypes.c_void_p, ctypes.c_uint32, ctypes.c_int, ctypes.c_uint]
    lib.seccomp_load.argtypes = [ctypes.c_void_p]
    lib.seccomp_syscall_resolve_name.argtypes = [ctypes.c_char_p]
    libc = ctypes.CDLL(None, use_errno=True)
    lib.prctl = libc.prctl  # type: ignore[attr-defined]
    return lib


def _bytes(value: str) -> int:
    """systemd's sizes: a number with an optional K, M, G, T suffix (powers of 1024)."""
    m = re.fullmatch(r"(\d+)([KMGT]?)", value)
    if m is None:
        raise ValueError(f"MemoryMax={value}: expected bytes with an optional K, M, G or T")
    return int(m.group(1)) * 1024 ** " KMGT".index(m.group(2) or " ")
