"""The streams on the ROS 2 graph over DDS, without ROS (floor 12, beside the Foxglove bridge).

Two outputs, chosen by ``[ros2] output``: ``"bridge"``, `ftsensord ros2` (`bridge`), a
process of its own, a client of the daemon like any other (its ZeroMQ streams, its control
socket, its orientation input); ``"in-loop"`` (`inloop`), the daemon's loop thread writing to
DDS right after its ZeroMQ sends, handed to `daemon.run` by the command line.
docs/results/performance.md, "ROS 2", measures both. Owns the ROS 2 message types as DDS
types and their type hashes (`msgs`), the diagnostics built from the daemon's status
(`diagnostics`) and the node (`node`: writers, the tare service, the orientation readers).
cyclonedds (the ``ros2`` extra) is imported only in `node` and `msgs`, only when an output runs.

May import: `recording` (the ROS 2 messages' CDR), `client`, `daemon` (its status, for
`/diagnostics`), `processing`, `config`, `protocol` and the floors below.
"""

from ftsensord.ros2.bridge import add_parser as add_ros2_parser
from ftsensord.ros2.inloop import InLoop

__all__ = ["InLoop", "add_ros2_parser"]
