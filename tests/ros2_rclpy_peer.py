"""A ROS 2 node written as a ROS 2 user writes one (rclpy, the message packages, the default
rmw), run by a distribution's own Python (tests/ros2_venvs.py makes it): ``python
ros2_rclpy_peer.py DOMAIN STEPS_JSON``. Each step prints one JSON line on stdout (rclpy's
own logging goes to stderr). Nothing here comes from ftsensord: what it sees is what any
ROS 2 node on the same domain sees.

Steps (``do``): ``graph`` (node, topic and publisher listing), ``read`` (subscribe and take
``count`` messages a topic, with the default profile or SensorDataQoS), ``publish``
(QuaternionStamped, Imu, Empty), ``tare-topic`` (Empty, then /diagnostics until every sensor
says it is tared), ``trigger`` (std_srvs/srv/Trigger called by a service client), ``spin``
(stay on the graph, subscribed, for ``seconds``), ``stamps`` (each message's stamp and
arrival, for benchmarks/performance/ros2_latency.py).
"""

from __future__ import annotations

import json
import os
import sys
import time
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import QuaternionStamped, WrenchStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import Imu
from std_msgs.msg import Empty
from std_srvs.srv import Trigger

TYPES = {
    "WrenchStamped": WrenchStamped,
    "DiagnosticArray": DiagnosticArray,
    "QuaternionStamped": QuaternionStamped,
    "Imu": Imu,
    "Empty": Empty,
}
DEFAULT = QoSProfile(
    depth=10
)  # rclpy's default publisher/subscriber profile: reliable, volatile, keep last 10


def plain(msg: Any) -> Any:
    """A message as JSON values (fields by name, arrays as lists)."""
    if hasattr(msg, "get_fields_and_field_types"):
        return {name: plain(getattr(msg, name)) for name in msg.get_fields_and_field_types()}
    if isinstance(msg, (list, tuple)) or hasattr(msg, "tolist"):
        return [plain(v) for v in (msg.tolist() if hasattr(msg, "tolist") else msg)]
    if isinstance(msg, bytes):
        return list(msg)
    return msg


