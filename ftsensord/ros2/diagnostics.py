"""The daemon's status as ``diagnostic_msgs/msg/DiagnosticArray`` statuses, in the form ROS's
diagnostic tools read (rqt_robot_monitor, diagnostic_aggregator's analyzers): one status a
component, named ``<namespace>: <component>``, with a level, a one-line message, a hardware id
and key/value pairs (strings).

Components: the daemon (rate, cycles missed and late), each sensor (its tare, estimator,
temperature, the flags of its latest wrench, its predicted sigma at rest), each chip (state,
counts, temperature). Levels (DiagnosticStatus): OK 0, WARN 1, ERROR 2, STALE 3. No dependency on DDS: plain tuples,
made into a message's CDR bytes by `cdr` (struct, not the binding's serializer: a tenth of
its 2 ms, which the in-loop output spends in the loop's thread).
"""

from __future__ import annotations

import struct
from itertools import chain
from typing import Any

from ftsensord.daemon.status import predicted_sigma
from ftsensord.protocol import wire
from ftsensord.recording.ros2mcap import CDR_LE, stamp

OK, WARN, ERROR, STALE = 0, 1, 2, 3
#: Chip states (`daemon.status`) and their levels: a chip being reset still answers the
#: others' cycle (the sensor runs degraded); a failing one is out.
CHIP_LEVELS = {"ok": OK, "resetting": WARN, "failing": ERROR}
#: Sample flags that make a sensor's level ERROR: no estimate, or one from too few chips' data.
ERROR_FLAGS = wire.FLAG_INVALID | wire.FLAG_CHIP_MISSING
#: Flags that say nothing about the sensor's health (a late cycle is the host's): not raised.
QUIET_FLAGS = wire.FLAG_LATE
#: The achieved rate below this share of the configured one is a WARN: 5 % is five cycles in
#: 100 missed, beyond the one-off late start of a loaded host.
RATE_SHARE = 0.95

Status = tuple[int, str, str, str, list[tuple[str, str]]]  # level, name, message, hardware_id, values
#: The daemon's own keys of the `status` reply its diagnostic status shows.
DAEMON_KEYS = [
    "rate_hz",
    "achieved_rate_hz",
    "cycles",
    "missed_cycles",
    "late_cycles",
    "bus",
    "scheduler",
    "uptime_s",
]


def _values(d: dict[str, Any], keys: list[str]) -> list[tuple[str, str]]:
    return [(k, str(d.get(k))) for k in keys if k in d]


def daemon_status(status: dict[str, Any], namespace: str) -> Status:
    rate, achieved = float(status.get("rate_hz", 0.0)), status.get("achieved_rate_hz")
    slow = achieved is not None and float(achieved) < RATE_SHARE * rate
    message = f"{achieved:.1f} of {rate:g} Hz" if achieved is not None else f"{rate:g} Hz"
    values = _values(status, DAEMON_KEYS)
    return (
        WARN if slow else OK,
        f"{namespace}: daemon",
        message + (" (below the configured rate)" if slow else ""),
        str(status.get("bus", "")),
        values,
    )


def sensor_status(
    name: str, s: dict[str, Any], chips: dict[str, dict[str, Any]], flags: int | None, namespace: str
) -> Status:
    """A sensor's status: the worst of its chips' levels and of its latest wrench's flags."""
    levels = [CHIP_LEVELS.get(str(c.get("state")), WARN) for c in chips.values()] or [OK]
    level = max(levels)
    shown = (flags or 0) & ~QUIET_FLAGS
    if shown:
        level = max(level, ERROR if shown & ERROR_FLAGS else WARN)
    temperature = s.get("temperature") or {}
    if temperature.get("beyond_span"):
        level = max(level, WARN)
    problems = wire.flag_names(shown) + (
        ["temperature beyond the calibrated span"] if temperature.get("beyond_span") else []
    )
    values = [
        *_values(s, ["serial", "frame", "tared", "estimator", "fallbacks", "calibration"]),
        ("mean_temperature_c", str(temperature.get("mean_c"))),
        ("flags", ",".join(wire.flag_names(flags or 0)) or "none"),
        ("chips_ok", f"{sum(1 for c in chips.values() if c.get('state') == 'ok')} of {len(chips)}"),
        ("predicted_sigma_at_rest", predicted_sigma(s) or "unknown"),
    ]
    return (level, f"{namespace}: {name}", ", ".join(problems) or "OK", str(s.get("serial", name)), values)


