"""The configuration's ``[ros2]`` table: the streams on the ROS 2 graph (`ftsensord.ros2`).

    [ros2]
    namespace = "ftsensord"   # topics /<namespace>/wrench/<stream>, service /<namespace>/tare
    domain_id = 0             # default: $ROS_DOMAIN_ID, else 0 (ROS's default)
    output = "in-loop"        # or "bridge" (docs/results/performance.md, "ROS 2")

Parsed here; nothing is started here. ``output = "bridge"``: `daemon.ros2child.ros2_beside`
starts the bridge (`ftsensord ros2`) for `ftsensord run` as a process of its own, by its
command line. ``output = "in-loop"``: the daemon's loop thread writes to DDS itself, after
each cycle's ZeroMQ sends (`ftsensord.ros2.inloop`, handed to `run` by the command line). A
``[ros2]`` table without the ``ros2`` extra installed is refused at load, naming the extra,
so the daemon never starts believing it is on the graph.
"""

from __future__ import annotations

import importlib.util
import os
import re
from dataclasses import dataclass
from pathlib import Path

from ftsensord.docfile import Table
from ftsensord.errors import ConfigError

#: A ROS 2 name's tokens (design.ros2.org, Topic and Service names): a letter or underscore
#: first, then letters, digits, underscores; no empty token, no "__".
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
#: DDS's RTPS port mapping leaves 0-232 for domain ids (ROS 2 docs, "The ROS_DOMAIN_ID").
MAX_DOMAIN_ID = 232
#: Where the DDS writes are made: a bridge process fed by ZeroMQ, or the daemon's loop thread.
OUTPUTS = ("in-loop", "bridge")


@dataclass(frozen=True)
class Ros2Config:
    namespace: str = "ftsensord"  # without slashes at either end
    domain_id: int = 0
    output: str = "in-loop"  # one of OUTPUTS: in-loop measured better (docs/results/performance.md)


def default_domain_id(environ: dict[str, str] | None = None) -> int:
    """ROS_DOMAIN_ID, else 0 (what ROS 2 nodes default to); ConfigError when it is set to
    anything but a number in 0-232 (the bridge would sit on another domain than the nodes)."""
    text = (os.environ if environ is None else environ).get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    return check_domain_id("ROS_DOMAIN_ID (environment)", int(text) if text.isdigit() else text)


def check_domain_id(where: str, value: object) -> int:
    """``value`` as a DDS domain id; ConfigError naming ``where`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_DOMAIN_ID:
        raise ConfigError(
            f"{where}: expected a DDS domain id, an integer from 0 to {MAX_DOMAIN_ID}, got {value!r}"
        )
    return value


def parse_ros2(doc: Table, path: Path) -> Ros2Config | None:
    """``[ros2]`` of ``doc`` (the file ``path``), None when absent; ConfigError naming the
    file and key for a bad value, or naming the extra when cyclonedds is not installed."""
    if "ros2" not in doc.doc:
        return None
    t = doc.table("ros2")
    t.only({"namespace", "domain_id", "output"})
    namespace = t.string("namespace", "ftsensord").strip("/")
    if not is_ros_name(namespace):
        raise t.fail(
            "namespace",
            "a ROS 2 name: tokens of letters, digits and underscores separated by /, "
            "none starting with a digit",
            namespace,
        )
    domain_id = t.integer(
        "domain_id",
        0 if "domain_id" in t.doc else default_domain_id(),
        low=0,
        high=MAX_DOMAIN_ID,
        what=f"a DDS domain id, 0 to {MAX_DOMAIN_ID}",
    )
    output = t.string("output", Ros2Config.output)
    if output not in OUTPUTS:
        raise t.fail("output", " or ".join(f'"{o}"' for o in OUTPUTS), output)
    needs_cyclonedds(f"{path}: ros2: the ROS 2 output", " (or remove the [ros2] table)")
    return Ros2Config(namespace, domain_id, output)


def is_ros_name(name: str) -> bool:
    """Whether ``name`` (no slash at either end) is a ROS 2 name's tokens joined by /."""
    return all(_TOKEN.fullmatch(token) and "__" not in token for token in name.split("/"))


def needs_cyclonedds(who: str, hint: str = "") -> None:
    """ConfigError naming the extra when Cyclone DDS's Python binding is not installed."""
    if importlib.util.find_spec("cyclonedds") is None:
        raise ConfigError(
            f"{who} needs Eclipse Cyclone DDS's Python binding: pip install 'ftsensord[ros2]'{hint}"
        )