def spin_until(node: Node, done: Any, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if done():
            return True
        rclpy.spin_once(node, timeout_sec=0.02)
    return bool(done())


def endpoint(info: Any) -> dict[str, Any]:
    return {
        "node_name": info.node_name,
        "node_namespace": info.node_namespace,
        "topic_type": info.topic_type,
        "reliability": info.qos_profile.reliability.name.lower(),
        "durability": info.qos_profile.durability.name.lower(),
    }


def graph(node: Node, step: dict) -> None:
    """The graph once ``node_fqn`` is listed and each of ``topics`` has a publisher (or
    ``timeout_s`` passed), and each publisher is that node's (or ``attribution_s`` more
    passed: discovery tells a publisher before the node that has it): nodes, topics with
    their types, each topic's publishers and each of ``subscribed``'s subscriptions."""
    want_ns, _, want_name = step["node_fqn"].rpartition("/")
    want_ns = want_ns or "/"

    def listed() -> bool:
        return (want_name, want_ns) in node.get_node_names_and_namespaces() and all(
            node.get_publishers_info_by_topic(t) for t in step["topics"]
        )

    def attributed() -> bool:
        return all(
            any(
                (p.node_name, p.node_namespace) == (want_name, want_ns)
                for p in node.get_publishers_info_by_topic(t)
            )
            for t in step["topics"]
        )

    spin_until(node, listed, step.get("timeout_s", 20.0))
    spin_until(node, attributed, step.get("attribution_s", 3.0))
    print(
        json.dumps(
            {
                "nodes": [list(n) for n in node.get_node_names_and_namespaces()],
                "topics": {name: types for name, types in node.get_topic_names_and_types()},
                "publishers": {
                    t: [endpoint(p) for p in node.get_publishers_info_by_topic(t)] for t in step["topics"]
                },
                "subscribers": {
                    t: [endpoint(p) for p in node.get_subscriptions_info_by_topic(t)]
                    for t in step.get("subscribed", [])
                },
            }
        ),
        flush=True,
    )


def read(node: Node, step: dict) -> None:
    """``count`` messages of each of ``topics`` (name: type) as they came, each with its
    arrival time (UNIX s); ``qos``: ``default`` or ``sensor_data``."""
    qos = qos_profile_sensor_data if step.get("qos") == "sensor_data" else DEFAULT
    got: dict[str, list] = {t: [] for t in step["topics"]}

    def keep(topic: str) -> Any:
        def take(msg: Any) -> None:
            if len(got[topic]) < step["count"]:
                got[topic].append({**plain(msg), "received": time.time()})

        return take

    subs = [node.create_subscription(TYPES[kind], t, keep(t), qos) for t, kind in step["topics"].items()]
    spin_until(node, lambda: all(len(v) >= step["count"] for v in got.values()), step.get("timeout_s", 20.0))
    for sub in subs:
        node.destroy_subscription(sub)
    for t, messages in got.items():
        print(json.dumps({"topic": t, "messages": messages}), flush=True)


def message(kind: str, m: dict) -> Any:
    msg = TYPES[kind]()
    if kind == "Empty":
        return msg
    msg.header.stamp.sec, msg.header.stamp.nanosec = m["stamp"]
    msg.header.frame_id = m.get("frame_id", "")
    q = msg.quaternion if kind == "QuaternionStamped" else msg.orientation
    q.x, q.y, q.z, q.w = m["q_xyzw"]
    if kind == "Imu":
        msg.orientation_covariance[0] = m.get("covariance0", 0.0)
    return msg


def wait_subscribed(node: Node, publisher: Any, timeout_s: float = 10.0) -> bool:
    return spin_until(node, lambda: publisher.get_subscription_count() > 0, timeout_s)


def publish(node: Node, step: dict) -> None:
    """``message`` on ``topic``, ``times`` times ``period_s`` apart, once a subscriber is matched."""
    pub = node.create_publisher(TYPES[step["type"]], step["topic"], DEFAULT)
    matched = wait_subscribed(node, pub)
    msg = message(step["type"], step.get("message", {}))
    for _ in range(step.get("times", 1)):
        pub.publish(msg)
        spin_until(node, lambda: False, step.get("period_s", 0.0))
    spin_until(node, lambda: False, 0.2)  # reliable: the last ones acknowledged before the node goes
    print(json.dumps({"published": step["topic"], "matched": matched}), flush=True)


def orienting(node: Node, topics: list[str]) -> Any:
    """The identity orientation on each of ``topics`` at 100 Hz (a timer of the node's), once
    every publisher is matched; the timer (cancel it to stop)."""
    pubs = [node.create_publisher(QuaternionStamped, t, qos_profile_sensor_data) for t in topics]
    for p in pubs:
        wait_subscribed(node, p)

    def tick() -> None:
        msg = QuaternionStamped()
        msg.header.stamp = node.get_clock().now().to_msg()
        msg.quaternion.w = 1.0
        for p in pubs:
            p.publish(msg)

    timer = node.create_timer(0.01, tick)
    spin_until(node, lambda: False, 0.3)  # a few in: the daemon's newest orientation fresh
    return timer


def tare_topic(node: Node, step: dict) -> None:
    """std_msgs/msg/Empty on ``topic`` with orientations coming, then /diagnostics until every
    sensor says it is tared (the tare takes 100 samples: 1 s at 100 Hz, more on a loaded host)."""
    pub = node.create_publisher(Empty, step["topic"], DEFAULT)
    said: list[bool] = []

    def diagnosed(msg: DiagnosticArray) -> None:
        tared = [kv.value for s in msg.status for kv in s.values if kv.key == "tared"]
        said.append(bool(tared) and all(v == "True" for v in tared))

    node.create_subscription(DiagnosticArray, "/diagnostics", diagnosed, DEFAULT)
    matched = wait_subscribed(node, pub)
    timer = orienting(node, step.get("orient", []))
    pub.publish(Empty())
    tared = spin_until(node, lambda: bool(said) and said[-1], step.get("timeout_s", 20.0))
    timer.cancel()
    print(
        json.dumps(
            {"published": step["topic"], "matched": matched, "tared": tared, "diagnostics": len(said)}
        ),
        flush=True,
    )


def trigger(node: Node, step: dict) -> None:
    """std_srvs/srv/Trigger on ``name`` as a ROS 2 user calls it: wait for the service, call, wait
    for the answer (each up to ``timeout_s``)."""
    client = node.create_client(Trigger, step["name"])
    available = client.wait_for_service(timeout_sec=step.get("timeout_s", 5.0))
    timer = orienting(node, step.get("orient", [])) if available else None
    out: dict[str, Any] = {"service": step["name"], "available": available, "answered": False}
    if available:
        future = client.call_async(Trigger.Request())
        spin_until(node, future.done, step.get("timeout_s", 5.0))
        if future.done():
            out.update(answered=True, success=future.result().success, message=future.result().message)
    if timer is not None:
        timer.cancel()
    print(json.dumps(out), flush=True)


def spin(node: Node, step: dict) -> None:
    """On the graph for ``seconds``, subscribed to ``topics`` (name: type) with the default profile."""
    for t, kind in step.get("topics", {}).items():
        node.create_subscription(TYPES[kind], t, lambda _: None, DEFAULT)
    spin_until(node, lambda: False, step["seconds"])
    print(json.dumps({"spun": step["seconds"]}), flush=True)


def stamps(node: Node, step: dict) -> None:
    """Each WrenchStamped on ``topic`` until ``until`` (UNIX s): its stamp and when the callback
    had it (UNIX s), as an rclpy user's callback has a message (deserialized into its object)."""
    qos = qos_profile_sensor_data if step.get("qos") == "sensor_data" else DEFAULT
    got: list[tuple[float, float]] = []
    node.create_subscription(
        WrenchStamped,
        step["topic"],
        lambda m: got.append((m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, time.time())),
        qos,
    )
    while time.time() < step["until"]:
        rclpy.spin_once(node, timeout_sec=0.1)
    print(json.dumps({"topic": step["topic"], "stamps": got}), flush=True)


def main() -> int:
    os.environ["ROS_DOMAIN_ID"] = sys.argv[1]  # read by rclpy.init
    steps = json.loads(sys.argv[2])
    rclpy.init()
    node = rclpy.create_node(os.environ.get("PEER_NODE", "ftsensord_test_peer"))
    try:
        for step in steps:
            {
                "graph": graph,
                "read": read,
                "publish": publish,
                "tare-topic": tare_topic,
                "trigger": trigger,
                "spin": spin,
                "stamps": stamps,
            }[step["do"]](node, step)
    finally:
        node.destroy_node()
        rclpy.shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
