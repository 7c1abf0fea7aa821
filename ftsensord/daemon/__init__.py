"""Floor 10, the daemon: the process that turns cycles of flux into published wrenches.

- `daemon`: the coordinator over one bus, the pipelines and two sockets, a cycle at a time.
- `loop`: the cycles' deadlines, late and missed cycles, their statistics.
- `control`: the control endpoint's requests, parsed and bounded; `commands`: what they do.
- `status`: the status reply and its one-line summary.
- `reloads`: configuration and calibration re-read off the loop's critical path; `plans`:
  `set --accuracy`'s choice of conversion made the same way.
- `run`: `ftsensord run`: bus, sockets, signals, clean-up.
- The OS plumbing: `sdnotify` (systemd's notify protocol), `realtime` (SCHED_FIFO),
  `connections` (caps on clients), `runtime` (the runtime folder's files), `host` (all
  three between cycles), `ros2child` (the ROS 2 bridge as a process of its own).

May import every floor below: `processing`, `config`, `protocol`, `calibration`,
`acquire`, `sim` (a simulated bus on a real-time clock), `chip`, `model`, `docfile`, `errors`.
"""
