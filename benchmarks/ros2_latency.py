"""What the ROS 2 bridge adds: latency to a DDS subscriber against ZeroMQ's, and the daemon's CPU.

Starts `ftsensord run` on the packaged simulated configuration (16 chips in real time,
100 Hz) twice: without ``[ros2]``, then with it (`run` starts `ftsensord ros2`). In each
run, one ZeroMQ subscriber and (with ros2) ``--dds`` DDS subscribers (Cyclone DDS, best
effort and reliable alternately, each its own process, as separate ROS 2 nodes would be)
read ``wrench/sensor1`` for ``--seconds``. A receipt's delay is the subscriber's wall clock
at receipt minus the sample's stamp (``t_wall``, the header.stamp on DDS): one host, one
clock. The daemon's CPU (its own process; the bridge is another) per cycle and its missed
cycles, its start jitter and its publish time (p99 of the last 1000 cycles) come from /proc
and its status. DDS stays on the loopback interface (CYCLONEDDS_URI).

    python benchmarks/ros2_latency.py --seconds 30 [--dds 2]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ftsensord.client import ControlClient, Subscriber

sys.path.insert(0, str(Path(__file__).resolve().parent))
from launch import cpu_seconds, packaged_config, start_daemon, stop

SETTLE_S = 2.0  # the bridge up, discovery done, the first samples through before counting
DOMAIN = 200 + os.getpid() % 30  # 200-229: clear of ROS's default 0 and of the tests' 100-199
URI = ("<CycloneDDS><Domain Id='any'><General><Interfaces><NetworkInterface address='127.0.0.1'/></Interfaces>"
       "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
       "<MaxAutoParticipantIndex>30</MaxAutoParticipantIndex><Peers><Peer address='127.0.0.1'/></Peers>"
       "</Discovery></Domain></CycloneDDS>")


def zmq_listen(endpoint: str, seconds: float, out: mp.Queue) -> None:
    delays = []
    with Subscriber(endpoint, ["wrench/sensor1"]) as sub:
        start = time.monotonic()
        while time.monotonic() < start + SETTLE_S + seconds:
            s = sub.receive(timeout_s=0.1)
            t = time.time()
            if s is not None and time.monotonic() - start >= SETTLE_S:
                delays.append(t - s.t_wall)
    out.put(("zmq", delays))


def dds_listen(topic: str, reliable: bool, seconds: float, out: mp.Queue) -> None:
    os.environ["CYCLONEDDS_URI"] = URI
    from cyclonedds.core import Policy, Qos, ReadCondition, SampleState, ViewState, InstanceState, WaitSet
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    from ftsensord.ros2.msgs import WrenchStamped

    dp = DomainParticipant(DOMAIN)
    qos = Qos(Policy.Reliability.Reliable(10**9) if reliable else Policy.Reliability.BestEffort,
              Policy.History.KeepLast(10 if reliable else 5))
    reader = DataReader(dp, Topic(dp, topic, WrenchStamped), qos)
    ws = WaitSet(dp)
    ws.attach(ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Any))
    delays = []
    start = time.monotonic()
    while time.monotonic() < start + SETTLE_S + seconds:
        ws.wait(100_000_000)
        t = time.time()
        for m in reader.take(N=100):
            if time.monotonic() - start >= SETTLE_S and m.sample_info.valid_data:
                delays.append(t - (m.header.stamp.sec + m.header.stamp.nanosec * 1e-9))
    out.put((f"dds {'reliable' if reliable else 'best effort'}", delays))


def run(seconds: float, dds: int, ros2: bool) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        config = packaged_config(Path(tmp) / "ftsensord.toml")
        if ros2:
            config.write_text(config.read_text() + f'\n[ros2]\nnamespace = "bench"\ndomain_id = {DOMAIN}\n')
        proc, notify = start_daemon(config, Path(tmp), env={"CYCLONEDDS_URI": URI})
        folder = Path(tmp) / "ftsensord"
        try:
            queue: mp.Queue = mp.Queue()
            workers = [mp.Process(target=zmq_listen, args=(f"ipc://{folder / 'wrench'}", seconds, queue))]
            if ros2:
                workers += [mp.Process(target=dds_listen, args=("rt/bench/wrench/sensor1", i % 2 == 1, seconds, queue))
                            for i in range(dds)]
            for w in workers:
                w.start()
            time.sleep(SETTLE_S)
            control = ControlClient(f"ipc://{folder / 'control'}", timeout_s=5)
            s0, cpu0 = control.status(), cpu_seconds(proc.pid)
            results = dict(queue.get(timeout=seconds + 60) for _ in workers)
            s1, cpu1 = control.status(), cpu_seconds(proc.pid)
            for w in workers:
                w.join()
        finally:
            stop(proc, notify)
    cycles = s1["cycles"] - s0["cycles"]
    return {"results": results, "cpu_us_per_cycle": (cpu1 - cpu0) / cycles * 1e6, "cycles": cycles,
            "missed": s1["missed_cycles"] - s0["missed_cycles"], "rate": s1["achieved_rate_hz"],
            "jitter_p99": s1["jitter_us"]["p99"], "publish_p99": s1["publish_us"]["p99"]}


def in_loop_cost(streams: int = 5, cycles: int = 2000) -> float:
    """What the daemon's loop would spend a cycle (us) if it wrote to DDS itself: ``streams``
    wrench samples (the packaged configuration publishes five), each a WrenchStamped and its
    status, through the bridge's own `Ros2Node.publish`, with no reader (the least it costs)."""
    os.environ["CYCLONEDDS_URI"] = URI
    from ftsensord.ros2.node import Ros2Node
    from ftsensord.service import wire

    names = [f"wrench/s{i}" for i in range(streams)]
    node = Ros2Node("inloop", DOMAIN, {n: n for n in names}, [])
    values = np.arange(6.0)
    t0 = time.perf_counter()
    for seq in range(cycles):
        for n in names:
            node.publish(wire.Sample(n, wire.KIND_WRENCH, seq, 0.0, time.time(), 0, values))
    return (time.perf_counter() - t0) / cycles * 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--dds", type=int, default=2, help="DDS subscribers (default 2)")
    parser.add_argument("--rounds", type=int, default=3, help="runs without and with [ros2], alternated (default 3)")
    args = parser.parse_args()
    print(f"load {os.getloadavg()[0]:.2f} at start; {args.rounds} rounds of {args.seconds:g} s a run, "
          f"wrench/sensor1 at 100 Hz")
    delays: dict[str, list[float]] = {}
    cpu: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(args.rounds):
        for ros2 in (False, True):
            r = run(args.seconds, args.dds, ros2)
            cpu[ros2].append(r["cpu_us_per_cycle"])
            print(f"{'with' if ros2 else 'without'} [ros2]: daemon CPU {r['cpu_us_per_cycle']:.0f} us a cycle over "
                  f"{r['cycles']} cycles, missed {r['missed']}, achieved {r['rate']:.2f} Hz; last 1000 cycles' "
                  f"start jitter p99 {r['jitter_p99']:.0f} us, publish p99 {r['publish_p99']:.0f} us; load "
                  f"{os.getloadavg()[0]:.2f}")
            for name, d in r["results"].items():
                d = np.array(d) * 1e6
                delays.setdefault(f"{name}{' (with [ros2])' if ros2 and name == 'zmq' else ''}", []).extend(d)
                print(f"  {name}: {len(d)} samples, stamp to receipt p50 {np.percentile(d, 50):.0f} us, "
                      f"p99 {np.percentile(d, 99):.0f} us, max {d.max():.0f} us")
    print("all rounds:")
    for name, d in delays.items():
        print(f"  {name}: {len(d)} samples, p50 {np.percentile(d, 50):.0f} us, p99 {np.percentile(d, 99):.0f} us, "
              f"max {np.max(d):.0f} us")
    print(f"  daemon CPU a cycle, median of the rounds: without {np.median(cpu[False]):.0f} us, "
          f"with {np.median(cpu[True]):.0f} us")
    print(f"DDS writes in the loop instead (5 wrench streams, WrenchStamped + status each, no reader): "
          f"{in_loop_cost():.0f} us a cycle")
    print(f"load {os.getloadavg()[0]:.2f} at end")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
