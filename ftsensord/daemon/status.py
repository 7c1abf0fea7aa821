"""What the daemon tells an operator: per-chip counters, the status reply and its one-line summary.

The keys of the `status` reply are documented in docs/reference/protocol.md.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from ftsensord import __version__
from ftsensord.acquire.health import ChipHealth, ChipResult
from ftsensord.acquire.reader import Reader
from ftsensord.acquire.readings import Readings
from ftsensord.chip.i2c import BusTiming
from ftsensord.config.file import Config
from ftsensord.config.frames import TIP
from ftsensord.daemon.control import Control
from ftsensord.daemon.host import HostGuard
from ftsensord.daemon.loop import LoopTiming, percentiles_us
from ftsensord.daemon.realtime import Scheduling
from ftsensord.daemon.ros2child import BridgeWatch
from ftsensord.errors import ChipError, ChipRefusedError
from ftsensord.processing.gravity import Gravity
from ftsensord.processing.pipeline import SensorPipeline
from ftsensord.processing.uncertainty import sigma_text


@dataclass
class ChipStats:
    sensor: str
    ok: bool = True
    errors: int = 0
    saturated: int = 0
    stale: int = 0
    last_error: str | None = None
    temperature_c: float | None = None


class ChipLedger:
    """Counts, per chip, what its results were since the daemon started."""

    def __init__(self, sensors: dict[str, tuple[int, ...]]):
        self.chips = {a: ChipStats(name) for name, addresses in sensors.items() for a in addresses}
        self._clean_last = False  # the last cycle counted was clean: every chip's ok is set

    def failed_to_start(self, address: int, exc: ChipError) -> None:
        self._clean_last = False
        stats = self.chips[address]
        stats.ok, stats.errors, stats.last_error = False, stats.errors + 1, str(exc)

    def count(self, r: ChipResult) -> None:
        stats = self.chips[r.address]
        m = r.measurement
        if m is not None:
            stats.ok = True
            stats.saturated += m.any_saturated
            if m.temperature_c is not None:
                stats.temperature_c = round(m.temperature_c, 2)
            return
        stats.errors += 1
        stats.last_error = str(r.error)
        if isinstance(r.error, ChipRefusedError) and r.error.command == "RM":
            stats.stale += 1
        else:
            stats.ok = False

    def count_all(self, results: Mapping[int, ChipResult]) -> None:
        """`count` every result of a cycle; the usual one (a reading, unsaturated, no
        temperature) without a call of its own, a clean cycle (`Readings.clean`) at once."""
        if type(results) is Readings and results.clean:
            if not self._clean_last:  # every chip read: ok, and nothing else counted
                for a in results.addresses:
                    self.chips[a].ok = True
                self._clean_last = True
            return
        self._clean_last = False
        chips, count = self.chips, self.count
        for r in results.values():
            m = r.measurement
            if m is not None and m.saturated_any is False and m.temperature_c is None:
                chips[r.address].ok = True
            else:
                count(r)

    @property
    def failing(self) -> int:
        return sum(not c.ok for c in self.chips.values())

    def report(self, health: dict[int, ChipHealth], now: float) -> dict[str, Any]:
        """Every chip's counters and its reader's view (state, retry, resets), keyed "0x0C"."""
        out = {}
        for address, stats in self.chips.items():
            h = health[address]
            retry = max(0.0, h.retry_at - now) if h.failing else None
            out[f"0x{address:02X}"] = {
                **vars(stats),
                "state": "resetting" if h.step else "failing" if h.failing else "ok",
                "retry_in_s": retry,
                "reinits": h.reinits,
                "register_drifts": h.register_drifts,
                "stuck_detections": h.stuck_detections,
            }
        return out


class Output(Protocol):
    """An output the loop feeds after each cycle's sends (`ros2.inloop.InLoop`)."""

    def status(self) -> dict[str, Any]: ...


class Reported(Protocol):
    """What the status reads of the daemon (`daemon.Daemon` is one): its configuration, bus
    and loop, its sensors, sockets and outputs."""

    config: Config
    board_timing: BusTiming | None
    reader: Reader
    chips: ChipLedger
    sensors: list[SensorPipeline]
    gravity: Gravity | None
    timing: LoopTiming
    control: Control
    guard: HostGuard
    scheduling: Scheduling
    bridge: BridgeWatch
    streams: set[str]
    outputs: list[Any]
    started_at: float  # s, on `clock`
    clock: Callable[[], float]  # monotonic s

    @property
    def period_s(self) -> float: ...


def status_line(d: Reported) -> str:
    """The one line systemd shows (`systemctl status`): rate against bound, misses, failing chips."""
    rate = d.timing.achieved_rate_hz()
    return (
        f"{f'{rate:.1f}' if rate else '-'} Hz of {d.config.rate_hz:g} Hz "
        f"(bound {d.config.bound(d.board_timing).rate_hz:.0f} Hz), {d.timing.missed} missed, "
        f"{d.chips.failing} chip(s) failing"
    )


