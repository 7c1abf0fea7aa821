"""The daemon: a coordinator over the loop's parts, one bus and two sockets.

Each cycle: the `Reader` reads every chip, each sensor's `SensorPipeline`
turns the results into a flagged, filtered wrench, the tip wrench is summed,
every stream is published, `Tares` take their samples; between cycles,
`Control` answers requests until the next deadline (`LoopTiming`).

The daemon takes its dependencies (bus, configuration, sockets, notifier,
clock), so tests drive `Daemon.cycle` and `Daemon.handle_control` on a
virtual clock, and `ftsensord run` wires the real ones (`service.run`).
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable

import numpy as np
import zmq

from .. import __version__
from ..acquire.reader import Reader
from ..chip import mlx90393 as mlx
from ..chip.driver import MLX90393
from ..chip.i2c import Bus
from ..errors import ConfigError, FtsensordError
from ..model import se3
from . import wire
from .config import Config, SensorConfig, check_rate, load_config, needs_restart
from .control import Control
from .filters import WrenchFilter
from .loop import LoopTiming, percentiles_us
from .pipeline import SensorPipeline
from .sdnotify import Notifier
from .status import ChipLedger
from .tare import Tares

log = logging.getLogger("ftsensord")


class Daemon:
    """One bus, its sensors, a publisher socket and a control socket."""

    def __init__(self, config: Config, bus: Bus, publisher: zmq.Socket, control: zmq.Socket | None = None, *,
                 notifier: Notifier | None = None, clock: Callable[[], float] = time.monotonic,
                 wall: Callable[[], float] = time.time):
        self.config = config
        self.bus = bus
        self.publisher = publisher
        self.notifier = notifier or Notifier(environ={})
        self.clock, self.wall = clock, wall
        chips = [MLX90393(bus, a, sleep=bus.sleep) for a in config.addresses]
        self.reader = Reader(bus, chips, config.scheduler, config.settings, config.bus_hz, config.bus_overhead_s,
                             stuck_cycles=config.stuck_cycles, readback_every=config.readback_every)
        self.chips = ChipLedger({s.name: s.addresses for s in config.sensors})
        self.sensors = [self._pipeline(s) for s in config.sensors]
        self.timing = LoopTiming()
        self.control = Control(control, self)
        self.tares = Tares(self.control.reply)
        self.streams: set[str] = set()
        self.started_at = clock()
        self.stop_requested = self.reload_requested = False
        self.ready = False

    def _pipeline(self, s: SensorConfig) -> SensorPipeline:
        smoothing = WrenchFilter(self.config.averaging, self.config.lowpass_hz, self.config.rate_hz)
        return SensorPipeline.build(s, smoothing, self.config.max_missing_chips)

    @property
    def period_s(self) -> float:
        return 1.0 / self.config.rate_hz

    @property
    def sensor_names(self) -> list[str]:
        return [s.name for s in self.sensors]

    # --- the loop ------------------------------------------------------------------
    def start(self) -> None:
        for address, exc in self.reader.start().items():
            self.chips.failed_to_start(address, exc)
            log.warning("chip 0x%02X failed to start: %s", address, exc)

    def run(self) -> int:
        """Cycle until asked to stop; then put the chips to idle. Returns the exit status."""
        self.start()
        deadline = self.clock()
        while not self.stop_requested:
            deadline, lateness = self.timing.skip_missed(deadline, self.clock(), self.period_s)
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
        socket = self.control.socket
        if socket is not None:
            poller.register(socket, zmq.POLLIN)
        while not self.stop_requested:
            self.control.serve_waiting()
            remaining = deadline - self.clock()
            if remaining <= 0:
                return
            if remaining > 2e-3 and socket is not None:
                poller.poll(timeout=int((remaining - 1e-3) * 1000))
            else:
                time.sleep(remaining)

    def handle_control(self) -> None:
        """Answer every waiting control request now (tests call this between cycles)."""
        self.control.serve_waiting()

    def shutdown(self) -> None:
        self.notifier.stopping()
        self.reader.stop()
        t = self.timing
        log.info("stopped after %d cycles (%d missed, %d late)", t.cycles, t.missed, t.late)

    def cycle(self, lateness: float = 0.0) -> None:
        """Read every chip once, estimate and publish every stream."""
        start = self.clock()
        late = self.timing.begin(start, lateness, self.period_s)
        every = self.config.temperature_every
        zyxt = mlx.ZYXT_XYZT if every and self.timing.cycles % every == 0 else mlx.ZYXT_XYZ
        results = {r.address: r for r in self.reader.read(zyxt)}
        t_mono, t_wall = self.clock(), self.wall()
        # Every stream's sequence number is the cycle's: a deadline the loop skipped is a jump.
        seq = self.timing.cycles + self.timing.missed
        for r in results.values():
            self.chips.count(r)
        samples = {p.name: p.step(results, wire.FLAG_LATE if late else 0) for p in self.sensors}
        for name, s in samples.items():
            if s.valid:
                self.tares.feed(name, s.flux, s.flags)
            # Wrenches first: a haptic loop waits for them; the flux streams are for debugging.
            self._publish(f"wrench/{name}", wire.KIND_WRENCH, seq, t_mono, t_wall, s.flags, s.wrench)
        if self.config.tool_offsets_m:
            tip = sum((se3.wrench_transform(se3.pose(p=offset)) @ samples[name].wrench
                       for name, offset in self.config.tool_offsets_m.items()), start=np.zeros(6))
            tip_flags = 0
            for s in samples.values():
                tip_flags |= s.flags  # the tip is as good as its worst sensor
            self._publish("wrench/tip", wire.KIND_WRENCH, seq, t_mono, t_wall, tip_flags, tip)
        for name, s in samples.items():
            self._publish(f"flux/{name}", wire.KIND_FLUX, seq, t_mono, t_wall, s.flux_flags, s.flux)
        self.tares.advance(self.sensors)
        self.timing.end(self.clock() - start)
        if not self.ready:
            self.ready = True
            self.notifier.ready(self.status_line())
            log.info("ready: %s", self.status_line())
        self.notifier.watchdog()
        if self.timing.cycles % max(1, int(self.config.rate_hz)) == 0:
            self.notifier.status(self.status_line())

    def _publish(self, topic: str, kind: int, seq: int, t_mono: float, t_wall: float, flags: int,
                 values: np.ndarray) -> None:
        self.streams.add(topic)
        try:
            self.publisher.send(wire.encode(topic, kind, seq, t_mono, t_wall, flags, values), zmq.NOBLOCK)
        except zmq.Again:
            pass  # no room for a slow subscriber: latest value wins, the sequence shows the gap

    # --- what control requests do (`control.Controlled`) ---------------------------------
    def request_tare(self, envelope: list[bytes], sensors: list[str], samples: int) -> None:
        self.tares.request(envelope, sensors, samples)

    def loop_settings(self) -> tuple[float, int, float]:
        return self.config.rate_hz, self.config.averaging, self.config.lowpass_hz

    def set_loop(self, rate_hz: float, averaging: int, lowpass_hz: float) -> dict[str, Any]:
        check_rate(self.config, rate_hz)
        self.config.rate_hz, self.config.averaging, self.config.lowpass_hz = rate_hz, averaging, lowpass_hz
        for s in self.sensors:
            s.filter.configure(averaging, lowpass_hz, rate_hz)
        return {"rate_hz": rate_hz, "averaging": averaging, "lowpass_hz": lowpass_hz}

    def set_estimator(self, estimator: str, sensor: str | None) -> dict[str, Any]:
        chosen = [s for s in self.sensors if sensor is None or s.name == sensor]
        lacking = [s.name for s in chosen if estimator == "nonlinear" and s.nonlinear is None]
        if lacking:
            raise ValueError(f"no nonlinear calibration for {', '.join(lacking)}")
        for s in chosen:
            s.use(estimator)
        return {"estimator": {s.name: s.estimator for s in self.sensors}}

    def reload(self) -> dict[str, Any]:
        """Re-read the configuration and calibrations; keep the old ones if the new are bad.

        Calibrations, rate, averaging, low-pass and tool offsets change at once;
        a change of bus, chips, scheduler or endpoints needs a restart.
        """
        self.notifier.reloading()
        try:
            new = load_config(self.config.path)
            fixed = needs_restart(self.config, new)
            if fixed:
                raise ConfigError(f"{new.path}: changing {', '.join(fixed)} needs a restart; nothing was changed")
        except FtsensordError as exc:
            log.error("reload refused, the running configuration stays: %s", exc)
            self.notifier.ready(self.status_line())
            raise
        self.config = new
        self.sensors = [self._pipeline(s) for s in new.sensors]
        log.info("reloaded %s", new.path)
        self.notifier.ready(self.status_line())
        return {"config": str(new.path), "calibrations": {s.name: str(s.calibration_path) for s in new.sensors}}

    # --- status --------------------------------------------------------------------------------
    def status_line(self) -> str:
        rate = self.timing.achieved_rate_hz()
        return (f"{'%.1f' % rate if rate else '-'} Hz of {self.config.rate_hz:g} Hz "
                f"(bound {self.config.bound().rate_hz:.0f} Hz), {self.timing.missed} missed, "
                f"{self.chips.failing} chip(s) failing")

    def status(self) -> dict[str, Any]:
        bound, t = self.config.bound(), self.timing
        return {
            "version": __version__, "uptime_s": round(self.clock() - self.started_at, 3),
            "config": str(self.config.path), "bus": self.config.bus, "scheduler": self.config.scheduler,
            "rate_hz": self.config.rate_hz, "achieved_rate_hz": t.achieved_rate_hz(),
            "bound_hz": bound.rate_hz, "bound": bound.describe(),
            "jitter_us": percentiles_us(t.lateness),
            # What the loop leaves of its period: the bound counts the bus, this adds the CPU.
            "cycle_us": percentiles_us(t.durations), "period_us": self.period_s * 1e6,
            "cycles": t.cycles, "missed_cycles": t.missed, "late_cycles": t.late,
            "averaging": self.config.averaging, "lowpass_hz": self.config.lowpass_hz,
            "chips": self.chips.report(self.reader.health, self.reader.bus.monotonic()),
            "sensors": {s.name: s.status() for s in self.sensors},
            "streams": sorted(self.streams), "publish": self.config.publish, "control": self.config.control,
        }
