"""The runtime folder and the lock: another local user cannot take the sockets over,
and a second daemon on the same folder refuses to start, naming the first."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
import zmq

from ftsensord import client
from ftsensord.config import file as config_module
from ftsensord.config.file import load_config
from ftsensord.daemon.run import LOCK_NAME, bind, lock_runtime
from ftsensord.errors import ConfigError
from ftsensord.protocol.paths import check_private_dir, ensure_private_dir

from .test_daemon import write_config


def someone_else_owns(path, monkeypatch) -> None:
    """Make ``path`` another user's: chown when root, else pretend to be another user."""
    if os.geteuid() == 0:
        os.chown(path, 4242, 4242)
    else:
        uid = os.geteuid()
        monkeypatch.setattr(os, "geteuid", lambda: uid + 1)


@pytest.fixture
def fallback(tmp_path, monkeypatch):
    """The fallback runtime folder (no RUNTIME_DIRECTORY, no XDG_RUNTIME_DIR), moved into tmp_path."""
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    folder = tmp_path / f"ftsensord-{os.getuid()}"
    monkeypatch.setattr(config_module, "runtime_dir", lambda: folder)
    monkeypatch.setattr(client, "runtime_dir", lambda: folder)
    monkeypatch.setattr(client, "SERVICE_RUNTIME_DIR", tmp_path / "no-service")
    return folder


def test_the_fallback_folder_is_created_private(fallback):
    ensure_private_dir(fallback)
    st = os.lstat(fallback)
    assert st.st_mode & 0o777 == 0o700 and st.st_uid == os.geteuid()
    assert client.default_endpoint("wrench") == f"ipc://{fallback}/wrench"


def test_a_folder_taken_over_by_another_user_is_refused_by_daemon_and_client(
    fallback, monkeypatch, zmq_context
):
    fallback.mkdir(mode=0o755)
    ctx = zmq_context  # terminated at teardown, with any socket an assert left open
    impostor = ctx.socket(zmq.PUB)  # the attacker's publisher, in place before the victim
    impostor.bind(f"ipc://{fallback}/wrench")
    someone_else_owns(fallback, monkeypatch)
    try:
        with pytest.raises(ConfigError, match="belongs to uid"):
            client.default_endpoint("wrench")  # `ftsensord echo` would have printed the impostor's 42 N
        sock = ctx.socket(zmq.PUB)
        with pytest.raises(ConfigError, match="refusing this runtime folder"):
            bind(sock, f"ipc://{fallback}/control")
        sock.close(linger=0)
        assert not (fallback / "control").exists()
    finally:
        impostor.close(linger=0)


def test_a_symlinked_folder_is_refused_and_nothing_is_created_through_it(fallback, tmp_path, zmq_context):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir(mode=0o700)
    fallback.symlink_to(elsewhere)
    with pytest.raises(ConfigError, match="symbolic link"):
        ensure_private_dir(fallback)
    with pytest.raises(ConfigError, match="symbolic link"):
        client.default_endpoint("control")
    ctx = zmq_context  # terminated at teardown, with any socket an assert left open
    sock = ctx.socket(zmq.PUB)
    with pytest.raises(ConfigError, match="symbolic link"):
        bind(sock, f"ipc://{fallback}/wrench")
    sock.close(linger=0)
    assert list(elsewhere.iterdir()) == []


@pytest.mark.parametrize("mode", [0o777, 0o1777, 0o770])
def test_a_folder_writable_by_others_is_refused_not_kept(fallback, mode):
    fallback.mkdir()
    os.chmod(fallback, mode)
    with pytest.raises(ConfigError, match="writable by"):
        ensure_private_dir(fallback)
    with pytest.raises(ConfigError, match="writable by"):
        client.default_endpoint("wrench")
    assert os.lstat(fallback).st_mode & 0o7777 == mode  # refused, never silently used or changed


def test_the_service_folder_may_be_the_service_users_but_must_sit_in_roots_folder(tmp_path):
    service = tmp_path / "service"
    service.mkdir(mode=0o750)
    # tmp_path is not root's (or is, under root: then the check passes on the parent's mode 0700).
    if os.lstat(tmp_path).st_uid != 0:
        with pytest.raises(ConfigError, match="root alone"):
            check_private_dir(service, owner=-1)
    else:
        check_private_dir(service, owner=-1)
        os.chmod(tmp_path, 0o777)
        with pytest.raises(ConfigError, match="root alone"):
            check_private_dir(service, owner=-1)
        os.chmod(tmp_path, 0o700)


def test_a_lock_file_planted_as_a_symlink_is_not_followed(tmp_path):
    config = load_config(
        write_config(
            tmp_path, extra=f'publish = "ipc://{tmp_path}/rt/pub"\ncontrol = "ipc://{tmp_path}/rt/ctl"'
        )
    )
    (tmp_path / "rt").mkdir(mode=0o700)
    target = tmp_path / "victim-file"
    target.write_text("precious")
    (tmp_path / "rt" / LOCK_NAME).symlink_to(target)
    with pytest.raises(OSError):
        lock_runtime(config)
    assert target.read_text() == "precious"