def stream_frames(d: Reported) -> dict[str, str]:
    """The frame of every stream the configuration publishes: a sensor's wrench in its
    frame, the tip's in the tip frame, a compensated wrench in its raw one's, a flux
    stream in its chips' frames (``<sensor>/chip<i>``, i from 0)."""
    compensated = d.config.gravity.payloads if d.config.gravity is not None else {}
    frames = {}
    for s in d.config.sensors:
        frames[f"wrench/{s.name}"] = s.frame
        if s.name in compensated:
            frames[f"wrench/{s.name}/compensated"] = s.frame
        frames[f"flux/{s.name}"] = f"{s.name}/chip<i>"
    if d.config.tool_poses:
        frames["wrench/tip"] = d.config.tool_frame
        if TIP in compensated:
            frames["wrench/tip/compensated"] = d.config.tool_frame
    return frames


def health_reply(d: Reported) -> dict[str, Any]:
    """The part of the `status` reply that says how the loop, its chips and its sensors fare:
    what ROS 2's ``/diagnostics`` shows, made in the loop's own thread by the in-loop output.
    Without the reply's timing percentiles (each over the last 1000 cycles) and the rest,
    which make the whole reply six times dearer (callgrind: 2.1M instructions against 0.35M)."""
    t = d.timing
    return {
        "uptime_s": round(d.clock() - d.started_at, 3),
        "bus": d.config.bus,
        "scheduler": d.config.scheduler,
        "rate_hz": d.config.rate_hz,
        "achieved_rate_hz": t.achieved_rate_hz(),
        "cycles": t.cycles,
        "missed_cycles": t.missed,
        "late_cycles": t.late,
        "chips": d.chips.report(d.reader.health, d.reader.bus.monotonic()),
        "sensors": {s.name: sensor_status(s) for s in d.sensors},
    }


def status_reply(d: Reported) -> dict[str, Any]:
    """The `status` reply (keys in docs/reference/protocol.md): `health_reply` and the rest."""
    bound, t, board = d.config.bound(d.board_timing), d.timing, d.board_timing
    return {
        "version": __version__,
        **health_reply(d),
        "config": str(d.config.path),
        "readback_every": d.config.readback_every,
        "schedule": d.config.choice,
        "bound_hz": bound.rate_hz,
        "bound": bound.describe(),  # the bus as measured at start, or simulated:
        "adapter": board and board.adapter,
        "clock_hz": board and board.clock_hz,
        "ioctl_us": None if board is None or board.ioctl_s is None else board.ioctl_s * 1e6,
        "jitter_us": percentiles_us(t.lateness),
        # What the loop leaves of its period: the bound counts the bus, this adds the CPU.
        "cycle_us": percentiles_us(t.durations),
        "period_us": d.period_s * 1e6,
        # The daemon's part of a sample's latency: t_mono to its first stream's send.
        "publish_us": percentiles_us(t.publish_delays),
        "osr": d.config.settings.osr,
        "dig_filt": d.config.settings.dig_filt,
        "averaging": d.config.averaging,
        "lowpass_hz": d.config.lowpass_hz,
        "streams": sorted(d.streams),
        "publish": d.config.publish,
        "control": d.config.control,
        "connections": {c.name: c.status() for c in d.guard.caps},
        "replies_dropped": d.control.dropped,
        "frames": stream_frames(d),
        "gravity": d.gravity.status(d.sensors, d.clock()) if d.gravity else None,
        "scheduling": d.scheduling.status(),
        "ros2_bridge": d.bridge.status(),
        "outputs": [o.status() for o in d.outputs],
    }


def predicted_sigma(s: dict[str, Any]) -> str | None:
    """A sensor's predicted sigma at rest at the current settings (its `sensor_status`'s
    ``sigma``, `processing.uncertainty`) as one line, "fx fy fz N, mx my mz mNm"; None where
    it has none."""
    sigma = (s.get("sigma") or {}).get("sigma")
    return sigma_text(sigma) if sigma else None


