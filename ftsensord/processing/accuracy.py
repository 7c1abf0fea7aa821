"""The fastest settings whose predicted sigma meets an accuracy (`config.accuracy`).

For each conversion setting (OSR, DIG_FILT) the loop's rate is the fastest that holds with
`choice.TARGET_SPARE` of the period left (`choice.options`: the computed bound of the
schedulers the configuration leaves open), and for each averaging (powers of two up to
`MAX_AVERAGING`, the low-pass off) each sensor's sigma is what `status` shows at rest
(`uncertainty.Uncertainty.predicted`: the chips' noise at that setting through the
estimator in use, times the averaging's variance factor, plus the tare's noise and the
calibration's model error) with the quantisation the chips' noise leaves undithered, as a
load brings it (`predicted`'s ``loaded``: at the longest conversions most of the LSB's share,
which averaging does not shrink). The plan is the one that gives an independent sample most
often, ``rate / averaging`` (a tie: the least averaging); None meets it when even the
longest conversion and the most averaging leave a sigma above the target, which the error
says with the part averaging cannot shrink (the model error, the tare's noise and the
undithered quantisation).

Why averaging and not the low-pass: at equal variance the moving average of n samples has
forgotten a step after n samples; a first-order low-pass of the same variance factor
(alpha / (2 - alpha) = 1 / n) keeps a tail of it for longer (`filters.variance_factors`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ftsensord.acquire import choice
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.i2c import BusTiming
from ftsensord.config.accuracy import Accuracy
from ftsensord.config.file import Config
from ftsensord.config.sensors import SensorConfig
from ftsensord.errors import ConfigError
from ftsensord.processing.filters import variance_factors
from ftsensord.processing.pipeline import channel_lsb_t, channel_sigma_t
from ftsensord.processing.uncertainty import AXES, Uncertainty

#: The most averaging considered: 256 samples (2.6 s at 100 Hz), beyond which a sensor
#: that is still too noisy needs another calibration, not more waiting.
MAX_AVERAGING = 256
AVERAGINGS = tuple(2**k for k in range(MAX_AVERAGING.bit_length()))
#: The daemon's fastest loop (`Config`'s rate_hz limit).
MAX_RATE_HZ = 10e3


@dataclass(frozen=True)
class Sensor:
    """What a sensor's predicted sigma depends on: its configuration (model, calibration
    report), the estimator in use and the samples its tare averaged (None: not tared)."""

    config: SensorConfig
    estimator: str
    tare_samples: int | None = None


@dataclass(frozen=True)
class Plan:
    """Settings that meet the targets: the conversion, the loop's ``rate_hz``, ``averaging``
    (the low-pass off), and each sensor's predicted sigma there (6, N and Nm)."""

    settings: mlx.Settings
    rate_hz: float
    averaging: int
    sigma: dict[str, list[float]]

    @property
    def effective_hz(self) -> float:
        """Independent samples a second: the rate over the averaging."""
        return self.rate_hz / self.averaging

    def describe(self) -> str:
        worst = {
            name: ", ".join(f"{a} {v:.3g}" for a, v in zip(AXES, sigma)) for name, sigma in self.sigma.items()
        }
        return (
            f"{self.settings.conversion}, {self.rate_hz:g} Hz, "
            f"averaging {self.averaging} (low-pass off): an independent sample every "
            f"{1e3 / self.effective_hz:.3g} ms ({self.effective_hz:.3g} Hz); sigma at rest "
            + "; ".join(f"{n}: {w} (N, Nm)" for n, w in worst.items())
        )


def fastest_rate(bus: choice.Bus, scheduler: str | None, readback_every: int | None) -> float:
    """The fastest rate (Hz, to 0.1 Hz down) that an open option holds with
    `choice.TARGET_SPARE` of the period spare, at most `MAX_RATE_HZ`; with the register
    read-back where an option keeps it (as `choice.choose` prefers: it catches a chip that
    lost its settings), so accuracy never costs the check."""
    open_ = choice.options(bus, 1.0, scheduler, readback_every)
    bound = max(o.bound.rate_hz for o in [o for o in open_ if o.readback_every] or open_)
    return min(MAX_RATE_HZ, int(bound * (1.0 - choice.TARGET_SPARE) * 10) / 10)


def uncertainty_at(sensor: Sensor, settings: mlx.Settings) -> Uncertainty:
    """A sensor's `Uncertainty` with its chips at ``settings`` (as `SensorPipeline.build` makes it)."""
    s = sensor.config
    nl = s.calibration.nonlinear
    return Uncertainty(
        s.model,
        channel_sigma_t(settings, len(s.addresses)),
        s.calibration.report,
        None if nl is None else nl.estimator(),
        channel_lsb_t(settings, len(s.addresses)),
    )


def sigma_at(sensor: Sensor, uncertainty: Uncertainty, averaging: int, noise: bool = True) -> np.ndarray:
    """A sensor's sigma at rest (6, N and Nm) with ``uncertainty`` (`uncertainty_at`) and an
    averaging, as `status` predicts it; ``noise`` False: the part averaging cannot shrink (the
    tare's noise and the model error)."""
    factor = variance_factors(averaging, 1.0).steady if noise else 0.0
    # With the quantisation a load brings: at the tare's load it is not there, but no averaging
    # shrinks it under one (at the longest conversions it is most of the LSB's share).
    predicted = uncertainty.predicted(factor, sensor.tare_samples, sensor.estimator, loaded=True)["sigma"]
    return np.full(6, np.inf) if predicted is None else np.array(predicted)


def meets(sigma: np.ndarray, targets: list[Accuracy]) -> bool:
    return all(float(np.max(sigma[t.axes])) <= t.value for t in targets)


