"""The daemon: a coordinator over the loop's parts, one bus and two sockets.

Each cycle: the `Reader` reads every chip, each sensor's `SensorPipeline`
turns the results into a flagged, filtered wrench, the tip wrench is summed,
the orientation stream is read and `Gravity` makes the compensated wrenches,
every stream is published, `Tares` take their samples; between cycles,
`Control` answers requests until the next deadline (`LoopTiming`).

The daemon takes its dependencies (bus, configuration, sockets, notifier,
clock), so tests drive `Daemon.cycle` and `Daemon.handle_control` on a
virtual clock, and `ftsensord run` wires the real ones (`daemon.run`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import zmq

from ftsensord.acquire import choice
from ftsensord.acquire.board import know_board
from ftsensord.acquire.reader import Reader
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393
from ftsensord.chip.i2c import Bus, BusTiming
from ftsensord.config.accuracy import parse_accuracies
from ftsensord.config.file import Config, reload_config
from ftsensord.config.frames import TIP
from ftsensord.config.sensors import Calibrations, SensorConfig
from ftsensord.daemon.control import Control
from ftsensord.daemon.host import HostGuard
from ftsensord.daemon.loop import LoopTiming, serve_until
from ftsensord.daemon.plans import Plans
from ftsensord.daemon.realtime import Scheduling
from ftsensord.daemon.reloads import Reloads
from ftsensord.daemon.ros2child import BridgeWatch
from ftsensord.daemon.sdnotify import Notifier
from ftsensord.daemon.status import ChipLedger, status_line, status_reply
from ftsensord.errors import ChipError, ConfigError, FtsensordError
from ftsensord.processing.accuracy import Plan, Sensor, apply_accuracy, plan
from ftsensord.processing.filters import WrenchFilter
from ftsensord.processing.gravity import Gravity
from ftsensord.processing.pipeline import SensorPipeline, SensorSample, tip_moves, tip_wrench, use_estimator
from ftsensord.processing.tare import Tares, carry_tares
from ftsensord.processing.uncertainty import tip_sigma
from ftsensord.protocol import wire
from ftsensord.protocol.orientation import OrientationReceiver

log = logging.getLogger("ftsensord")


class Daemon:
    """One bus, its sensors, a publisher socket and a control socket; what control
    requests do is `commands.Commands`'."""

    def __init__(
        self,
        config: Config,
        bus: Bus,
        publisher: zmq.Socket,
        control: zmq.Socket | None = None,
        *,
        notifier: Notifier | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
        orientation: zmq.Socket | None = None,
        guard: HostGuard | None = None,
        background_reload: bool = False,
        scheduling: Scheduling | None = None,
    ):
        self.config = config
        self.bus = bus
        self.publisher = publisher
        self.guard = guard or HostGuard()
        self.scheduling = scheduling or Scheduling()  # what `run` asked of the kernel, for status
        self.notifier = notifier or Notifier(environ={})
        self.clock, self.wall = clock, wall
        self.reader = self._reader(config)
        self.board_timing: BusTiming | None = getattr(bus, "timing", None)  # a real bus's: measured at start
        self.chips = ChipLedger({s.name: s.addresses for s in config.sensors})
        self.sensors = [self._pipeline(s, config) for s in config.sensors]
        self.orientations = OrientationReceiver(orientation, {*self.sensor_names, TIP})
        self.gravity = self._gravity(config)
        self.timing = LoopTiming()
        self._tip: tuple[dict[str, np.ndarray] | None, list[tuple[str, np.ndarray]]] = (
            None,
            [],
        )  # poses, tip_moves
        self.control = Control(control, self)
        self.tares = Tares(self.control.reply)
        self.reloads = (
            Reloads(self._prepared, self.finish_reload, self.control.reply) if background_reload else None
        )
        # `set --accuracy`'s plan in a worker thread too (`run`'s daemon); None: planned at once
        self.plans = Plans(self.control.reply) if background_reload else None
        self.streams: set[str] = set()
        self.started_at = clock()
        self.stop_requested = self.reload_requested = False
        self.ready = False
        self.calibrations = Calibrations().remember(config.sensors)
        self.bridge = BridgeWatch()  # the ROS 2 bridge `run` started beside it, if any
        self.outputs: list[Any] = []  # `run` adds ([ros2] output "in-loop"): after_sends(...) each cycle
        #: The last cycle's tool tip sigma (N, Nm; NaN unknown), as sent on sigma/wrench/tip: for the outputs.
        self.tip_sigma: np.ndarray | None = None

    def _reader(self, config: Config) -> Reader:
        chips = [MLX90393(self.bus, a, sleep=self.bus.sleep) for a in config.addresses]
        return Reader(
            self.bus,
            chips,
            config.scheduler,
            config.settings,
            config.bus_hz,
            config.bus_overhead_s,
            stuck_cycles=config.stuck_cycles,
            readback_every=config.readback_every,
            temperature=config.temperature_every > 0,
        )

    @staticmethod
    def _pipeline(s: SensorConfig, config: Config) -> SensorPipeline:
        smoothing = WrenchFilter(config.averaging, config.lowpass_hz, config.rate_hz)
        return SensorPipeline.build(
            s,
            smoothing,
            config.max_missing_chips,
            config.settings,
            config.temperature_every > 0,
            config.rate_hz,
        )

    def _gravity(self, config: Config) -> Gravity | None:
        g = config.gravity
        return (
            None
            if g is None
            else Gravity(
                g, config.tool_poses, self.orientations, config.averaging, config.lowpass_hz, config.rate_hz
            )
        )

    @property
    def period_s(self) -> float:
        return 1.0 / self.config.rate_hz

    @property
    def sensor_names(self) -> list[str]:
        return [s.name for s in self.sensors]

    # --- the loop ------------------------------------------------------------------
    def start(self) -> None:
        """Know the board (a real adapter: driver, clock and ioctl cost measured), start every chip."""
        if getattr(self.bus, "number", None) is not None:
            self.board_timing = measure_board(self.bus, self.config)
            self._choose_on_board()
        thin = self.config.bound(self.board_timing).cycle_s * self.config.rate_hz > 1 - choice.TARGET_SPARE
        log.log(logging.WARNING if thin else logging.INFO, "schedule: %s", self.config.choice)
        if self.board_timing is not None:
            self.reader.use_timing(self.board_timing)
        for address, exc in self.reader.start().items():
            self.chips.failed_to_start(address, exc)
            log.warning("chip 0x%02X failed to start: %s", address, exc)

    def _choose_on_board(self) -> None:
        """Choose again what the file leaves unnamed, from the measured bound (a new reader
        if the choice changes: nothing has used the first yet); a named one is checked.
        Where nothing holds, the loop runs late with the fastest option, said in the log."""
        before = self.config.scheduler, self.config.readback_every
        self.config.choose(self.board_timing, strict=False)
        if (self.config.scheduler, self.config.readback_every) != before:
            self.reader = self._reader(self.config)

    def run(self) -> int:
        """Cycle until asked to stop; then put the chips to idle. Returns the exit status:
        0, or 1 when the runtime folder's files are gone (systemd restarts the service)."""
        self.start()
        deadline = self.clock()
        while not self.stop_requested:
            deadline, lateness = self.timing.skip_missed(deadline, self.clock(), self.period_s)
            self.cycle(lateness)
            deadline += self.period_s
            lost = self.guard.between_cycles()  # right after the cycle, in its slack
            if lost is not None:  # its files gone: unreachable, so exit, and systemd restarts it
                log.error("%s; exiting for a restart with a new folder", lost)
                self.shutdown()
                return 1
            self.serve_until(deadline)
            if self.reload_requested:  # SIGHUP, handled between cycles
                self.reload_requested = False
                try:
                    self.request_reload(None)
                except FtsensordError:
                    pass  # logged; the running configuration stays
            if self.reloads is not None:
                self.reloads.poll()
            if self.plans is not None:
                self.plans.poll()
        self.shutdown()
        return 0

    def serve_until(self, deadline: float) -> None:
        """Answer control requests until ``deadline`` within this cycle's budget (`loop.serve_until`)."""
        serve_until(
            self.control,
            deadline,
            self.period_s,
            self.clock,
            self.bus.sleep,
            lambda: self.stop_requested,
            self.guard.caps,
        )

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
        results = self.reader.read(zyxt)
        t_mono, t_wall = self.clock(), self.wall()
        # Every stream's sequence number is the cycle's: a deadline the loop skipped is a jump.
        seq = self.timing.cycles + self.timing.missed
        gap = self.timing.gap(seq)
        if gap:  # a gap in the input (a stall, skipped deadlines): the filters' memory says
            for p in self.sensors:  # nothing of the load now; restart them
                p.gap(gap)
            if self.gravity is not None:
                self.gravity.restart()
        self.orientations.drain(start)
        samples: dict[str, SensorSample] = {}
        for p in self.sensors:
            R = self.gravity.orientation(p.name, start)[0] if p.stray is not None and self.gravity else None
            s = samples[p.name] = p.step(results, wire.FLAG_LATE if late else 0, R)
            # Each wrench as soon as it is known: a haptic loop waits for it; flux is for
            # debugging, and the tares' and counters' bookkeeping waits until after the sends.
            # Its sigma just before it, so that a subscriber to both has it in hand with the wrench.
            self._publish(
                f"sigma/wrench/{p.name}", wire.KIND_SIGMA, seq, t_mono, t_wall, s.flags, s.sigma.sigma
            )
            self._publish(f"wrench/{p.name}", wire.KIND_WRENCH, seq, t_mono, t_wall, s.flags, s.wrench)
            if p is self.sensors[0]:
                self.timing.published(self.clock() - t_mono)
        poses = self.config.tool_poses
        if poses is not self._tip[0]:  # a new configuration: its transforms, once
            self._tip = (poses, tip_moves(poses))
        tip = tip_wrench(samples, self._tip[1]) if poses else None
        if tip is not None:
            moves = self._tip[1]
            sigma = self.tip_sigma = tip_sigma([(X, samples[name].sigma) for name, X in moves])
            self._publish("sigma/wrench/tip", wire.KIND_SIGMA, seq, t_mono, t_wall, tip[1], sigma)
            self._publish("wrench/tip", wire.KIND_WRENCH, seq, t_mono, t_wall, tip[1], tip[0])
        compensated = (
            self.gravity.streams(samples, tip, self.tip_sigma, self.sensors, start) if self.gravity else []
        )
        for c in compensated:  # each with its sigma just before it, as the raw ones
            self._publish(wire.SIGMA_PREFIX + c.topic, wire.KIND_SIGMA, seq, t_mono, t_wall, c.flags, c.sigma)
            self._publish(c.topic, wire.KIND_WRENCH, seq, t_mono, t_wall, c.flags, c.wrench)
        for name, s in samples.items():
            self._publish(f"flux/{name}", wire.KIND_FLUX, seq, t_mono, t_wall, s.flux_flags, s.flux)
        for out in self.outputs:  # after every ZeroMQ send: no ZeroMQ sample waits for them
            out.after_sends(seq, t_wall, samples, tip, compensated)
        self.reader.upkeep()  # the register read-back: bus time no sample waits for
        for p in self.sensors:
            s = samples[p.name]
            if s.valid:
                flags, gravity = self.gravity.tare_input(p.name, start) if self.gravity else (0, None)
                self.tares.feed(p.name, s.flux, s.flags | flags, gravity)
        self.tares.advance(self.sensors)
        self.chips.count_all(results)
        self.timing.end(self.clock() - start)
        if not self.ready:
            self.ready = True
            self.notifier.ready(self.status_line())
            log.info("ready: %s", self.status_line())
        self.notifier.watchdog()
        if self.timing.cycles % max(1, int(self.config.rate_hz)) == 0:
            self.notifier.status(self.status_line())
            self.bridge.check()

    def _publish(
        self, topic: str, kind: int, seq: int, t_mono: float, t_wall: float, flags: int, values: np.ndarray
    ) -> None:
        self.streams.add(topic)
        try:
            self.publisher.send(wire.encode(topic, kind, seq, t_mono, t_wall, flags, values), zmq.NOBLOCK)
        except zmq.Again:
            pass  # no room for a slow subscriber: latest value wins, the sequence shows the gap

    # --- status (`daemon.status`) ---------------------------------------------------------
    def status_line(self) -> str:
        return status_line(self)

    def status(self) -> dict[str, Any]:
        return status_reply(self)

    # What control requests do (the `control.Controlled` surface): tare, untare, loop
    # settings, estimator, reload.

    def request_tare(self, envelope: list[bytes], sensors: list[str], samples: int) -> None:
        """Start a tare (answered when done); ValueError when one of ``sensors`` has one under way."""
        self.tares.request(envelope, sensors, samples)

    def untare(self, sensors: list[str]) -> dict[str, Any]:
        """Back to the calibrations' own zeros; refused for a sensor with a tare under way."""
        return {"removed_tare_wrench": self.tares.untare([s for s in self.sensors if s.name in sensors])}

    def loop_settings(self) -> tuple[float, int, float]:
        return self.config.rate_hz, self.config.averaging, self.config.lowpass_hz

    def set_loop(self, rate_hz: float, averaging: int, lowpass_hz: float) -> dict[str, Any]:
        before = self.config.rate_hz
        self.config.rate_hz = rate_hz
        try:  # what the file leaves unnamed follows the rate; the scheduler stays (a restart chooses it)
            self.config.choose(self.board_timing, running=self.config.scheduler)
        except ConfigError:
            self.config.rate_hz = before
            raise
        self.reader.readback_every = self.config.readback_every
        self.config.averaging, self.config.lowpass_hz = averaging, lowpass_hz
        for s in self.sensors:
            s.configure(averaging, lowpass_hz, rate_hz)
        if self.gravity is not None:
            self.gravity.configure(averaging, lowpass_hz, rate_hz)  # the weight lags as the wrench
        return {"rate_hz": rate_hz, "averaging": averaging, "lowpass_hz": lowpass_hz}

    def set_accuracy(self, value: object, envelope: list[bytes] | None = None) -> dict[str, Any] | None:
        """The fastest conversion (OSR, DIG_FILT), averaging and rate (the low-pass off) whose
        predicted sigma at rest meets ``value`` ("0.02N", "0.5mNm", or a list of one of each)
        for every sensor, at its estimator and tare, with the running scheduler (only a restart
        chooses it again), as a sensor table's ``accuracy`` chooses them at start; applied
        between cycles (`convert`, then as `set_loop`). With `plans` and a client's
        ``envelope``, planned in its worker thread and answered when applied (None now); else
        at once (the reply's result). ConfigError, nothing changed, when no setting meets it,
        the running scheduler cannot hold the new conversion, or the sensors or configuration
        changed while it was planned; a chip that refuses it is said, as `convert` leaves it."""
        targets = parse_accuracies(value, "accuracy")
        running = self.config
        before, planned_on = running.settings, self._planned_on()
        inputs = (
            {p.name: targets for p in self.sensors},
            [Sensor(p.config, p.estimator, p.tare_samples) for p in self.sensors],
            running.bus_levers(self.board_timing),
            running.scheduler,  # kept: only a restart chooses the scheduler again
            running.readback_every if "readback_every" in running.named else None,
        )

        def work() -> Plan:
            return plan(*inputs, running=before)

        def finish(found: Plan) -> dict[str, Any]:
            if self._planned_on() != planned_on:
                raise ConfigError(
                    "accuracy: a tare, an estimator or the configuration changed while it was "
                    "planned, and the plan with them: nothing changed; ask again"
                )
            # As `set` checks a rate: the watchdog's pings follow cycles.
            self.notifier.check_rate(found.rate_hz)
            self.convert(found.settings, found.rate_hz)
            done = self.set_loop(found.rate_hz, found.averaging, 0.0)
            return {
                **done,
                "accuracy": [t.text for t in targets],
                "effective_rate_hz": round(found.effective_hz, 3),
                "osr": found.settings.osr,
                "dig_filt": found.settings.dig_filt,
                "conversion_changed": found.settings != before,
                "sigma": found.sigma,
                "plan": found.describe(),
            }

        if self.plans is None or envelope is None:
            return finish(work())
        self.plans.request(envelope, work, finish)
        return None

    def _planned_on(self) -> tuple[Any, ...]:
        """What an accuracy's plan depends on, by identity and version: the configuration (a
        reload makes another), its conversion and checks, each pipeline, its tare and estimator."""
        c = self.config
        return (
            id(c),
            c.settings,
            c.scheduler,
            c.readback_every,
            tuple((id(p), p.version, p.estimator, p.tare_samples) for p in self.sensors),
        )

    def convert(self, settings: mlx.Settings, rate_hz: float) -> None:
        """Between cycles: the chips' conversion changed to ``settings`` (the loop to run at
        ``rate_hz`` next, set by the caller): written to every chip (`Reader.convert`, which
        times the reads by it from the next cycle), then each sensor's pipeline built again
        for its noise (`channel_sigma_t`: the sigma, the redundancy check's weights), keeping
        its estimator and tare (`carry_tares`). A tare holds: it is a flux in tesla, and the
        chips' scale (GAIN_SEL, RES, HALLCONF) and offset do not depend on OSR and DIG_FILT,
        which set only how many ADC samples a conversion averages and how they are filtered;
        the mean of the words read moves by a part of an LSB where the new noise dithers it
        otherwise, the undithered quantisation a load brings, which the plan's sigma counts.
        ConfigError, nothing changed, when the running scheduler cannot hold the conversion
        at ``rate_hz``; ConfigError naming the chip when one refuses it: every chip then runs
        the running conversion or is failing, reset to come back at it (`Reader.convert`)."""
        running = self.config
        if settings == running.settings:
            return
        trial = replace(running, settings=settings, rate_hz=rate_hz)
        trial.choose(self.board_timing, f"{settings.conversion} at {rate_hz:g} Hz", running=running.scheduler)
        self._write_conversion(settings)
        running.settings = settings
        old, self.sensors = self.sensors, [self._pipeline(s, running) for s in running.sensors]
        for o, p in zip(old, self.sensors):
            if p.estimator != o.estimator:
                p.use(o.estimator)  # `set --estimator`'s, which the file does not hold
        carry_tares(old, self.sensors, f"the conversion's change to {settings.conversion}")

    def _write_conversion(self, settings: mlx.Settings) -> None:
        """``settings`` written to the chips (`Reader.convert`) when the reader runs others;
        ConfigError naming the chip that refused them, the running ones kept."""
        was = self.reader.settings
        if settings == was:
            return
        try:
            self.reader.convert(settings)
        except ChipError as exc:
            raise ConfigError(
                f"{settings.conversion} not written: {exc}; that chip is reset and comes back at the "
                f"running conversion, {was.conversion}, which the others kept: nothing else changed"
            ) from exc
        log.info("conversion now %s (was %s)", settings.conversion, was.conversion)

    def set_estimator(self, estimator: str, sensor: str | None) -> dict[str, Any]:
        return {"estimator": use_estimator(self.sensors, estimator, sensor)}

    def request_reload(self, envelope: list[bytes] | None) -> dict[str, Any] | None:
        """A reload asked by a client (its envelope) or SIGHUP (None): handed to `reloads`
        (answered when done: None now), or done at once without them (the result)."""
        if self.reloads is not None:
            self.reloads.request(envelope)
            return None
        return self.reload()

    def reload(self) -> dict[str, Any]:
        """Re-read the configuration and calibrations now; keep the old ones if the new are bad.

        Calibrations, rate, averaging, low-pass, the chips' conversion (OSR, DIG_FILT), tool
        poses and gravity change at once; a change of bus, chips' addresses or other settings,
        scheduler or endpoints needs a restart. Unchanged
        calibration files are not read again (`config.Calibrations`).
        """
        prepared = self._prepared()
        reply = self.finish_reload(prepared)
        if isinstance(prepared, FtsensordError):
            raise prepared
        if not reply["ok"]:  # the chips refused the file's conversion
            raise ConfigError(reply["error"])
        return reply["result"]

    def _prepared(self) -> tuple[Config, list[SensorPipeline]] | FtsensordError:
        """The file work of a reload (`reloads.Reloads` runs it in its thread): the new
        configuration and its pipelines, or why they were refused."""
        self.notifier.reloading()
        try:
            # A sensor's accuracy planned as at start, on the configured timing (`run`): the
            # measured board's would change the plan, and with it the conversion.
            new = reload_config(
                self.config, self.calibrations, self.board_timing, lambda c, _timing: apply_accuracy(c)
            )
            self.notifier.check_rate(new.rate_hz, f"{new.path}: rate_hz")
        except FtsensordError as exc:
            return exc
        return new, [self._pipeline(s, new) for s in new.sensors]

    def finish_reload(self, prepared: tuple[Config, list[SensorPipeline]] | FtsensordError) -> dict[str, Any]:
        """Swap in what `_prepared` made (between cycles), the chips' conversion first where it
        changed (their noise is what the pipelines were built for); the reply to the request."""
        if not isinstance(prepared, FtsensordError):
            try:
                self._write_conversion(prepared[0].settings)
            except ConfigError as exc:
                prepared = ConfigError(f"{prepared[0].path}: chip: {exc}")
        if isinstance(prepared, FtsensordError):
            log.error("reload refused, the running configuration stays: %s", prepared)
            self.notifier.ready(self.status_line())
            return {"ok": False, "error": str(prepared)}
        new, pipelines = prepared
        self.config = new
        # The reader's care follows the file: stuck detection and register read-back.
        self.reader.readback_every = new.readback_every
        self.reader.care_for(new.stuck_cycles)
        old, self.sensors = self.sensors, pipelines
        tares = carry_tares(old, self.sensors)  # kept where the calibration is the same, else dropped, said
        self.gravity = self._gravity(new)
        log.info("reloaded %s; schedule: %s", new.path, new.choice)
        self.notifier.ready(self.status_line())
        return {
            "ok": True,
            "result": {
                "config": str(new.path),
                "tare": tares,
                "calibrations": {s.name: str(s.calibration_path) for s in new.sensors},
            },
        }


def measure_board(bus: Bus, config: Config) -> BusTiming:
    """A real adapter's rules, ioctl cost and clock, measured through the first chip that
    answers (`acquire.board.know_board`); logs its warnings."""
    report = None
    for address in config.addresses[:4]:
        report = know_board(bus, address, config.bus_hz)
        if report.measured is not None:
            break
    assert report is not None  # a configuration names at least one chip
    for warning in report.warnings:
        log.warning("%s", warning)
    m = report.measured
    log.info(
        "I2C adapter %s (%s): %s",
        report.driver or "unknown",
        report.adapter or "rules unknown",
        "not measured (no chip answered)"
        if m is None
        else f"ioctl {m.ioctl_s * 1e6:.0f} us, clock {m.clock_hz / 1e3:.0f} kHz measured",
    )
    return report.timing
