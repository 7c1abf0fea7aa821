"""Recording streams to disk as they arrive: CSV, NPZ (through a sidecar) and MCAP.

Every writer holds at most `FLUSH_EVERY_S` of samples in the process, so memory
stays flat however long a recording runs, and a recorder killed outright
(``kill -9``, a power-less crash of the process, not of the host) loses at most
that much; what was flushed is in the kernel's page cache and reaches the disk
without the process. Ending cleanly (count, time, SIGINT/SIGTERM/SIGHUP) makes
the file complete and returns a per-stream summary.

- **CSV** (one stream): the column names, then a row per sample as it comes, so
  any CSV reader takes it with its defaults; the stream, frame, units and counts
  are in the sidecar ``FILE.csv.json`` (`csvfile`, `read_meta`).
- **NPZ** (one stream): a zip cannot be appended to safely, so rows go to a
  sidecar ``FILE.npz.part`` (a JSON line, then fixed-size binary records) and
  the ``.npz`` is built from it at a clean end, the sidecar then removed. After a
  kill the sidecar stays: `load_rows` reads it (a torn last record is dropped),
  `finish_npz` turns it into the ``.npz``.
- **MCAP** (any number of streams): each wrench a ROS 2 ``geometry_msgs/msg/WrenchStamped``
  (CDR), each chip of a flux stream a ``sensor_msgs/msg/MagneticField``, and per
  stream a companion ``<topic>/status`` (``ftsensord_msgs/msg/SampleStatus``: seq,
  flags, missed). A chunk is closed every `FLUSH_EVERY_S`; the summary and index
  come at a clean end. A file cut short still reads, chunk by chunk, with
  `read_mcap` (mcap's non-seeking reader) and `recover_mcap` rewrites it whole.

May import: `client` (to subscribe), `protocol`, `errors`; never the daemon's floors.
"""

from ftsensord.recording.columns import WRENCH_COLUMNS, Tally, value_columns
from ftsensord.recording.csvfile import CsvWriter, read_meta
from ftsensord.recording.loop import (
    FLUSH_EVERY_S,
    Outcome,
    Receiver,
    SampleWriter,
    StopOnSignals,
    daemon_frames,
    open_writer,
    record,
    summary_line,
)
from ftsensord.recording.npz import CHUNK_ROWS, NpzWriter, finish_npz, gaps_of, load_rows
from ftsensord.recording.ros2mcap import read_mcap, recover_mcap

__all__ = [
    "CHUNK_ROWS",
    "FLUSH_EVERY_S",
    "WRENCH_COLUMNS",
    "CsvWriter",
    "NpzWriter",
    "Outcome",
    "Receiver",
    "SampleWriter",
    "StopOnSignals",
    "Tally",
    "daemon_frames",
    "finish_npz",
    "gaps_of",
    "load_rows",
    "open_writer",
    "read_mcap",
    "read_meta",
    "record",
    "recover_mcap",
    "summary_line",
    "value_columns",
]
