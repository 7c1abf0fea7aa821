"""What control requests do to the daemon (the `control.Controlled` surface): tare, untare,
loop settings, estimator, reload. A part of `Daemon` (its base class), kept apart so that
each stays a size one can read."""

from __future__ import annotations

import logging
from typing import Any

from ..acquire.reader import Reader
from ..chip.i2c import BusTiming
from ..errors import ConfigError, FtsensordError
from .config import Config, reload_config
from .gravity import Gravity
from .pipeline import SensorPipeline, use_estimator
from .reloads import Reloads
from .sdnotify import Notifier
from .sensorconf import Calibrations
from .tare import Tares, carry_tares

log = logging.getLogger("ftsensord")


class Commands:
    """The daemon's answers to control requests; the attributes, and the methods
    ``_pipeline``, ``_gravity`` and ``status_line``, are the `Daemon`'s."""

    config: Config
    sensors: list[SensorPipeline]
    gravity: Gravity | None
    tares: Tares
    notifier: Notifier
    calibrations: Calibrations
    board_timing: BusTiming | None
    reader: Reader
    reloads: Reloads | None  # None: reloads done at once, in the caller's thread (tests)

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
            s.filter.configure(averaging, lowpass_hz, rate_hz)
            s.creep.configure(rate_hz)  # the silicone stage's coefficients are the period's: afresh
        if self.gravity is not None:
            self.gravity.configure(averaging, lowpass_hz, rate_hz)  # the weight lags as the wrench
        return {"rate_hz": rate_hz, "averaging": averaging, "lowpass_hz": lowpass_hz}

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

        Calibrations, rate, averaging, low-pass, tool poses and gravity change at once;
        a change of bus, chips, scheduler or endpoints needs a restart. Unchanged
        calibration files are not read again (`config.Calibrations`).
        """
        prepared = self._prepared()
        reply = self.finish_reload(prepared)
        if isinstance(prepared, FtsensordError):
            raise prepared
        return reply["result"]

    def _prepared(self) -> tuple[Config, list[SensorPipeline]] | FtsensordError:
        """The file work of a reload (`reloads.Reloads` runs it in its thread): the new
        configuration and its pipelines, or why they were refused."""
        self.notifier.reloading()
        try:
            new = reload_config(self.config, self.calibrations, self.board_timing)
            self.notifier.check_rate(new.rate_hz, f"{new.path}: rate_hz")
        except FtsensordError as exc:
            return exc
        return new, [self._pipeline(s, new) for s in new.sensors]

    def finish_reload(self, prepared: tuple[Config, list[SensorPipeline]] | FtsensordError) -> dict[str, Any]:
        """Swap in what `_prepared` made (between cycles); the reply to the request."""
        if isinstance(prepared, FtsensordError):
            log.error("reload refused, the running configuration stays: %s", prepared)
            self.notifier.ready(self.status_line())
            return {"ok": False, "error": str(prepared)}
        new, pipelines = prepared
        self.config = new
        # The reader's care follows the file: stuck detection and register read-back.
        self.reader.readback_every = new.readback_every
        self.reader.stuck_cycles = self.reader.care.stuck_cycles = new.stuck_cycles
        old, self.sensors = self.sensors, pipelines
        tares = carry_tares(old, self.sensors)  # kept where the calibration is the same, else dropped, said
        self.gravity = self._gravity(new)
        log.info("reloaded %s; schedule: %s", new.path, new.choice)
        self.notifier.ready(self.status_line())
        return {"ok": True, "result": {"config": str(new.path), "tare": tares,
                                       "calibrations": {s.name: str(s.calibration_path) for s in new.sensors}}}
