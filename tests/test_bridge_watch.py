"""The ROS 2 bridge as the daemon watches it (daemon/ros2child.py): an exit is logged once and
shown in `status`; a bridge that does not stop is killed, never left behind. No DDS here:
the child is a stand-in process."""

from __future__ import annotations

import logging
import subprocess
import sys
import time

import pytest

from ftsensord.config.ros2conf import Ros2Config
from ftsensord.daemon import ros2child
from ftsensord.daemon.ros2child import BridgeWatch, ros2_beside


def test_a_bridge_that_exits_is_logged_once_and_shown_in_status(caplog):
    child = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    watch = BridgeWatch(child)
    child.wait(timeout=30)
    with caplog.at_level(logging.WARNING, logger="ftsensord"):
        watch.check()
        watch.check()
    said = [r.getMessage() for r in caplog.records if "ROS 2 bridge" in r.getMessage()]
    assert len(said) == 1 and f"pid {child.pid}" in said[0] and "status 3" in said[0]
    assert watch.status() == {"pid": child.pid, "exit_status": 3}
    assert BridgeWatch().status() is None  # no [ros2]: nothing to watch
    BridgeWatch().check()


def test_a_bridge_that_ignores_sigterm_is_killed_when_the_daemon_stops(monkeypatch, tmp_path, caplog):
    stubborn = [
        sys.executable,
        "-c",
        "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
        "open(r'%s', 'w').close(); time.sleep(60)" % (tmp_path / "up"),
    ]
    real = subprocess.Popen
    monkeypatch.setattr(ros2child.subprocess, "Popen", lambda args, **kw: real(stubborn, **kw))
    monkeypatch.setattr(ros2child, "BRIDGE_EXIT_S", 0.5)
    t0 = time.monotonic()
    with caplog.at_level(logging.WARNING, logger="ftsensord"):
        with ros2_beside(Ros2Config(output="bridge"), tmp_path / "ftsensord.toml") as child:
            while not (tmp_path / "up").exists():  # its SIGTERM handler set
                assert child.poll() is None and time.monotonic() - t0 < 30
                time.sleep(0.01)
    assert child.returncode == -9  # SIGKILL after the wait, not left running
    assert any("did not stop within 0.5 s: killed" in r.getMessage() for r in caplog.records)


def test_without_a_ros2_table_nothing_is_started(tmp_path):
    with ros2_beside(None, tmp_path / "x.toml") as child:
        assert child is None


def test_a_domain_id_from_the_environment_or_the_flag_is_checked():
    from ftsensord.config.ros2conf import check_domain_id, default_domain_id
    from ftsensord.errors import ConfigError

    assert default_domain_id({}) == 0 and default_domain_id({"ROS_DOMAIN_ID": " 42 "}) == 42
    for bad in ("300", "abc", "-1"):  # once silently domain 0: the bridge off the nodes' domain
        with pytest.raises(ConfigError, match=r"ROS_DOMAIN_ID \(environment\): expected a DDS domain id"):
            default_domain_id({"ROS_DOMAIN_ID": bad})
    with pytest.raises(ConfigError, match="--domain-id: expected"):
        check_domain_id("--domain-id", 500)
