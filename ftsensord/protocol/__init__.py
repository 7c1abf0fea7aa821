"""Floor 7, the protocol: what the daemon and every client share.

- `wire`: the published samples' bytes (docs/reference/protocol.md has them byte by byte), the
  flags and the topics.
- `orientation`: the orientation stream's message (a client tells the daemon how the tool
  is turned) and the latest-value receiver the daemon reads it with.
- `endpoints`: ZeroMQ endpoints, who may reach them, and their ``[security]`` table.
- `paths`: the runtime folder the sockets live in, and files a configuration names.

May import: `docfile`, `errors` (floor 1). Never `model` and above: a client that only
subscribes imports this floor and nothing of the sensor.
"""
