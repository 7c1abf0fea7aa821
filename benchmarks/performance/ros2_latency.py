"""What the ROS 2 bridge adds: latency from a sample's stamp to a DDS subscriber, against ZeroMQ's.

One daemon (`ftsensord run`, the packaged simulated configuration: 16 chips in real time,
100 Hz, five wrench streams; ``--realtime 50`` as the systemd unit runs it, ``--fifo 0``: at
the normal priority) runs throughout, and three subscribers to ``wrench/sensor1``, each a
process of its own: ZeroMQ, DDS best effort (SensorDataQoS) and DDS reliable (ROS's default
QoS). Each is the minimal loop doing the same work: wait (ZeroMQ's poll; a DDS waitset, as
rclcpp's executor waits), take the message's bytes, unpack the stamp from them, read the
clock; no message object is built on either side (a ROS 2 node deserializes in C, not in
Python). The variants run in segments of ``--seconds``, interleaved in ``--rounds`` rounds,
so the host's load falls on each alike:

- ``none``: no bridge (ZeroMQ's own figure);
- ``zmq3``: no bridge, two more ZeroMQ subscribers: three processes woken by each sample, as
  with the bridge and its two DDS subscribers (the share of the subscribers' own contention);
- ``bridge``: ``ftsensord ros2 --config`` as `run` starts it under a daemon at the normal priority;
- ``bridge-rt``: the same with ``--realtime 1`` (its forwarding thread SCHED_FIFO 1), as
  `run` starts it under a real-time daemon.

A receipt's delay is the subscriber's wall clock minus the sample's stamp (``t_wall``,
DDS's header.stamp): one host, one clock. Per segment, from the daemon: its CPU per cycle
(/proc), its start jitter and publish time p99 (`status`, the last 1000 cycles), missed
cycles. ``--split`` runs the bridge inside this benchmark instead (the same `Bridge`, with
clocks read where a frame arrives and around its DDS write) and breaks the DDS path into
hops. ``--in-loop`` sets, a daemon started for each segment, no DDS at all (``none``: the
daemon and the ZeroMQ subscriber alone), the bridge process as `run` starts it
(``bridge-rt``, ``bridge`` under ``--fifo 0``) and ``[ros2] output = "in-loop"`` (the loop
thread's own DDS writes, after the cycle's ZeroMQ sends): each one's latencies, the loop's
start jitter and cycle time, the daemon's CPU (and the bridge process's).

``--alone``, a daemon started for each segment, one subscriber process in each (`ALONE`), so
none competes with another for the core the loop thread leaves: ``none`` (no [ros2]: plain
ZeroMQ), ``zmq-alone`` (the ZeroMQ subscriber), ``dds-be-alone``, ``dds-rel-alone`` (one DDS
subscriber, best effort or reliable, no ZeroMQ one). All but ``none`` run ``[ros2] output =
"in-loop"``; with no DDS reader it writes no wrench, so ``zmq-alone`` measures the daemon as
shipped (readers asked, inputs polled, /diagnostics once a second) without the one wrench
write a cycle: that write comes after the cycle's ZeroMQ sends, so it cannot delay the
sample measured, and a DDS reader to make it happen would be the competing process this mode
removes (``none`` shows what the rest of the output costs ZeroMQ). It prints each DDS
variant's p99 minus ``zmq-alone``'s (and ``none``'s), pooled and round by round.
``--rclpy DISTRO`` adds two variants to ``--alone``: ``rclpy-be-alone`` and ``rclpy-rel-alone``,
one rclpy node a segment (tests/ros2_rclpy_peer.py, the distribution's own environment from
tests/ros2_venvs.py, made on first use; rmw_fastrtps_cpp), its callback handed each
WrenchStamped as a ROS 2 user's is: the message deserialized into its Python object, the
clock read in the callback. Beside the minimal DDS subscriber it shows what a real ROS 2
node adds on the same path.
DDS stays on the loopback interface (CYCLONEDDS_URI; the rclpy node's discovery, this host).

    python -m benchmarks.performance.ros2_latency --seconds 10 --rounds 3 [--fifo 50] [--split | \
        --in-loop | --alone [--rclpy jazzy]]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import struct
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zmq

from ftsensord.client import ControlClient
from ftsensord.daemon.ros2child import bridge_command
from ftsensord.protocol import wire
from ftsensord.testing.harness import cpu_seconds, packaged_config, start_daemon, stop

SETTLE_S = 3.0  # a bridge started (imports, participant), discovered, its first samples through
DOMAIN = 200 + os.getpid() % 30  # 200-229: clear of ROS's default 0 and of the tests' 100-199
URI = (
    "<CycloneDDS><Domain Id='any'><General><Interfaces><NetworkInterface address='127.0.0.1'/></Interfaces>"
    "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
    "<MaxAutoParticipantIndex>30</MaxAutoParticipantIndex><Peers><Peer address='127.0.0.1'/></Peers>"
    "</Discovery></Domain></CycloneDDS>"
)
TOPIC = "wrench/sensor1"
T_WALL = struct.Struct("<d")
T_WALL_AT = struct.calcsize(wire.HEADER.format[:7])  # the header's t_wall: after "<HBBIQd" (magic ... t_mono)
CDR_STAMP = struct.Struct("<iI")  # header.stamp, right after CDR's 4-byte encapsulation


def zmq_listen(endpoint: str, stop_at: float, out: mp.Queue) -> None:
    sock = zmq.Context().socket(zmq.SUB)
    sock.setsockopt(zmq.SUBSCRIBE, TOPIC.encode() + b"\0")
    sock.connect(endpoint)
    got, offset = [], len(TOPIC) + 1 + T_WALL_AT
    while time.time() < stop_at:
        if sock.poll(100):
            frame = sock.recv()
            got.append((T_WALL.unpack_from(frame, offset)[0], time.time()))
    out.put(("zmq", got))


def dds_listen(topic: str, reliable: bool, stop_at: float, out: mp.Queue) -> None:
    os.environ["CYCLONEDDS_URI"] = URI
    from cyclonedds._clayer import ddspy_take
    from cyclonedds.core import InstanceState, Policy, Qos, ReadCondition, SampleState, ViewState, WaitSet
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    from ftsensord.ros2.msgs import WrenchStamped

    dp = DomainParticipant(DOMAIN)
    qos = Qos(
        Policy.Reliability.Reliable(10**9) if reliable else Policy.Reliability.BestEffort,
        Policy.History.KeepLast(10 if reliable else 5),
    )  # ROS's default profile; SensorDataQoS
    reader = DataReader(dp, Topic(dp, topic, WrenchStamped), qos)
    waitset = WaitSet(dp)
    mask = SampleState.Any | ViewState.Any | InstanceState.Any
    waitset.attach(ReadCondition(reader, mask))
    got = []
    while time.time() < stop_at:
        waitset.wait(100_000_000)
        for data, info in ddspy_take(reader._ref, mask, 16):  # the CDR bytes, as DataReader.take has them
            if info.valid_data:
                sec, nanosec = CDR_STAMP.unpack_from(data, 4)
                got.append((sec + nanosec * 1e-9, time.time()))
    out.put((f"dds {'reliable' if reliable else 'best effort'}", got))


class RclpyListener:
    """An rclpy node (the ``distro`` environment's Python) taking ``topic``'s WrenchStamped
    until ``stop_at``; a process as `listener`'s are (start, join), its receipts on ``out``."""

    def __init__(self, distro: str, topic: str, reliable: bool, stop_at: float, out: mp.Queue):
        self.name = f"rclpy {'reliable' if reliable else 'best effort'}"
        self.distro, self.topic, self.reliable, self.stop_at, self.out = distro, topic, reliable, stop_at, out

    def start(self) -> None:
        from tests.ros2_venvs import PEER, peer_env, python_of

        step = {
            "do": "stamps",
            "topic": self.topic,
            "qos": "default" if self.reliable else "sensor_data",
            "until": self.stop_at,
        }
        proc = subprocess.Popen(
            [str(python_of(self.distro)), str(PEER), str(DOMAIN), json.dumps([step])],
            env=peer_env(),
            stdout=subprocess.PIPE,
            text=True,
        )

        def collect() -> None:  # the receipts on the queue when the node ends, as a listener process's
            out, _ = proc.communicate(timeout=self.stop_at - time.time() + 120)
            self.out.put((self.name, [tuple(p) for p in json.loads(out.splitlines()[-1])["stamps"]]))

        self.thread = threading.Thread(target=collect, daemon=True)
        self.thread.start()

    def join(self) -> None:
        self.thread.join()


def split_bridge(folder: Path, realtime: int, stop_at: float, out: mp.Queue) -> None:
    """The bridge's own `Bridge` in this process, the clock read as each sensor1 frame arrives
    and around its DDS write; (stamp, arrived, write called, write returned) each."""
    os.environ["CYCLONEDDS_URI"] = URI
    from ftsensord.ros2.bridge import Bridge

    control = ControlClient(f"ipc://{folder / 'control'}", timeout_s=5)
    bridge = Bridge(
        "bench",
        DOMAIN,
        f"ipc://{folder / 'wrench'}",
        control,
        control.status(),
        None,
        lambda: time.time() > stop_at,
        realtime,
    )
    got, arrived = [], [0.0]
    forward, publish = bridge.forward, bridge.node.publish_wrench

    def timed_forward(frame: bytes):
        arrived[0] = time.time()
        return forward(frame)

    def timed_publish(topic: str, t_wall: float, values: bytes) -> None:
        t = time.time()
        publish(topic, t_wall, values)
        if topic == TOPIC:
            got.append((t_wall, arrived[0], t, time.time()))

    bridge.forward, bridge.node.publish_wrench = timed_forward, timed_publish
    bridge.run()
    out.put(("bridge", got))


def segment(
    variant: str,
    config: Path,
    folder: Path,
    seconds: float,
    queue: mp.Queue,
    control: ControlClient,
    pid: int,
) -> dict:
    """One variant for ``seconds`` after `SETTLE_S`; the window counted and the daemon's figures."""
    child = None
    if variant in ("bridge", "bridge-rt"):
        child = subprocess.Popen(
            bridge_command(config, 1 if variant == "bridge-rt" else 0),
            env={**os.environ, "CYCLONEDDS_URI": URI, "XDG_RUNTIME_DIR": str(folder.parent)},
            stdout=subprocess.DEVNULL,
        )
    elif variant.startswith("split"):
        child = mp.Process(
            target=split_bridge,
            args=(folder, 1 if variant == "split-rt" else 0, time.time() + SETTLE_S + seconds, queue),
        )
        child.start()
    elif variant == "zmq3":  # two more ZeroMQ subscribers: as many woken a sample as with the two DDS ones
        child = [
            mp.Process(
                target=zmq_listen,
                args=(f"ipc://{folder / 'wrench'}", time.time() + SETTLE_S + seconds, mp.Queue()),
            )
            for _ in range(2)
        ]
        for c in child:
            c.start()
    time.sleep(SETTLE_S)
    s0, cpu0, t0 = control.status(), cpu_seconds(pid), time.time()
    time.sleep(seconds)
    s1, cpu1, t1 = control.status(), cpu_seconds(pid), time.time()
    got = None
    if isinstance(child, subprocess.Popen):
        child.terminate()
        child.wait(timeout=20)
    elif isinstance(child, list):
        for c in child:
            c.kill()  # their receipts are not counted
            c.join()
    elif child is not None:
        got = queue.get(timeout=60)[1]
        child.join()
    cycles = s1["cycles"] - s0["cycles"]
    return {
        "variant": variant,
        "window": (t0, t1),
        "cpu_us": (cpu1 - cpu0) / cycles * 1e6,
        "cycles": cycles,
        "missed": s1["missed_cycles"] - s0["missed_cycles"],
        "jitter_p99": s1["jitter_us"]["p99"],
        "publish_p99": s1["publish_us"]["p99"],
        "load": os.getloadavg()[0],
        "bridge": got,
    }


#: The subscribers a segment runs, by the names their receipts come back under.
EVERY = ("zmq", "dds best effort", "dds reliable")
#: --alone: one subscriber process a segment.
ALONE = {
    "none": ("zmq",),
    "zmq-alone": ("zmq",),
    "dds-be-alone": ("dds best effort",),
    "dds-rel-alone": ("dds reliable",),
}
#: --alone --rclpy: an rclpy node a segment.
RCLPY = {"rclpy-be-alone": ("rclpy best effort",), "rclpy-rel-alone": ("rclpy reliable",)}
#: --rclpy's distribution (`listener` starts its node).
RCLPY_DISTRO: list[str] = []


def listener(name: str, folder: Path, stop_at: float, queue: mp.Queue) -> mp.Process:
    """The subscriber process ``name`` (one of `EVERY`) to the daemon whose runtime folder is ``folder``."""
    if name == "zmq":
        return mp.Process(target=zmq_listen, args=(f"ipc://{folder / 'wrench'}", stop_at, queue))
    if name.startswith("rclpy"):
        return RclpyListener(RCLPY_DISTRO[0], f"/bench/{TOPIC}", name == "rclpy reliable", stop_at, queue)  # type: ignore[return-value]
    return mp.Process(target=dds_listen, args=(f"rt/bench/{TOPIC}", name == "dds reliable", stop_at, queue))


def segment_config(variant: str, path: Path) -> Path:
    """The packaged configuration at ``path``, with the [ros2] table a daemon of ``variant`` runs:
    ``output = "bridge"`` (``bridge*``), ``"in-loop"`` (``in-loop``, ``*-alone``) or none (``none``)."""
    config = packaged_config(path)
    if variant.startswith("bridge") or variant == "in-loop" or variant.endswith("-alone"):
        output = "bridge" if variant.startswith("bridge") else "in-loop"
        config.write_text(
            config.read_text() + f'\n[ros2]\nnamespace = "bench"\ndomain_id = {DOMAIN}\noutput = "{output}"\n'
        )
    return config


def daemon_segment(variant: str, seconds: float, fifo: int, listen: tuple[str, ...] | None = None) -> dict:
    """--in-loop, --alone: a daemon of its own for the segment (`segment_config`) and
    ``listen``, the subscribers for the segment (default:
    all of `EVERY`, ZeroMQ's alone for ``none``)."""
    listen = listen or (("zmq",) if variant == "none" else EVERY)
    with tempfile.TemporaryDirectory() as tmp:
        config = segment_config(variant, Path(tmp) / "ftsensord.toml")
        proc, notify = start_daemon(
            config, Path(tmp), args=["--realtime", str(fifo)] if fifo else [], env={"CYCLONEDDS_URI": URI}
        )
        folder = Path(tmp) / "ftsensord"
        try:
            queue: mp.Queue = mp.Queue()
            stop_at = time.time() + SETTLE_S + seconds + 1
            listeners = [listener(name, folder, stop_at, queue) for name in listen]
            for p in listeners:
                p.start()
            control = ControlClient(f"ipc://{folder / 'control'}", timeout_s=5)
            time.sleep(SETTLE_S)
            children = [
                int(c) for c in Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
            ]
            s0, cpu0, t0 = control.status(), cpu_seconds(proc.pid), time.time()
            child0 = sum(cpu_seconds(c) for c in children)
            time.sleep(seconds)
            s1, cpu1, t1 = control.status(), cpu_seconds(proc.pid), time.time()
            child1 = sum(cpu_seconds(c) for c in children)
            receipts = dict(queue.get(timeout=60) for _ in listeners)
            for p in listeners:
                p.join()
        finally:
            stop(proc, notify)
    cycles = s1["cycles"] - s0["cycles"]
    return {
        "variant": variant,
        "window": (t0, t1),
        "cpu_us": (cpu1 - cpu0) / cycles * 1e6,
        "cycles": cycles,
        "bridge_cpu_us": (child1 - child0) / cycles * 1e6 if children else None,
        "missed": s1["missed_cycles"] - s0["missed_cycles"],
        "jitter_p99": s1["jitter_us"]["p99"],
        "publish_p99": s1["publish_us"]["p99"],
        "cycle_p99": s1["cycle_us"]["p99"],
        "load": os.getloadavg()[0],
        "bridge": None,
        "receipts": receipts,
    }


def pct(d: np.ndarray) -> str:
    p50, p99 = np.percentile(d, [50, 99])
    return f"{len(d)} samples, p50 {p50:.0f} us, p99 {p99:.0f} us, max {d.max():.0f} us"


def hops(segments: list[dict], receipts: dict[str, list]) -> None:
    """--split: each sample's way in hops, and which hop its p99 belongs to."""
    zmq_at = dict(receipts["zmq"])
    dds_at = dict(receipts["dds reliable"])
    rows = [
        (s, zmq_at[s], a, w0, w1, dds_at[s])
        for seg in segments
        for s, a, w0, w1 in seg["bridge"]
        if seg["window"][0] <= s < seg["window"][1] and s in zmq_at and s in dds_at
    ]
    t = np.array(rows)
    names = [
        "stamp -> ZeroMQ subscriber",
        "stamp -> bridge has the frame",
        "frame -> write called",
        "write (WrenchStamped to DDS)",
        "write returned -> DDS reliable subscriber",
        "stamp -> DDS subscriber",
    ]
    parts = [
        t[:, 1] - t[:, 0],
        t[:, 2] - t[:, 0],
        t[:, 3] - t[:, 2],
        t[:, 4] - t[:, 3],
        t[:, 5] - t[:, 4],
        t[:, 5] - t[:, 0],
    ]
    top = parts[-1] >= np.percentile(parts[-1], 99)
    for name, d in zip(names, parts):
        d = d * 1e6
        print(f"    {name}: {pct(d)}; mean in the slowest 1 % of DDS receipts {d[top].mean():.0f} us")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="a segment's counted length (s)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument(
        "--fifo", type=int, default=50, help="the daemon's --realtime (0: the normal priority)"
    )
    parser.add_argument(
        "--split", action="store_true", help="the bridge inside the benchmark, its hops timed"
    )
    parser.add_argument(
        "--in-loop",
        action="store_true",
        help="no DDS, the bridge process and the loop's own DDS writes (a daemon a segment)",
    )
    parser.add_argument(
        "--alone",
        action="store_true",
        help="in-loop, one subscriber process a segment: ZeroMQ, DDS best effort, DDS reliable",
    )
    parser.add_argument(
        "--rclpy",
        metavar="DISTRO",
        choices=["jazzy", "kilted"],
        help="--alone: an rclpy node of this ROS 2 distribution too, best effort and reliable",
    )
    args = parser.parse_args()
    if args.rclpy:
        ALONE.update(RCLPY)
        RCLPY_DISTRO.append(args.rclpy)
    variants = (
        ["none", "split", "split-rt"]
        if args.split
        else ["none", "bridge-rt", "in-loop"]
        if args.in_loop
        else list(ALONE)
        if args.alone
        else ["none", "zmq3", "bridge", "bridge-rt"]
    )
    if not args.fifo and args.in_loop:
        # at the normal priority, as `run` starts the bridge then
        variants = [v.replace("bridge-rt", "bridge") for v in variants]
    elif not args.fifo:
        variants = [v for v in variants if not v.endswith("-rt")]  # `run` gives no FIFO to the bridge then
    print(
        f"load {os.getloadavg()[0]:.2f} at start; {args.rounds} rounds of {', '.join(variants)}, "
        f"{args.seconds:g} s each; daemon --realtime {args.fifo}; {TOPIC} at 100 Hz"
    )
    if args.in_loop or args.alone:
        segments = [
            daemon_segment(v, args.seconds, args.fifo, ALONE[v] if args.alone else None)
            for _ in range(args.rounds)
            for v in variants
        ]
        receipts: dict[str, list] = {}
        for seg in segments:
            for name, got in seg["receipts"].items():
                receipts.setdefault(name, []).extend(got)
        report(variants, segments, receipts)
        if args.alone:
            for v in ("dds-be-alone", "dds-rel-alone", *(RCLPY if args.rclpy else ())):
                for base in ("zmq-alone", "none"):
                    pooled, by_round = p99_above(segments, v, base)
                    print(
                        f"{v} p99 minus {base}'s: {pooled:+.0f} us pooled; by round "
                        + " ".join(f"{d:+.0f}" for d in by_round)
                        + " us"
                    )
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        config = packaged_config(Path(tmp) / "ftsensord.toml")
        config.write_text(config.read_text() + f'\n[ros2]\nnamespace = "bench"\ndomain_id = {DOMAIN}\n')
        # [ros2] for the bridges' --config; the daemon's own is started from a copy without it
        daemon_config = packaged_config(Path(tmp) / "daemon.toml")
        proc, notify = start_daemon(
            daemon_config, Path(tmp), args=["--realtime", str(args.fifo)] if args.fifo else []
        )
        folder = Path(tmp) / "ftsensord"
        try:
            queue: mp.Queue = mp.Queue()
            stop_at = time.time() + 5 + args.rounds * len(variants) * (args.seconds + SETTLE_S + 3)
            listeners = [listener(name, folder, stop_at, queue) for name in EVERY]
            for p in listeners:
                p.start()
            control = ControlClient(f"ipc://{folder / 'control'}", timeout_s=5)
            segments = [
                segment(v, config, folder, args.seconds, queue, control, proc.pid)
                for _ in range(args.rounds)
                for v in variants
            ]
            receipts = dict(queue.get(timeout=stop_at - time.time() + 60) for _ in listeners)
            for p in listeners:
                p.join()
        finally:
            stop(proc, notify)
    report(variants, segments, receipts)
    return 0


