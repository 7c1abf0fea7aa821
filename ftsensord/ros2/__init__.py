"""The streams on the ROS 2 graph over DDS, without ROS (floor 10, beside the Foxglove bridge).

`ftsensord ros2` is a process of its own, a client of the daemon like any other (its ZeroMQ
streams, its control socket, its orientation input): DDS's threads, its allocations and its
garbage stay out of the daemon's loop. Owns the ROS 2 message types as DDS types and their
type hashes (`msgs`), the diagnostics built from the daemon's status (`diagnostics`) and the
node (`node`: writers, the tare service, the orientation readers). Imports the client (9),
the service's wire and status formats (8) and the errors (1); cyclonedds (the ``ros2``
extra) only here, and only when the bridge runs.
"""
