"""`ftsensord run` with the ROS 2 bridge as a thread of the daemon's own process: the
alternative to the bridge process, for benchmarks/performance/ros2_latency.py ``--in-daemon`` (measured,
not shipped). The thread is the bridge's own `Bridge` (same code; REALTIME its SCHED_FIFO
priority, 1 as ``run`` gives the bridge process under a real-time daemon, 0: none), fed by
ZeroMQ from the same process; it shares the daemon's GIL, allocator and garbage collector,
which is what is measured.

    python -m benchmarks.performance.ros2_in_daemon NAMESPACE DOMAIN REALTIME run --config FILE [--realtime 50]
"""

from __future__ import annotations

import sys
import threading


def bridge(namespace: str, domain_id: int, realtime: int) -> None:
    from ftsensord.client import ControlClient, default_endpoint
    from ftsensord.ros2.bridge import Bridge, wait_for_status

    control = ControlClient(default_endpoint("control"), timeout_s=3.0)
    status = wait_for_status(control, lambda: False, 60.0)
    Bridge(namespace, domain_id, default_endpoint("wrench"), control, status, None, lambda: False, realtime).run()


if __name__ == "__main__":
    namespace, domain_id, realtime = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    del sys.argv[1:4]  # the rest is ftsensord's command line
    threading.Thread(target=bridge, args=(namespace, domain_id, realtime), daemon=True).start()
    from ftsensord.__main__ import main

    raise SystemExit(main())
