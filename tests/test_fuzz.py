"""Bad input on the control endpoint: 20,000 hostile messages (oversized numbers and
nesting among them), and the loop publishes on without a gap; a flood of clients does not
starve the loop. Real sockets (ipc), so the size limit and queue bounds are the service's."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import zmq

from ftsensord.config.file import load_config
from ftsensord.daemon.control import MAX_REQUEST
from ftsensord.daemon.daemon import Daemon
from ftsensord.daemon.run import make_sockets
from ftsensord.protocol import wire
from ftsensord.sim import VirtualClock, load_scene, simulated_bus

from .test_daemon import write_config

COMMANDS = ["status", "tare", "reload", "set", "launch", "", "STATUS", "tare ", "\u00e9\u00e8", "x" * 300]


def hostile(rng: np.random.Generator) -> bytes:
    kind = rng.integers(0, 11)
    if kind == 0:
        return rng.bytes(int(rng.integers(0, 200)))  # binary garbage
    if kind == 1:
        return b"[" * int(rng.integers(1, 50_000))  # nesting that breaks naive parsers
    if kind == 8:  # over Python's 4300-digit int limit: a plain ValueError killed the daemon
        return ('{"cmd":"status","n":-' + "7" * int(rng.integers(4_301, 60_000)) + "}").encode()
    if kind == 9:  # deep but complete nesting inside a valid request
        depth = int(rng.integers(2, 10_000))
        return ('{"cmd":"set","rate_hz":' + "[" * depth + "1" + "]" * depth + "}").encode()
    if kind == 10:  # a float literal far longer than any double needs
        return ('{"cmd":"tare","samples":1.' + "3" * int(rng.integers(101, 60_000)) + "e3}").encode()
    if kind == 2:
        return json.dumps(
            rng.normal(size=int(rng.integers(0, 20))).tolist()
        ).encode()  # valid JSON, not an object
    junk = [None, True, -1, 1e308, "x", [], {}, [1, [2]], {"a": {"b": 1}}, 10**30, float("nan")]
    request = {"cmd": COMMANDS[rng.integers(len(COMMANDS))]}
    for _ in range(int(rng.integers(0, 4))):
        key = ["samples", "sensor", "rate_hz", "averaging", "lowpass_hz", "path", "cmd"][rng.integers(7)]
        request[key] = junk[rng.integers(len(junk))]
    if kind == 3:
        request["cmd"] = junk[rng.integers(len(junk))]
    text = json.dumps(request)
    if kind == 4:
        text = text[: int(rng.integers(0, len(text)))]  # cut short
    return text.encode("utf-8", "surrogatepass")


def ask_status(ctx: zmq.Context, endpoint: str, daemon: Daemon) -> dict:
    """A status request from a fresh client, served as the loop would."""
    req = ctx.socket(zmq.REQ)
    req.connect(endpoint)
    req.send(b'{"cmd": "status"}')
    for _ in range(100):
        daemon.handle_control()
        if req.poll(10):
            break
    reply = json.loads(req.recv())
    req.close(linger=0)
    return reply


def test_twenty_thousand_hostile_requests_are_all_answered_and_publishing_stays_intact(tmp_path, zmq_context):
    config_path = write_config(
        tmp_path, extra=f'publish = "ipc://{tmp_path}/pub"\ncontrol = "ipc://{tmp_path}/ctl"'
    )
    config = load_config(config_path)
    clock = VirtualClock()
    bus = simulated_bus(load_scene(tmp_path / "scene.toml"), clock=clock, bus_hz=400e3, seed=2)
    ctx = zmq_context  # terminated at teardown, with any socket an assert left open
    pub, ctl, _ = make_sockets(ctx, config)
    daemon = Daemon(config, bus, pub, ctl, clock=clock.now, wall=lambda: 1.7e9 + clock.now())
    daemon.start()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"wrench/sensor1\0")
    sub.setsockopt(zmq.RCVHWM, 0)
    sub.connect(config.publish[0])
    client = ctx.socket(zmq.DEALER)
    client.setsockopt(zmq.LINGER, 0)
    client.setsockopt(zmq.SNDHWM, 0)
    client.connect(config.control)
    oversized = ctx.socket(zmq.DEALER)  # its own connection: ZeroMQ drops it with what it carried
    oversized.setsockopt(zmq.LINGER, 0)
    oversized.connect(config.control)
    rng = np.random.default_rng(7)
    sent = replies = errors = 0
    seqs: list[int] = []

    def collect() -> None:
        nonlocal replies, errors
        while client.poll(0):
            _, raw = client.recv_multipart()
            reply = json.loads(raw)
            assert set(reply) in ({"ok", "error"}, {"ok", "result"})
            replies += 1
            errors += not reply["ok"]

    for flood in range(200):
        for _ in range(100):
            payload = hostile(rng)
            assert len(payload) <= MAX_REQUEST
            client.send_multipart([b"", payload])
            sent += 1
        if flood == 50:
            oversized.send_multipart([b"", b"{" * (MAX_REQUEST + 10)])
        for _ in range(20):  # let the io thread deliver, serving as the loop does
            daemon.handle_control()
        deadline = clock.now() + daemon.period_s
        daemon.cycle()
        clock.wait_until(deadline)
        collect()
        while sub.poll(0):
            seqs.append(wire.decode(sub.recv()).seq)
    # What the last floods left queued, and tares still taking their samples: on a loaded
    # 2-core host the io thread can take seconds to deliver them (200 cycles were once short).
    drain_until = time.monotonic() + 30
    while replies + daemon.control.dropped < sent and time.monotonic() < drain_until:
        daemon.handle_control()
        deadline = clock.now() + daemon.period_s
        daemon.cycle()
        clock.wait_until(deadline)
        client.poll(10)
        collect()
    while sub.poll(100):
        seqs.append(wire.decode(sub.recv()).seq)
    assert sent == 20_000
    # Every request under the size limit answered, none lost: a reply is dropped (and counted)
    # only when ZeroMQ's queue to the client is full, which on a starved host (the io thread
    # behind by 1000 replies) happened to 10-61 of 20,000 here; the loop never blocks on it.
    assert replies + daemon.control.dropped == sent and daemon.control.dropped <= 0.01 * sent, (
        replies,
        daemon.control.dropped,
    )
    assert errors >= 0.9 * replies  # nearly all refused (a few valid commands among the junk)
    assert not oversized.poll(100)  # the oversized one: dropped, unanswered
    cycles = daemon.timing.cycles
    assert seqs == list(range(cycles)) and cycles >= 200  # publishing never skipped a cycle
    assert ask_status(ctx, config.control, daemon)["result"]["cycles"] == cycles  # still serving
    for sock in (pub, ctl, sub, client, oversized):
        sock.close(linger=0)


def test_clients_flooding_status_do_not_starve_the_loop(tmp_path, zmq_context):
    """Four clients keeping 20 requests each in flight, on the loop's own code (`Daemon.run`,
    `serve_until`) with a virtual clock in which building a status costs 1 ms: before, the
    loop answered every waiting request before its next cycle, and the sequence numbers
    jumped by whole periods; now no cycle is skipped, and every client is answered."""
    config = load_config(
        write_config(tmp_path, extra=f'publish = "ipc://{tmp_path}/pub"\ncontrol = "ipc://{tmp_path}/ctl"')
    )
    clock = VirtualClock()
    bus = simulated_bus(load_scene(tmp_path / "scene.toml"), clock=clock, bus_hz=400e3, seed=2)
    ctx = zmq_context  # terminated at teardown, with any socket an assert left open
    pub, ctl, _ = make_sockets(ctx, config)
    daemon = Daemon(config, bus, pub, ctl, clock=clock.now, wall=lambda: 1.7e9 + clock.now())
    build = daemon.status

    def costly_status() -> dict:
        clock.sleep(1e-3)  # a status as costly as the (virtual time: the same on any machine)
        return build()

    daemon.status = costly_status  # type: ignore[method-assign]
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"wrench/sensor1\0")
    sub.setsockopt(zmq.RCVHWM, 0)
    sub.connect(config.publish[0])
    stop = threading.Event()
    answered = [0] * 4

    def flood(i: int) -> None:
        sock = ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(config.control)
        sent = 0
        while not stop.is_set():
            while sent - answered[i] < 20:
                sock.send_multipart([b"", b'{"cmd": "status"}'])
                sent += 1
            if sock.poll(10):
                assert json.loads(sock.recv_multipart()[-1])["ok"]
                answered[i] += 1
        sock.close()

    clients = [threading.Thread(target=flood, args=(i,)) for i in range(4)]
    for c in clients:
        c.start()
    loop = threading.Thread(target=daemon.run)
    loop.start()
    seqs: list[int] = []
    try:
        while len(seqs) < 300 and loop.is_alive():
            if sub.poll(10_000):
                seqs.append(wire.decode(sub.recv()).seq)
            else:
                break
    finally:
        daemon.stop_requested = True
        loop.join(30)
        stop.set()
        for c in clients:
            c.join(10)
    assert len(seqs) == 300
    assert np.all(np.diff(seqs) == 1), f"sequence jumps: {np.diff(seqs)[np.diff(seqs) != 1]}"
    assert daemon.timing.missed == 0
    assert min(answered) > 0  # each client answered in turn
    for sock in (pub, ctl, sub):
        sock.close(linger=0)


def test_an_oversized_request_is_dropped_and_the_next_one_answered(tmp_path, zmq_context):
    config = load_config(write_config(tmp_path, extra=f'control = "ipc://{tmp_path}/ctl"'))
    ctx = zmq_context  # terminated at teardown, with any socket an assert left open
    pub, ctl, _ = make_sockets(ctx, config)
    daemon = Daemon(
        config, simulated_bus(load_scene(tmp_path / "scene.toml"), clock=VirtualClock()), pub, ctl
    )
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.connect(config.control)
    req.send(b" " * (MAX_REQUEST + 1))
    for _ in range(50):
        daemon.handle_control()
    assert not req.poll(100)  # dropped: the oversized peer is disconnected by ZeroMQ
    req.close()
    assert ask_status(ctx, config.control, daemon)["ok"]
    for sock in (pub, ctl):
        sock.close(linger=0)
