"""The daemon: a steady loop that reads every chip, estimates wrenches and
publishes them, and a control endpoint served while the loop waits.

The daemon takes its dependencies (bus, configuration, sockets, notifier,
clock), so tests drive `Daemon.cycle` and `Daemon.handle_request` on a
virtual clock, and `ftsensord run` wires the real ones (`ftsensord.service`).

Timing: cycles start on absolute deadlines k / rate (no drift). A cycle that
starts more than a tenth of a period late is counted late and its samples
flagged; deadlines already past by a whole period are skipped and counted as
missed, never made up by a burst.
"""

from __future__ import annotations

import json
import logging
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import zmq

from .. import __version__
from ..acquire.health import ChipResult
from ..acquire.reader import Reader
from ..chip import mlx90393 as mlx
from ..chip.driver import MLX90393
from ..chip.i2c import Bus
from ..errors import ChipRefusedError, ConfigError, FtsensordError
from ..model import se3
from ..model.linear import SENSOR_RANGE, LinearModel
from ..model.nonlinear import NonlinearEstimator
from . import wire
from .config import Config, SensorConfig, check_rate, load_config
from .filters import WrenchFilter
from .sdnotify import Notifier

log = logging.getLogger("ftsensord")

#: A cycle starting later than this fraction of a period after its deadline is late.
LATE_FRACTION = 0.1
#: Cycles kept for the achieved rate and the jitter percentiles (10 s at 100 Hz).
STATS_WINDOW = 1000
#: Largest control request accepted, bytes (ZMQ_MAXMSGSIZE drops larger ones).
MAX_REQUEST = 64 * 1024
#: A tare gives up when its sensor has been invalid for this many times the samples asked.
TARE_PATIENCE = 10
#: A linear estimate is flagged `extrapolated` past this multiple of the calibration's
#: largest load on an axis: up to 1.5x no axis's error relative to the load has grown
#: 1.5-fold, by 3x one has nearly tripled (benchmarks/extrapolation.py, docs/calibration.md).
EXTRAPOLATION_MARGIN = 1.5


@dataclass
class ChipStats:
    sensor: str
    ok: bool = True
    errors: int = 0
    saturated: int = 0
    stale: int = 0
    last_error: str | None = None
    temperature_c: float | None = None


@dataclass
class SensorRuntime:
    config: SensorConfig
    model: LinearModel
    filter: WrenchFilter
    last_flux: np.ndarray
    tared: bool = False
    estimator: str = "linear"
    nonlinear: NonlinearEstimator | None = None  # built from the calibration when it has one
    zero_twist: np.ndarray | None = None  # the nonlinear estimator's no-load deflection
    tare_wrench: np.ndarray = field(default_factory=lambda: np.zeros(6))  # what the tare removes (N, Nm)
    fallbacks: int = 0
    estimate_s: deque[float] = field(default_factory=lambda: deque(maxlen=STATS_WINDOW))

    @property
    def name(self) -> str:
        return self.config.name


@dataclass
class TareJob:
    reply_to: list[bytes]
    sensors: list[str]
    samples: int
    flux: dict[str, list[np.ndarray]] = field(default_factory=dict)
    cycles: int = 0