def p99_above(segments: list[dict], variant: str, base: str) -> tuple[float, list[float]]:
    """``variant``'s delay p99 minus ``base``'s (us): pooled over their segments, and each
    ``variant`` segment against the ``base`` segment of the same round (the n-th of each)."""

    def p99(segs: list[dict]) -> float:
        return float(
            np.percentile(
                [
                    r - s
                    for m in segs
                    for got in m["receipts"].values()
                    for s, r in got
                    if m["window"][0] <= s < m["window"][1]
                ],
                99,
            )
            * 1e6
        )

    mine, theirs = ([s for s in segments if s["variant"] == v] for v in (variant, base))
    return p99(mine) - p99(theirs), [p99([a]) - p99([b]) for a, b in zip(mine, theirs, strict=True)]


def report(variants: list[str], segments: list[dict], receipts: dict[str, list]) -> None:
    for v in variants:
        mine = [s for s in segments if s["variant"] == v]
        print(
            f"{v}: daemon CPU {np.median([s['cpu_us'] for s in mine]):.0f} us a cycle (median of segments), "
            f"missed {sum(s['missed'] for s in mine)} of {sum(s['cycles'] for s in mine)} cycles; start jitter "
            f"p99 {max(s['jitter_p99'] for s in mine):.0f} us, "
            f"publish p99 {max(s['publish_p99'] for s in mine):.0f} us "
            f"(worst segment); load {min(s['load'] for s in mine):.2f}-{max(s['load'] for s in mine):.2f}"
        )
        if "cycle_p99" in mine[0]:
            bridge = [s["bridge_cpu_us"] for s in mine if s["bridge_cpu_us"] is not None]
            print(
                "  start jitter p99 by segment "
                + " ".join(f"{s['jitter_p99']:.0f}" for s in mine)
                + " us; cycle p99 by segment "
                + " ".join(f"{s['cycle_p99']:.0f}" for s in mine)
                + " us"
                + (f"; the bridge process's CPU {np.median(bridge):.0f} us a cycle" if bridge else "")
            )
        for name, got in receipts.items():
            d = (
                np.array([r - s for s, r in got if any(m["window"][0] <= s < m["window"][1] for m in mine)])
                * 1e6
            )
            if len(d):
                # and each segment's p99: one segment whose subscriber the host starved moves the pooled p99
                each = [[r - s for s, r in got if m["window"][0] <= s < m["window"][1]] for m in mine]
                print(
                    f"  {name}: {pct(d)}; p99 by segment "
                    + " ".join(f"{np.percentile(e, 99) * 1e6:.0f}" for e in each if e)
                    + " us, samples by segment "
                    + " ".join(str(len(e)) for e in each)
                )
        if v.startswith("split"):
            hops(mine, receipts)
    print(f"load {os.getloadavg()[0]:.2f} at end")


if __name__ == "__main__":
    raise SystemExit(main())