def chip_status(address: str, c: dict[str, Any], namespace: str) -> Status:
    state = str(c.get("state"))
    message = state if not c.get("last_error") else f"{state}: {c['last_error']}"
    values = _values(
        c,
        [
            "sensor",
            "state",
            "errors",
            "saturated",
            "stale",
            "temperature_c",
            "reinits",
            "register_drifts",
            "stuck_detections",
            "last_error",
        ],
    )
    return (
        CHIP_LEVELS.get(state, WARN),
        f"{namespace}: {c.get('sensor', '?')} chip {address}",
        message,
        f"MLX90393 {address}",
        values,
    )


def statuses(
    status: dict[str, Any] | None, flags: dict[str, int], namespace: str, why: str = ""
) -> list[Status]:
    """Every component's status from the daemon's ``status`` (None: it did not answer, ``why``:
    one STALE status); ``flags``: each sensor's latest wrench's flags, by sensor name."""
    if status is None:
        return [(STALE, f"{namespace}: daemon", f"no answer from the daemon: {why}", "", [])]
    chips: dict[str, dict[str, Any]] = status.get("chips") or {}
    out = [daemon_status(status, namespace)]
    for name, s in (status.get("sensors") or {}).items():
        own = {a: c for a, c in chips.items() if c.get("sensor") == name}
        out.append(sensor_status(name, s, own, flags.get(name), namespace))
    out += [chip_status(a, c, namespace) for a, c in chips.items()]
    return out


_U32 = struct.Struct("<I")
_PAD = (b"", b"\0\0\0", b"\0\0", b"\0")  # by an offset mod 4: the zeros up to the next multiple of 4
_OCTET = [bytes((i,)) for i in range(256)]


class Encoder:
    """A ``diagnostic_msgs/msg/DiagnosticArray`` of ``statuses_`` as plain little-endian CDR
    (XCDR1, as the rmws write it), made a few statuses at a time (`add`; the in-loop output
    spreads them over cycles), its header's stamp put in last (`message`), its frame_id
    empty: each uint32 (a string's or a sequence's length) 4-aligned from after the
    encapsulation, a string's length counting its NUL, the level one octet."""

    def __init__(self, statuses_: list[Status]):
        self.statuses, self.done = statuses_, 0
        # the stamp's 8 bytes (`message`), frame_id "" (its length, its NUL), 3 to align, the count
        self.parts = [CDR_LE, b"", b"\1\0\0\0\0\0\0\0", _U32.pack(len(statuses_))]
        self.at = 20  # bytes after the encapsulation

    def add(self, count: int) -> bool:
        """The next ``count`` statuses encoded; whether every status is now."""
        parts, at, pack = self.parts, self.at, _U32.pack
        for level, name, message, hardware_id, values in self.statuses[self.done : self.done + count]:
            parts.append(_OCTET[level])
            at += 1
            # None: where the values' count goes, a uint32 alone (one loop: the per-string
            # work is the cost here, a function call a string would double it)
            for text in (name, message, hardware_id, None, *chain.from_iterable(values)):
                data = b"" if text is None else text.encode() + b"\0"
                pad = _PAD[at & 3]
                parts.append(pad + pack(len(values) if text is None else len(data)) + data)
                at += len(pad) + 4 + len(data)
        self.at, self.done = at, min(self.done + count, len(self.statuses))
        return self.done == len(self.statuses)

    def message(self, t_wall: float) -> bytes:
        """The message stamped ``t_wall`` (UNIX s), once `add` has encoded every status."""
        self.parts[1] = struct.pack("<iI", *stamp(t_wall))
        return b"".join(self.parts)


def cdr(statuses_: list[Status], t_wall: float) -> bytes:
    """`Encoder`'s message of ``statuses_`` stamped ``t_wall`` (UNIX s), made at once."""
    encoder = Encoder(statuses_)
    encoder.add(len(statuses_))
    return encoder.message(t_wall)
