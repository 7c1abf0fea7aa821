"""Real ROS 2 for the tests: one virtual environment a distribution, in the repository's
``.ros2-venvs/`` (not committed), made with ``python -m venv`` and filled by pip from the
package index's ROS 2 wheels (rclpy, the default rmw, the message packages the daemon speaks),
once: a later run finds it made. The distributions cannot share one environment: their wheels
depend on the same unversioned names (``ros-rclpy``, ``ros-rmw``...) at other versions.

The wheels need nothing set by hand: their ``ros_wheels_bootstrapper`` (a .pth file) starts
the interpreter again with LD_LIBRARY_PATH naming the wheels' libraries. It marks the process
environment it made (``_ROS_WHEELS_BOOTSTRAP_COMPLETE``); `peer_env` leaves that mark out, so a
distribution's Python started from another's process still sets its own paths.
"""

from __future__ import annotations

import fcntl
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VENVS = ROOT / ".ros2-venvs"
PEER = Path(__file__).with_name("ros2_rclpy_peer.py")

#: Each distribution's wheels, pinned: what the tests were written against. rclpy with its
#: default rmw (rmw_fastrtps_cpp: Fast DDS 2.14 on Jazzy, 3.2 on Kilted) and the message
#: packages of the daemon's topics and service.
DISTRIBUTIONS = {
    "jazzy": [
        "ros-jazzy-rclpy==7.1.6",
        "ros-jazzy-rmw-fastrtps-cpp==8.4.3",
        "ros-jazzy-geometry-msgs==5.3.6",
        "ros-jazzy-diagnostic-msgs==5.3.6",
        "ros-jazzy-std-msgs==5.3.6",
        "ros-jazzy-sensor-msgs==5.3.6",
        "ros-jazzy-std-srvs==5.3.6",
    ],
    "kilted": [
        "ros-kilted-rclpy==9.1.2",
        "ros-kilted-rmw-fastrtps-cpp==9.3.3",
        "ros-kilted-geometry-msgs==5.5.1",
        "ros-kilted-diagnostic-msgs==5.5.1",
        "ros-kilted-std-msgs==5.5.1",
        "ros-kilted-sensor-msgs==5.5.1",
        "ros-kilted-std-srvs==5.5.1",
    ],
}
#: How long pip may take a distribution (about 40 s each from the index on the CI machine).
INSTALL_TIMEOUT_S = 900


def python_of(distro: str) -> Path:
    """The Python of ``distro``'s environment, made first if it is not (or was made for other
    wheels, or half made: the list is written last); a file lock keeps two runs from making it
    at once. RuntimeError, with pip's output, when it cannot be made."""
    VENVS.mkdir(exist_ok=True)
    venv, wanted = VENVS / distro, json.dumps(DISTRIBUTIONS[distro])
    made = venv / "ftsensord-wheels.json"
    with open(VENVS / f"{distro}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (made.exists() and made.read_text() == wanted):
            start = time.monotonic()
            steps = [
                [sys.executable, "-m", "venv", "--clear", str(venv)],
                [str(venv / "bin" / "python"), "-m", "pip", "install", "-q", *DISTRIBUTIONS[distro]],
            ]
            for step in steps:
                done = subprocess.run(
                    step,
                    capture_output=True,
                    text=True,
                    timeout=INSTALL_TIMEOUT_S,
                    env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"},
                )
                if done.returncode != 0:
                    raise RuntimeError(
                        f"{' '.join(step)} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
                    )
            made.write_text(wanted)
            print(
                f"\n{distro}: ROS 2 wheels installed in {time.monotonic() - start:.0f} s ({venv})",
                file=sys.stderr,
            )
    return venv / "bin" / "python"


def peer_env(**more: str) -> dict[str, str]:
    """A ROS 2 user's environment: the default rmw named, discovery kept to this host, the
    bootstrapper's mark of another environment left out."""
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(
            ("_ROS_WHEELS_BOOTSTRAP", "ROS_", "RMW_", "AMENT_", "CYCLONEDDS_", "FASTDDS_", "FASTRTPS_")
        )
    }
    return {
        **env,
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        **more,
    }