def plan(
    targets: dict[str, list[Accuracy]],
    sensors: list[Sensor],
    bus: choice.Bus,
    scheduler: str | None = None,
    readback_every: int | None = None,
    running: mlx.Settings | None = None,
) -> Plan:
    """The fastest `Plan` that meets each sensor's ``targets`` (by name; a sensor without
    any is not held to one) among the conversions ``bus.settings`` permits, on ``bus`` with
    the scheduler and read-back the configuration leaves open; at a tie, the ``running``
    conversion (the chips are not written for nothing).
    ConfigError saying the closest any setting comes, and why, when none meets them."""
    held = [s for s in sensors if targets.get(s.config.name)]
    if not held:
        raise ConfigError("accuracy: no target given")
    best: tuple[tuple[float, int, bool], Plan] | None = None
    closest: tuple[float, mlx.Settings, float, str] | None = None  # worst sigma / target, where, axis
    for candidate in choice.conversions(bus.settings):
        rate = fastest_rate(replace(bus, settings=candidate), scheduler, readback_every)
        if rate < 0.1:  # the daemon's slowest loop
            continue
        uncertainties = {s.config.name: uncertainty_at(s, candidate) for s in held}
        for averaging in AVERAGINGS:
            sigmas = {s.config.name: sigma_at(s, uncertainties[s.config.name], averaging) for s in held}
            ok = all(meets(sigmas[s.config.name], targets[s.config.name]) for s in held)
            if ok:
                found = Plan(
                    candidate,
                    rate,
                    averaging,
                    {n: [round(float(v), 7) for v in w] for n, w in sigmas.items()},
                )
                key = (found.effective_hz, -averaging, candidate == running)
                if best is None or key > best[0]:
                    best = (key, found)
                break
            # the target this setting misses most: how close the setting comes
            ratio, what = max(
                (float(np.max(sigmas[s.config.name][t.axes])) / t.value, f"{s.config.name}'s {t.kind}")
                for s in held
                for t in targets[s.config.name]
            )
            if closest is None or ratio < closest[0]:
                closest = (ratio, candidate, rate, what)
    if best is not None:
        return best[1]
    asked = ", ".join(f"{s.config.name} {' and '.join(t.text for t in targets[s.config.name])}" for s in held)
    near = (
        ""
        if closest is None
        else f"the closest, {closest[1].conversion} at {closest[2]:g} Hz "
        f"with averaging {MAX_AVERAGING}, leaves {closest[3]} sigma {closest[0]:.2g} times the target; "
    )
    raise ConfigError(f"accuracy: no setting meets {asked}: {near}{_why_not(held, targets, bus.settings)}")


def _why_not(held: list[Sensor], targets: dict[str, list[Accuracy]], settings: mlx.Settings) -> str:
    """Why no setting meets the targets, from what the calibration files hold: the part
    averaging cannot shrink (the model error at rest, the tare's noise, the undithered
    quantisation) when it stands at half a target or more, with the nonlinear estimator's own
    where a sensor runs the linear one, has it and it is lower; else the chips' noise, which
    `MAX_AVERAGING` readings do not bring under the target."""

    def floor(s: Sensor) -> np.ndarray:
        return sigma_at(s, uncertainty_at(s, settings), 1, noise=False)

    floors = {s.config.name: floor(s) for s in held}
    worst = {(n, t): float(np.max(floors[n][t.axes])) for n in floors for t in targets[n]}
    # Half the target: below it, the floor's share of the variance is under a quarter and the
    # chips' noise is what averaging leaves.
    if not any(v >= 0.5 * t.value for (_, t), v in worst.items()):
        return f"the chips' noise averaged {MAX_AVERAGING} times stays above it: a larger target"

    def listed(values: dict[tuple[str, Accuracy], float]) -> str:
        return "; ".join(f"{n} {t.kind} {v:.3g} {t.unit}" for (n, t), v in values.items())

    better = {}
    for s in held:
        if s.estimator == "linear" and s.config.calibration.nonlinear is not None:
            other = floor(replace(s, estimator="nonlinear"))
            for t in targets[s.config.name]:
                if float(np.max(other[t.axes])) < worst[(s.config.name, t)]:
                    better[(s.config.name, t)] = float(np.max(other[t.axes]))
    advice = (
        "with the nonlinear estimator (ftsensord set --estimator nonlinear) they are " + listed(better)
        if better
        else "a larger target"
    )
    return (
        f"the calibration's model error, the tare's noise and the chips' undithered quantisation "
        f"alone give {listed(worst)}, which averaging does not shrink; {advice}"
    )


def apply_accuracy(config: Config, timing: BusTiming | None = None) -> Plan | None:
    """With a sensor table's ``accuracy``: ``config``'s conversion (``[chip]`` OSR and
    DIG_FILT), rate, averaging and low-pass (off) set to the `plan` that meets every sensor's
    target untared (as at start), the scheduler and read-back chosen again for that rate;
    the plan, or None when no sensor asks. ConfigError naming the file when none meets them."""
    targets = {s.name: list(s.accuracy) for s in config.sensors if s.accuracy}
    if not targets:
        return None
    named = (
        config.scheduler if "scheduler" in config.named else None,
        config.readback_every if "readback_every" in config.named else None,
    )
    sensors = [Sensor(s, s.estimator) for s in config.sensors]
    try:
        found = plan(targets, sensors, config.bus_levers(timing), *named)
    except ConfigError as exc:
        raise ConfigError(f"{config.path}: sensor: {exc}") from exc
    config.settings, config.rate_hz, config.averaging, config.lowpass_hz = (
        found.settings,
        found.rate_hz,
        found.averaging,
        0.0,
    )
    config.choose(timing, f"{config.path}: accuracy", strict=False)
    return found
