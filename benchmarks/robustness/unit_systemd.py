"""The shipped unit started by this machine's own systemd, installed as README's "As a
service" says, in namespaces of its own (PID, mount, network, UTS, IPC) so that nothing
of the host changes: `benchmarks/robustness/unit_sandbox.py` applies the unit's filter and limits
by hand; this runs the real thing, so whatever systemd does before exec (users, groups,
namespaces, devices, cgroups, scheduling, limits) is what the daemon meets.

Inside, on top of the host's files: /run a fresh tmpfs; /etc and /opt overlays (their
changes kept in that tmpfs) where the README's `useradd`, `/etc/ftsensord` and
/opt/ftsensord are made, the last a virtual environment of the system's python3 that sees
this checkout and the packages of the interpreter running this script (a .pth file to
both, bound into /run: no download, the code under test, wherever the checkout is).
The unit file is copied unchanged; one drop-in removes its default dependencies (no
sysinit.target: it would run the host's tmpfiles and sysctl setup) and sends its output
to a file in that /run. systemd itself runs as PID 1 of the namespace (container mode).

    python -m benchmarks.robustness.unit_systemd [--dropin 'CPUWeight=100']   # prints systemctl status

Needs root, util-linux's unshare and nsenter, and systemd installed (not running).
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

from benchmarks.common import ROOT

REPO = ROOT
UNIT = REPO / "systemd" / "ftsensord.service"
SYSTEMD = next(
    (p for p in (Path("/lib/systemd/systemd"), Path("/usr/lib/systemd/systemd")) if p.exists()), None
)
SYSTEM_PYTHON = Path("/usr/bin/python3")
#: Units of the host that the boot must not run: they act on shared files (tmpfiles
#: empties /tmp, which is the host's) even in namespaces of its own.
MASKED = (
    "systemd-tmpfiles-setup.service",
    "systemd-tmpfiles-setup-dev.service",
    "systemd-tmpfiles-clean.timer",
    "sysinit.target",
    "basic.target",
    "systemd-journald.service",
    "systemd-journald.socket",
    "systemd-journald-dev-log.socket",
)


def why_not() -> str | None:
    """Why this machine cannot run the unit this way, or None."""
    if os.geteuid() != 0:
        return "needs root (namespaces, and systemd as their PID 1)"
    if SYSTEMD is None:
        return "systemd is not installed"
    if not SYSTEM_PYTHON.exists():
        return f"{SYSTEM_PYTHON} is missing (the unit's ProtectHome=yes hides a Python under /home or /root)"
    for tool in ("unshare", "nsenter", "useradd"):
        if shutil.which(tool) is None:
            return f"{tool} is missing"
    return None


#: The daemon's output, in the namespace's /run (a path of the host could be under an overlay).
LOG = "/run/ftsensord-test.log"


def _boot_script(config: Path, dropins: list[str]) -> str:
    site = sysconfig.get_paths()["purelib"]  # this interpreter's packages: numpy, pyzmq, smbus2
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    units = "/run/systemd/system"
    q = shlex.quote
    return "\n".join(
        [
            "set -eu",
            "mount --make-rprivate /",
            "mount -t tmpfs -o mode=755 tmpfs /run",
            f"mkdir -p {units}/ftsensord.service.d",
            # /etc and /opt writable over the host's, the changes in the namespace's /run only.
            *(
                f"mkdir -p /run/over{d}/upper /run/over{d}/work && mount -t overlay overlay "
                f"-o lowerdir={d},upperdir=/run/over{d}/upper,workdir=/run/over{d}/work {d}"
                for d in ("/etc", "/opt")
            ),
            # README, "As a service": the i2c group, the user, the environment, the configuration.
            "getent group i2c >/dev/null || groupadd --system i2c",
            "useradd --system --no-create-home --groups i2c ftsensord",
            "rm -rf /opt/ftsensord",
            f"{SYSTEM_PYTHON} -m venv --without-pip /opt/ftsensord",
            # The checkout and the packages are bound into /run: where they are (/tmp, /home) the
            # unit may hide (PrivateTmp=, ProtectHome=).
            f"mkdir -p /run/checkout/src /run/checkout/site && mount --bind {q(str(REPO))} /run/checkout/src "
            f"&& mount --bind {q(site)} /run/checkout/site",
            f"printf '%s\\n' /run/checkout/src /run/checkout/site "
            f"> /opt/ftsensord/lib/{version}/site-packages/checkout.pth",
            "printf '#!/opt/ftsensord/bin/python3\\nimport sys\\nfrom ftsensord.__main__ import main\\n"
            "sys.exit(main())\\n' > /opt/ftsensord/bin/ftsensord && chmod 755 /opt/ftsensord/bin/ftsensord",
            f"install -d /etc/ftsensord && cp {q(str(config))} /etc/ftsensord/ftsensord.toml",
            f"cp {q(str(UNIT))} {units}/",
            *(f"ln -s /dev/null {units}/{u}" for u in MASKED),
            f"printf '[Unit]\\nDefaultDependencies=no\\n[Service]\\nStandardOutput=append:{LOG}\\n"
            f"StandardError=inherit\\n' > {units}/ftsensord.service.d/test.conf",
            *(
                f"printf '[Service]\\n%s\\n' {q(line)} > {units}/ftsensord.service.d/extra{i}.conf"
                for i, line in enumerate(dropins)
            ),
            f"printf '[Unit]\\nDefaultDependencies=no\\nWants=ftsensord.service\\n' > {units}/fts-test.target",
            "export container=ftsensord-test",
            f"exec {SYSTEMD} --system --unit=fts-test.target --log-target=console --show-status=no",
        ]
    )


class SystemdHost:
    """systemd as PID 1 of fresh namespaces, running the shipped unit (drop-ins: extra
    [Service] lines). Use as a context manager; `systemctl` and `run` act inside."""

    def __init__(self, work: Path, config: Path, dropins: list[str] | None = None):
        self.work, self.config, self.dropins = work, config, dropins or []
        self.proc: subprocess.Popen | None = None
        self.pid = 0

    def __enter__(self) -> SystemdHost:
        self.work.mkdir(parents=True, exist_ok=True)
        script = self.work / "boot.sh"
        script.write_text(_boot_script(self.config, self.dropins))
        with open(self.work / "systemd.log", "w") as log:
            self.proc = subprocess.Popen(
                [
                    "unshare",
                    "--fork",
                    "--pid",
                    "--mount",
                    "--net",
                    "--uts",
                    "--ipc",
                    "--mount-proc",
                    "bash",
                    str(script),
                ],
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and self.proc.poll() is None:
            self.pid = self._namespace_init()
            if self.pid and self.systemctl("is-system-running").stdout.strip() in (
                "running",
                "degraded",
                "starting",
            ):
                return self
            time.sleep(0.2)
        self.__exit__()
        raise RuntimeError(f"systemd did not come up: {(self.work / 'systemd.log').read_text()[-2000:]}")

    def _namespace_init(self) -> int:
        """The host's pid of the namespace's PID 1 (systemd, once the script exec'd it)."""
        children = Path(f"/proc/{self.proc.pid}/task/{self.proc.pid}/children")
        for pid in children.read_text().split() if children.exists() else ():
            if Path(f"/proc/{pid}/exe").resolve() == SYSTEMD.resolve():
                return int(pid)
        return 0

    def run(self, *argv: str, timeout: float = 30) -> subprocess.CompletedProcess:
        """A command inside the namespaces (as root)."""
        return subprocess.run(
            ["nsenter", "-t", str(self.pid), "-m", "-p", "-n", "-u", "-i", *argv],
            capture_output=True,
            text=True,
            timeout=timeout,
        )

    def systemctl(self, *args: str) -> subprocess.CompletedProcess:
        return self.run("systemctl", "--no-pager", *args)

    def show(self, *properties: str) -> dict[str, str]:
        """`systemctl show ftsensord` for these properties."""
        out = self.systemctl("show", "ftsensord", *(f"--property={p}" for p in properties)).stdout
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)

    def wait_for(self, prop: str, values: tuple[str, ...], timeout: float = 30) -> dict[str, str]:
        """Until the unit's ``prop`` is one of ``values``; the last `show` of it and a few more."""
        deadline = time.monotonic() + timeout
        while True:
            state = self.show(
                prop, "ActiveState", "SubState", "Result", "ExecMainStatus", "NRestarts", "StatusText"
            )
            if state.get(prop) in values or time.monotonic() > deadline:
                return state
            time.sleep(0.2)

    def daemon_log(self) -> str:
        """What the daemon printed (stdout and stderr) so far."""
        return self.run("cat", LOG).stdout

    def __exit__(self, *exc: object) -> None:
        if self.pid:  # PID 1 of the namespace: its end ends every process in it
            try:
                os.kill(self.pid, 9)
            except ProcessLookupError:
                pass
        if self.proc is not None:
            self.proc.wait(timeout=10)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--dropin", action="append", default=[], help="an extra [Service] line, e.g. CPUWeight=100"
    )
    parser.add_argument("--work", type=Path, default=REPO / "build" / "unit-systemd")
    parser.add_argument("--seconds", type=float, default=5.0, help="how long to let it run before the status")
    args = parser.parse_args(argv)
    reason = why_not()
    if reason:
        print(f"unit_systemd: {reason}", file=sys.stderr)
        return 2
    config = REPO / "ftsensord" / "data" / "sim.toml"
    with SystemdHost(args.work, config, args.dropin) as host:
        host.wait_for("SubState", ("running",))
        time.sleep(args.seconds)
        print(host.systemctl("status", "ftsensord").stdout)
        print(host.run("/opt/ftsensord/bin/ftsensord", "status").stdout)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
