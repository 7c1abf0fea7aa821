"""`ftsensord run` with the in-loop ROS 2 output writing each stream's DDS sample right after
that stream's own ZeroMQ send, instead of once after the cycle's last send: the alternative
to ``[ros2] output = "in-loop"`` for benchmarks/performance/ros2_latency.py ``--each-send`` (measured,
not shipped: it needs a call in `Daemon._publish`, patched here). The writes are the
shipped output's own (`InLoop.write`); the diagnostics, readers and inputs stay after the
cycle's sends.

    python -m benchmarks.performance.ros2_each_send run --config FILE [--realtime 50]   (output = "in-loop")
"""

from __future__ import annotations

from typing import Any

import numpy as np

import ftsensord.ros2 as ros2
from ftsensord.ros2.inloop import _TIME, InLoop
from ftsensord.recording.ros2mcap import stamp
from ftsensord.protocol import wire
from ftsensord.daemon.daemon import Daemon


class EachSend(InLoop):
    def each(self, topic: str, seq: int, t_wall: float, flags: int, values: np.ndarray) -> None:
        stream = self.streams.get(topic)
        if stream is None:
            return
        last, stream.last_seq = stream.last_seq, seq
        if stream in self.read:
            self.write(stream, seq, last, _TIME.pack(*stamp(t_wall)), flags, values)

    def _after_sends(self, seq: int, t_wall: float, samples: dict, tip: Any, compensated: list) -> None:
        super()._after_sends(seq, t_wall, {}, None, [])  # the writes are made at each send


_publish = Daemon._publish


def publish_then_write(self: Daemon, topic: str, kind: int, seq: int, t_mono: float, t_wall: float, flags: int,
                       values: np.ndarray) -> None:
    _publish(self, topic, kind, seq, t_mono, t_wall, flags, values)
    if kind == wire.KIND_WRENCH:
        for out in self.outputs:
            out.each(topic, seq, t_wall, flags, values)


if __name__ == "__main__":
    Daemon._publish = publish_then_write  # type: ignore[method-assign]
    ros2.InLoop = EachSend  # type: ignore[misc]  # what the command line hands to `run`
    from ftsensord.__main__ import main

    raise SystemExit(main())