def test_a_second_daemon_refuses_to_start_naming_the_first(tmp_path):
    rt = tmp_path / "rt"
    config_path = write_config(tmp_path, extra=f'publish = "ipc://{rt}/pub"\ncontrol = "ipc://{rt}/ctl"')
    # The first daemon: a real process holding the lock (the flock is per open file, so
    # a second lock in this process would be refused as well; a process is the honest test).
    first = subprocess.Popen(
        [sys.executable, "-m", "ftsensord", "run", "--config", str(config_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        ctl = client.ControlClient(f"ipc://{rt}/ctl", timeout_s=10)
        assert ctl.status()["cycles"] >= 0  # the first one serves
        second = subprocess.run(
            [sys.executable, "-m", "ftsensord", "run", "--config", str(config_path)],
            check=False,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert second.returncode != 0
        assert f"another ftsensord (pid {first.pid}) runs here" in second.stderr + second.stdout
        assert ctl.status()["cycles"] > 0  # the first one still has its endpoints
        assert (rt / "ctl").exists() and (rt / "pub").exists()
    finally:
        first.terminate()
        first.wait(timeout=30)
    assert first.returncode == 0
    # The lock died with the first daemon: a new one may take the folder.
    fd = lock_runtime(load_config(config_path))
    assert (rt / LOCK_NAME).read_text().strip() == str(os.getpid())
    for f in fd:
        os.close(f)


def test_a_deleted_folder_ends_the_daemon_and_a_second_one_keeps_its_sockets(tmp_path):
    """The folder deleted under a running daemon (logind at logout, a /tmp cleaner): it
    exits 1 naming what is gone (systemd restarts it), so it never runs on unreachable or
    beside a second daemon in a new folder of the same name; and stopping, it deletes
    only the sockets it made, not the second daemon's."""
    rt = tmp_path / "rt"
    config_path = write_config(tmp_path, extra=f'publish = "ipc://{rt}/pub"\ncontrol = "ipc://{rt}/ctl"')
    run = [sys.executable, "-m", "ftsensord", "run", "--config", str(config_path)]
    first = subprocess.Popen(run, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    second = None
    try:
        assert client.ControlClient(f"ipc://{rt}/ctl", timeout_s=10).status()["cycles"] >= 0
        shutil.rmtree(rt)
        second = subprocess.Popen(run, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        out = first.communicate(timeout=10)[0]  # a cycle sees it (10 ms); 10 s for a loaded host
        assert first.returncode == 1, out[-2000:]
        assert f"{rt}/" in out and "deleted" in out, out[-2000:]
        status = client.ControlClient(f"ipc://{rt}/ctl", timeout_s=10).status()
        assert (
            status["cycles"] >= 0 and second.poll() is None
        )  # the second's sockets survived the first's exit
        assert (rt / "ctl").exists() and (rt / "pub").exists()
    finally:
        for proc in (first, second):
            if proc is not None and proc.poll() is None:
                proc.terminate()
                proc.wait(timeout=30)
    assert second.returncode == 0
    assert not (rt / "ctl").exists()  # the second removed its own at its clean exit


def _caught(pid: int, signum: int) -> bool:
    """Whether process ``pid`` has a handler for ``signum`` (/proc/PID/status SigCgt)."""
    for line in open(f"/proc/{pid}/status"):
        if line.startswith("SigCgt:"):
            return bool(int(line.split()[1], 16) >> (signum - 1) & 1)
    return False


@pytest.mark.parametrize("when", ["handler", "lock", "sockets"])
def test_a_sigterm_while_starting_is_a_clean_exit(tmp_path, when):
    """systemctl stop right after start: as soon as the process handles SIGTERM at all
    (while still importing), once it holds the lock, once its sockets exist: exit 0 and
    no socket left behind, never a death by the signal."""
    rt = tmp_path / "rt"
    config_path = write_config(tmp_path, extra=f'publish = "ipc://{rt}/pub"\ncontrol = "ipc://{rt}/ctl"')
    proc = subprocess.Popen(
        [sys.executable, "-m", "ftsensord", "run", "--config", str(config_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    ready = {
        "handler": lambda: _caught(proc.pid, signal.SIGTERM),
        "lock": (rt / LOCK_NAME).exists,
        "sockets": (rt / "ctl").exists,
    }[when]
    try:
        while not ready():
            assert proc.poll() is None, proc.communicate()[0]
            time.sleep(1e-3)  # polled at 1 ms: the start takes about a second
        proc.send_signal(signal.SIGTERM)
        out = proc.communicate(timeout=30)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out[-2000:]
    assert not (rt / "ctl").exists() and not (rt / "pub").exists()
