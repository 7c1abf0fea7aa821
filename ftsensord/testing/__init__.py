"""Floor 14, testing: the daemon as the tests and benchmarks run it, shipped in the package
(as gpiozero ships its mock pin factory) so that neither loads the other's files by path.

- `harness`: `ftsensord run` as a process in a runtime folder of its own, handed back once
  it said READY=1 (`start_daemon`, `stop`); or a `Daemon` in this process on a virtual
  clock, stepped a cycle at a time (`InProcess`); the packaged configuration with lines
  replaced (`packaged_config`).

May import every floor; nothing in the package imports it.
"""