def describe(status: dict[str, Any]) -> str:
    """A `status` reply as the text `ftsensord status` prints: rate against bound, jitter,
    cycle time, smoothing, sensors, and the chips that are not well."""
    out: list[str] = []
    jitter = status["jitter_us"]
    rate = status["achieved_rate_hz"]
    out.append(
        f"ftsensord {status['version']}, up {status['uptime_s']:.0f} s, bus {status['bus']}, "
        f"scheduler {status['scheduler']}"
    )
    out.append(
        f"rate: {rate:.2f} Hz achieved of {status['rate_hz']:g} Hz configured"
        if rate
        else f"rate: - of {status['rate_hz']:g} Hz configured"
    )
    out.append(f"bound: {status['bound']}")
    out.append(f"schedule: {status['schedule']}")
    out.append(
        f"cycles {status['cycles']}, missed {status['missed_cycles']}, late {status['late_cycles']}; "
        f"jitter p50 {jitter['p50']:.0f} us, p99 {jitter['p99']:.0f} us"
    )
    cycle = status["cycle_us"]
    out.append(
        f"cycle p50 {cycle['p50']:.0f} us, p99 {cycle['p99']:.0f} us, max {cycle['max']:.0f} us "
        f"of a {status['period_us']:.0f} us period"
    )
    out.append(
        f"conversion OSR {status['osr']}, DIG_FILT {status['dig_filt']}; "
        f"averaging {status['averaging']}, low-pass {status['lowpass_hz'] or 'off'}"
    )
    sched = status.get("scheduling")
    if sched:
        out.append(
            f"scheduling: {sched['policy']}"
            + (f" {sched['priority']}" if sched["priority"] else "")
            + (f" (SCHED_FIFO {sched['asked']} refused: {sched['refused']})" if sched["refused"] else "")
        )
    for name, s in status["sensors"].items():
        tare = (
            "tared, offset " + " ".join(f"{v:+.4g}" for v in s["tare_wrench"]) if s["tared"] else "not tared"
        )
        creep = s.get("silicone")
        out.append(
            f"sensor {name}: frame {s['frame']}, serial {s['serial']}, {tare}; calibration {s['calibration']}"
            + (f"; silicone's creep undone ({creep['restarts']} restarts)" if creep else "")
        )
        predicted = predicted_sigma(s)
        if predicted:
            out.append(f"  predicted sigma at rest ({s.get('estimator', 'linear')}): {predicted}")
    if "wrench/tip" in status.get("frames", {}):
        out.append(f"tip: frame {status['frames']['wrench/tip']}")
    gravity = status.get("gravity")
    if gravity:
        stream = gravity["stream"]
        out.append(
            f"gravity compensation ({gravity['orientation']}): "
            + ", ".join(
                f"{f} {g['mass_kg'] * 1e3:.0f} g"
                + (" (orientation stale)" if g["orientation_stale"] else "")
                + (
                    " gravity now [" + " ".join(f"{v:+.2f}" for v in g["gravity_now_mps2"]) + "] m/s^2"
                    if g.get("gravity_now_mps2")
                    else ""
                )
                for f, g in gravity["frames"].items()
            )
            + (
                f"; orientation messages {stream['received']} received, "
                f"{sum(stream['dropped'].values())} dropped"
                if gravity["orientation"] == "stream"
                else ""
            )
        )
    bad = {a: c for a, c in status["chips"].items() if not c["ok"] or c["errors"] or c["reinits"]}
    temps = [c["temperature_c"] for c in status["chips"].values() if c["temperature_c"] is not None]
    out.append(
        f"chips: {len(status['chips'])}, failing {sum(not c['ok'] for c in status['chips'].values())}"
        + (f", {min(temps):.1f}-{max(temps):.1f} degC" if temps else "")
    )
    for address, c in bad.items():
        retry = f", retry in {c['retry_in_s']:.2f} s" if c["retry_in_s"] is not None else ""
        out.append(
            f"  {address}: {c['state'].upper()}{retry}, {c['errors']} errors, {c['reinits']} resets, "
            f"{c['register_drifts']} register changes, {c['stuck_detections']} stuck; last: {c['last_error']}"
        )
    return "\n".join(out)


def sensor_status(p: SensorPipeline) -> dict[str, Any]:
    """One sensor's part of the `status` reply: calibration, tare, estimator and its stages."""
    return {
        "calibration": str(p.config.calibration_path),
        "serial": p.config.calibration.serial,
        "frame": p.config.frame,
        "tared": p.tared,
        "estimator": p.estimator,
        "nonlinear_calibrated": p.nonlinear is not None,
        "fallbacks": p.fallbacks,
        # Which solve the nonlinear estimator runs: the C one built at install, or numpy's.
        "nonlinear_solver": None
        if p.nonlinear is None
        else "numpy"
        if p.nonlinear.compiled is None
        else "compiled",
        "estimate_cpu_us": {"mean": statistics.fmean(p.estimate_s) * 1e6, "max": max(p.estimate_s) * 1e6}
        if p.estimate_s
        else None,
        "tare_wrench": p.tare_wrench.round(6).tolist(),
        # The sigma at rest of the current settings, every chip (`processing.uncertainty`).
        "sigma": None
        if p.uncertainty is None
        else p.uncertainty.predicted(p.filter.factors[-1], p.tare_samples, p.estimator, spread=p.tare_spread),
        **p.stages_status(),
    }