class Daemon:
    """One bus, its sensors, a publisher socket and a control socket."""

    def __init__(self, config: Config, bus: Bus, publisher: zmq.Socket, control: zmq.Socket | None = None, *,
                 notifier: Notifier | None = None, clock: Callable[[], float] = time.monotonic,
                 wall: Callable[[], float] = time.time):
        self.config = config
        self.bus = bus
        self.publisher = publisher
        self.control = control
        self.notifier = notifier or Notifier(environ={})
        self.clock, self.wall = clock, wall
        chips = [MLX90393(bus, a, sleep=bus.sleep) for a in config.addresses]
        self.reader = Reader(bus, chips, config.scheduler, config.settings, config.bus_hz, config.bus_overhead_s,
                             stuck_cycles=config.stuck_cycles, readback_every=config.readback_every)
        self.chip_stats = {a: ChipStats(s.name) for s in config.sensors for a in s.addresses}
        self.sensors = [self._runtime(s) for s in config.sensors]
        self.seq: dict[str, int] = {}
        self.cycles = self.missed = self.late = 0
        self.starts: deque[float] = deque(maxlen=STATS_WINDOW)
        self.lateness: deque[float] = deque(maxlen=STATS_WINDOW)
        self.durations: deque[float] = deque(maxlen=STATS_WINDOW)  # s, a cycle's start to its last publish
        self.tares: list[TareJob] = []
        self.started_at = clock()
        self.stop_requested = self.reload_requested = False
        self.ready = False

    def _runtime(self, s: SensorConfig) -> SensorRuntime:
        nl = s.calibration.nonlinear
        return SensorRuntime(s, s.calibration.model,
                             WrenchFilter(self.config.averaging, self.config.lowpass_hz, self.config.rate_hz),
                             np.full(3 * len(s.addresses), np.nan), estimator=s.estimator,
                             nonlinear=nl.estimator() if nl is not None else None,
                             zero_twist=nl.zero_twist.copy() if nl is not None else None)

    @property
    def period_s(self) -> float:
        return 1.0 / self.config.rate_hz

    # --- the loop ------------------------------------------------------------------
    def start(self) -> None:
        for address, exc in self.reader.start().items():
            self.chip_stats[address].ok = False
            self.chip_stats[address].errors += 1
            self.chip_stats[address].last_error = str(exc)
            log.warning("chip 0x%02X failed to start: %s", address, exc)

    def run(self) -> int:
        """Cycle until asked to stop; then put the chips to idle. Returns the exit status."""
        self.start()
        deadline = self.clock()
        while not self.stop_requested:
            lateness = self.clock() - deadline
            if lateness >= self.period_s:
                skipped = int(lateness // self.period_s)
                self.missed += skipped
                deadline += skipped * self.period_s
                lateness -= skipped * self.period_s
            self.cycle(lateness)
            deadline += self.period_s
            self.serve_until(deadline)
            if self.reload_requested:  # SIGHUP, handled between cycles
                self.reload_requested = False
                try:
                    self.reload()
                except FtsensordError:
                    pass  # logged; the running configuration stays
        self.shutdown()
        return 0

    def serve_until(self, deadline: float) -> None:
        """Answer control requests until ``deadline``, then return (sleeping the last ms)."""
        poller = zmq.Poller()
        if self.control is not None:
            poller.register(self.control, zmq.POLLIN)
        while not self.stop_requested:
            self.handle_control()
            remaining = deadline - self.clock()
            if remaining <= 0:
                return
            if remaining > 2e-3 and self.control is not None:
                poller.poll(timeout=int((remaining - 1e-3) * 1000))
            else:
                time.sleep(remaining)

    def shutdown(self) -> None:
        self.notifier.stopping()
        self.reader.stop()
        log.info("stopped after %d cycles (%d missed, %d late)", self.cycles, self.missed, self.late)

    def cycle(self, lateness: float = 0.0) -> None:
        """Read every chip once, estimate and publish every stream."""
        start = self.clock()
        self.starts.append(start)
        self.lateness.append(max(0.0, lateness))
        late = lateness > LATE_FRACTION * self.period_s
        self.late += late
        every = self.config.temperature_every
        zyxt = mlx.ZYXT_XYZT if every and self.cycles % every == 0 else mlx.ZYXT_XYZ
        results = {r.address: r for r in self.reader.read(zyxt)}
        t_mono, t_wall = self.clock(), self.wall()
        for r in results.values():
            self._count(r)
        base = wire.FLAG_LATE if late else 0
        wrenches, tip_flags, raw = {}, base, []
        for sensor in self.sensors:
            flux, flags, usable = self._flux(sensor, results)
            flags |= base
            raw.append((sensor.name, flux, flags))
            wrench, flags = self._estimate(sensor, flux, flags, usable)
            if not flags & wire.FLAG_INVALID:
                if np.any(np.abs(wrench) > SENSOR_RANGE):
                    flags |= wire.FLAG_OVERLOAD
                self._feed_tares(sensor, flux, flags)
            filtered = sensor.filter.update(wrench)
            # Wrenches first: a haptic loop waits for them; the flux streams are for debugging.
            self._publish(f"wrench/{sensor.name}", wire.KIND_WRENCH, t_mono, t_wall, flags, filtered)
            wrenches[sensor.name] = filtered
            tip_flags |= flags
        if self.config.tool_offsets_m:
            tip = sum((se3.wrench_transform(se3.pose(p=offset)) @ wrenches[name]
                       for name, offset in self.config.tool_offsets_m.items()), start=np.zeros(6))
            self._publish("wrench/tip", wire.KIND_WRENCH, t_mono, t_wall, tip_flags, tip)
        for name, flux, flags in raw:
            self._publish(f"flux/{name}", wire.KIND_FLUX, t_mono, t_wall, flags, flux)
        self._advance_tares()
        self.durations.append(self.clock() - start)
        self.cycles += 1
        if not self.ready:
            self.ready = True
            self.notifier.ready(self.status_line())
            log.info("ready: %s", self.status_line())
        self.notifier.watchdog()
        if self.cycles % max(1, int(self.config.rate_hz)) == 0:
            self.notifier.status(self.status_line())

    def _count(self, r: ChipResult) -> None:
        stats = self.chip_stats[r.address]
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

    def _estimate(self, sensor: SensorRuntime, flux: np.ndarray, flags: int,
                  usable: np.ndarray) -> tuple[np.ndarray, int]:
        """The wrench from every chip; from the usable ones (degraded) when one or
        two are missing or saturated; else NaN, flagged invalid. A failing chip's
        data never enter a wrench."""
        if sensor.estimator == "nonlinear" and sensor.nonlinear is not None and sensor.zero_twist is not None:
            if (~usable).sum() <= self.config.max_missing_chips:
                t0 = time.process_time()
                e = sensor.nonlinear.estimate(flux, usable)
                sensor.estimate_s.append(time.process_time() - t0)
                if e.converged:
                    w = sensor.nonlinear.stiffness @ (e.xi - sensor.zero_twist)
                    return w, flags | (0 if usable.all() else wire.FLAG_DEGRADED)
            sensor.fallbacks += 1
            flags |= wire.FLAG_FALLBACK
        if usable.all():
            return self._linear(sensor, sensor.model.wrench(flux), flags)
        if (~usable).sum() <= self.config.max_missing_chips and sensor.model.H is not None:
            try:
                return self._linear(sensor, sensor.model.wrench_from(flux, usable), flags | wire.FLAG_DEGRADED)
            except ValueError:
                pass  # the chips left do not see all six axes
        return np.full(6, np.nan), flags | wire.FLAG_INVALID

    @staticmethod
    def _linear(sensor: SensorRuntime, wrench: np.ndarray, flags: int) -> tuple[np.ndarray, int]:
        """A linear estimate, flagged `extrapolated` where the load on the sensor (the
        wrench plus what a tare removed) is beyond the calibration's loads."""
        fitted = sensor.config.calibration.wrench_range
        if fitted is not None and np.any(np.abs(wrench + sensor.tare_wrench) > EXTRAPOLATION_MARGIN * fitted):
            flags |= wire.FLAG_EXTRAPOLATED
        return wrench, flags

    def _flux(self, sensor: SensorRuntime, results: dict[int, ChipResult]) -> tuple[np.ndarray, int, np.ndarray]:
        """The sensor's stacked flux (T), its flags, and which chips are usable: a
        chip without new data gives its previous reading (flagged stale), a chip
        that did not answer NaN, a saturated chip its reading (not usable)."""
        flux = np.full(3 * len(sensor.config.addresses), np.nan)
        usable = np.zeros(len(sensor.config.addresses), dtype=bool)
        flags = 0
        for i, address in enumerate(sensor.config.addresses):
            r, part = results[address], slice(3 * i, 3 * i + 3)
            m = r.measurement
            if m is not None:
                flux[part] = sensor.last_flux[part] = m.field_t
                usable[i] = not m.any_saturated
                if m.any_saturated:
                    flags |= wire.FLAG_SATURATED
            elif (isinstance(r.error, ChipRefusedError) and r.error.command == "RM"
                  and np.all(np.isfinite(sensor.last_flux[part]))):
                flux[part] = sensor.last_flux[part]
                usable[i] = True
                flags |= wire.FLAG_STALE
            else:
                flags |= wire.FLAG_CHIP_MISSING
        return flux, flags, usable

    def _publish(self, topic: str, kind: int, t_mono: float, t_wall: float, flags: int, values: np.ndarray) -> None:
        seq = self.seq.get(topic, 0)
        self.seq[topic] = seq + 1
        try:
            self.publisher.send(wire.encode(topic, kind, seq, t_mono, t_wall, flags, values), zmq.NOBLOCK)
        except zmq.Again:
            pass  # no room for a slow subscriber: latest value wins, the sequence shows the gap

    # --- tare ----------------------------------------------------------------------------
    def _feed_tares(self, sensor: SensorRuntime, flux: np.ndarray, flags: int) -> None:
        if flags & (wire.FLAG_STALE | wire.FLAG_DEGRADED):
            return  # a zero needs every chip's fresh reading
        for job in self.tares:
            if sensor.name in job.sensors and len(job.flux.setdefault(sensor.name, [])) < job.samples:
                job.flux[sensor.name].append(flux)

    def _advance_tares(self) -> None:
        for job in list(self.tares):
            job.cycles += 1
            if all(len(job.flux.get(n, [])) >= job.samples for n in job.sensors):
                offsets = {}
                for sensor in self.sensors:
                    if sensor.name in job.sensors:
                        zero = np.mean(job.flux[sensor.name], axis=0)
                        sensor.tare_wrench = sensor.config.calibration.model.wrench(zero)
                        offsets[sensor.name] = sensor.tare_wrench.round(6).tolist()
                        sensor.model = sensor.model.with_zero(zero)
                        if sensor.nonlinear is not None:
                            e = sensor.nonlinear.estimate(zero)
                            if e.converged:
                                sensor.zero_twist = e.xi
                        sensor.filter.reset()
                        sensor.tared = True
                self.tares.remove(job)
                self._reply(job.reply_to, {"ok": True, "result": {"tare_wrench": offsets, "samples": job.samples}})
            elif job.cycles > TARE_PATIENCE * job.samples:
                self.tares.remove(job)
                self._reply(job.reply_to, {"ok": False, "error": f"tare gave up after {job.cycles} cycles: "
                                                               "the sensor had too few valid samples"})

    # --- control ---------------------------------------------------------------------------
    def handle_control(self) -> None:
        """Answer every waiting control request (ROUTER: [identity, (empty), request])."""
        if self.control is None:
            return
        while True:
            try:
                frames = self.control.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            if len(frames) < 2:
                continue  # not from a REQ or DEALER peer: nothing to answer to
            reply = self.handle_request(frames[-1], frames[:-1])
            if reply is not None:
                self._reply(frames[:-1], reply)

    def _reply(self, envelope: list[bytes], reply: dict[str, Any]) -> None:
        if self.control is None:
            return
        try:
            self.control.send_multipart([*envelope, json.dumps(reply, default=float).encode()], zmq.NOBLOCK)
        except zmq.ZMQError:
            pass  # the peer left: nobody to tell

    def handle_request(self, raw: bytes, envelope: list[bytes]) -> dict[str, Any] | None:
        """One JSON request; returns the reply, or None when it comes later (tare)."""
        try:
            request = json.loads(raw)
        except (UnicodeDecodeError, json.JSONDecodeError, RecursionError):
            return {"ok": False, "error": "the request is not JSON"}
        if not isinstance(request, dict) or not isinstance(request.get("cmd"), str):
            return {"ok": False, "error": 'expected a JSON object with a string "cmd"'}
        handler = {"status": self._cmd_status, "tare": self._cmd_tare, "reload": self._cmd_reload,
                   "set": self._cmd_set}.get(request["cmd"])
        if handler is None:
            return {"ok": False, "error": f"unknown command {request['cmd'][:40]!r}; "
                                          "commands: status, tare, reload, set"}
        args = {k: v for k, v in request.items() if k != "cmd"}
        try:
            result = handler(args, envelope)
        except (FtsensordError, ValueError, TypeError) as exc:
            return {"ok": False, "error": str(exc)}
        except Exception:  # a bug must not stop the loop: log it, answer, go on
            log.exception("control request %r failed", request.get("cmd"))
            return {"ok": False, "error": "internal error (logged by the daemon)"}
        return None if result is None else {"ok": True, "result": result}

    @staticmethod
    def _args(args: dict[str, Any], allowed: set[str]) -> None:
        unknown = sorted(set(args) - allowed)
        if unknown:
            raise ValueError(f"unknown argument(s) {unknown}; this command takes {sorted(allowed) or 'none'}")

    def _cmd_status(self, args: dict[str, Any], envelope: list[bytes]) -> dict[str, Any]:
        self._args(args, set())
        return self.status()

    def _cmd_tare(self, args: dict[str, Any], envelope: list[bytes]) -> None:
        self._args(args, {"samples", "sensor"})
        samples = args.get("samples", 100)
        if not isinstance(samples, int) or isinstance(samples, bool) or not 1 <= samples <= 10_000:
            raise ValueError("samples: expected an integer from 1 to 10000")
        names = [s.name for s in self.sensors]
        sensor = args.get("sensor")
        if sensor is not None and sensor not in names:
            raise ValueError(f"sensor: expected one of {names}, got {str(sensor)[:40]!r}")
        self.tares.append(TareJob(envelope, [sensor] if sensor else names, samples))
        return None

    def _cmd_reload(self, args: dict[str, Any], envelope: list[bytes]) -> dict[str, Any]:
        self._args(args, set())
        return self.reload()

    def _cmd_set(self, args: dict[str, Any], envelope: list[bytes]) -> dict[str, Any]:
        self._args(args, {"rate_hz", "averaging", "lowpass_hz", "estimator", "sensor"})
        if "estimator" in args:
            if set(args) - {"estimator", "sensor"}:
                raise ValueError("estimator: set it in a request of its own (with sensor, if any)")
            return self._set_estimator(args)
        if "sensor" in args:
            raise ValueError("sensor: goes with estimator only (rate, averaging and low-pass are the loop's)")
        rate = args.get("rate_hz", self.config.rate_hz)
        averaging = args.get("averaging", self.config.averaging)
        lowpass = args.get("lowpass_hz", self.config.lowpass_hz)
        if not isinstance(rate, (int, float)) or isinstance(rate, bool) or not 0.1 <= rate <= 10e3:
            raise ValueError("rate_hz: expected a number from 0.1 to 10000")
        if not isinstance(averaging, int) or isinstance(averaging, bool) or not 1 <= averaging <= 10_000:
            raise ValueError("averaging: expected an integer from 1 to 10000")
        if not isinstance(lowpass, (int, float)) or isinstance(lowpass, bool) or not 0 <= lowpass < rate / 2:
            raise ValueError(f"lowpass_hz: expected a number from 0 (off) to below half the rate ({rate / 2:g})")
        check_rate(self.config, float(rate))
        self.config.rate_hz, self.config.averaging, self.config.lowpass_hz = float(rate), averaging, float(lowpass)
        for s in self.sensors:
            s.filter.configure(averaging, float(lowpass), float(rate))
        return {"rate_hz": self.config.rate_hz, "averaging": averaging, "lowpass_hz": self.config.lowpass_hz}

    def _set_estimator(self, args: dict[str, Any]) -> dict[str, Any]:
        if set(args) - {"estimator", "sensor"}:
            raise ValueError("set estimator takes only sensor besides; set the rest in another request")
        estimator, name = args["estimator"], args.get("sensor")
        if estimator not in ("linear", "nonlinear"):
            raise ValueError(f'estimator: expected "linear" or "nonlinear", got {str(estimator)[:40]!r}')
        chosen = [s for s in self.sensors if name is None or s.name == name]
        if not chosen:
            raise ValueError(f"sensor: expected one of {[s.name for s in self.sensors]}, got {str(name)[:40]!r}")
        if estimator == "nonlinear":
            lacking = [s.name for s in chosen if s.nonlinear is None]
            if lacking:
                raise ValueError(f"no nonlinear calibration for {', '.join(lacking)}")
        for s in chosen:
            s.estimator = estimator
            s.filter.reset()
        return {"estimator": {s.name: s.estimator for s in self.sensors}}

    def reload(self) -> dict[str, Any]:
        """Re-read the configuration and calibrations; keep the old ones if the new are bad.

        Calibrations, rate, averaging, low-pass and tool offsets change at once;
        a change of bus, chips, scheduler or endpoints needs a restart.
        """
        self.notifier.reloading()
        try:
            new = load_config(self.config.path)
            fixed = [name for name, a, b in (
                ("bus", new.bus, self.config.bus), ("bus_hz", new.bus_hz, self.config.bus_hz),
                ("scheduler", new.scheduler, self.config.scheduler), ("chip", new.settings, self.config.settings),
                ("sensor addresses", [(s.name, s.addresses) for s in new.sensors],
                 [(s.name, s.addresses) for s in self.config.sensors]),
                ("endpoints", (new.publish, new.control), (self.config.publish, self.config.control))) if a != b]
            if fixed:
                raise ConfigError(f"{new.path}: changing {', '.join(fixed)} needs a restart; nothing was changed")
        except FtsensordError as exc:
            log.error("reload refused, the running configuration stays: %s", exc)
            self.notifier.ready(self.status_line())
            raise
        self.config = new
        self.sensors = [self._runtime(s) for s in new.sensors]
        log.info("reloaded %s", new.path)
        self.notifier.ready(self.status_line())
        return {"config": str(new.path), "calibrations": {s.name: str(s.calibration_path) for s in new.sensors}}

    # --- status --------------------------------------------------------------------------------
    def achieved_rate_hz(self) -> float | None:
        if len(self.starts) < 2 or self.starts[-1] == self.starts[0]:
            return None
        return (len(self.starts) - 1) / (self.starts[-1] - self.starts[0])

    def status_line(self) -> str:
        rate = self.achieved_rate_hz()
        return (f"{'%.1f' % rate if rate else '-'} Hz of {self.config.rate_hz:g} Hz "
                f"(bound {self.config.bound().rate_hz:.0f} Hz), {self.missed} missed, "
                f"{sum(not c.ok for c in self.chip_stats.values())} chip(s) failing")

    def _chip_status(self, address: int, stats: ChipStats) -> dict[str, Any]:
        h = self.reader.health[address]
        retry = max(0.0, h.retry_at - self.reader.bus.monotonic()) if h.failing else None
        return {**vars(stats), "state": "resetting" if h.step else "failing" if h.failing else "ok", "retry_in_s": retry,
                "reinits": h.reinits, "register_drifts": h.register_drifts, "stuck_detections": h.stuck_detections}

    def status(self) -> dict[str, Any]:
        bound = self.config.bound()
        return {
            "version": __version__, "uptime_s": round(self.clock() - self.started_at, 3),
            "config": str(self.config.path), "bus": self.config.bus, "scheduler": self.config.scheduler,
            "rate_hz": self.config.rate_hz, "achieved_rate_hz": self.achieved_rate_hz(),
            "bound_hz": bound.rate_hz, "bound": bound.describe(),
            "jitter_us": _percentiles_us(self.lateness),
            # What the loop leaves of its period: the bound counts the bus, this adds the CPU.
            "cycle_us": _percentiles_us(self.durations), "period_us": self.period_s * 1e6,
            "cycles": self.cycles, "missed_cycles": self.missed, "late_cycles": self.late,
            "averaging": self.config.averaging, "lowpass_hz": self.config.lowpass_hz,
            "chips": {f"0x{a:02X}": self._chip_status(a, c) for a, c in self.chip_stats.items()},
            "sensors": {s.name: {
                "calibration": str(s.config.calibration_path), "serial": s.config.calibration.serial,
                "frame": s.config.frame, "tared": s.tared, "estimator": s.estimator,
                "nonlinear_calibrated": s.nonlinear is not None, "fallbacks": s.fallbacks,
                "estimate_cpu_us": {"mean": float(np.mean(s.estimate_s)) * 1e6, "max": float(np.max(s.estimate_s)) * 1e6}
                if s.estimate_s else None,
                "tare_wrench": s.tare_wrench.round(6).tolist(),
            } for s in self.sensors},
            "streams": sorted(self.seq), "publish": self.config.publish, "control": self.config.control,
        }


def _percentiles_us(seconds: deque[float]) -> dict[str, float]:
    """p50, p99 and max of durations in s, in us (zeros before the first cycle)."""
    us = np.array(seconds) * 1e6 if seconds else np.zeros(1)
    return {"p50": float(np.percentile(us, 50)), "p99": float(np.percentile(us, 99)), "max": float(us.max())}
