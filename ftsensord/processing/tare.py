"""Tare: averaging a sensor's no-load flux over a number of cycles and making it the zero.

A tare request waits while its samples come in, one a cycle, then is
answered through the reply function it was given (the control endpoint's).
A tare takes only samples without any flag (a flagged sample may hold a
stuck, missing or disagreeing chip, or a load beyond the calibration's), and
only a steady load: when the two halves of its samples differ beyond their
noise the load moved (or drifted) and the tare is refused, saying why. One
tare per sensor at a time; a tare survives a reload that keeps the sensor's
calibration, and `untare` goes back to the calibration's own zero.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ftsensord.processing.pipeline import SensorPipeline
from ftsensord.protocol import wire

log = logging.getLogger("ftsensord")

#: A tare gives up when its sensor has been invalid for this many times the samples asked.
TARE_PATIENCE = 10
#: ...and sooner, after this many samples in a row turned away for a stale orientation
#: (1 s at 100 Hz): an application that sends orientations sends them every servo tick,
#: so a second without one means it stopped, and waiting TARE_PATIENCE x samples (10 s
#: for 100) would tell the user nothing more.
TARE_STALE_RUN = 100
#: The halves of a tare's samples may differ by this many standard deviations of their
#: difference (per axis, from the chips' noise): under noise alone a tare is refused
#: with odds of 2e-9 per axis; a load that moves or drifts by more is refused.
TARE_STEADY_SIGMAS = 6.0

Reply = Callable[[list[bytes], dict[str, Any]], None]
AXES = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")


@dataclass
class TareJob:
    reply_to: list[bytes]
    sensors: list[str]
    samples: int
    flux: dict[str, list[np.ndarray]] = field(default_factory=dict)
    gravity: dict[str, list[np.ndarray | None]] = field(default_factory=dict)  # m/s^2, sensor frame
    seen: dict[str, Counter[str]] = field(default_factory=dict)  # flags of the samples turned away
    turned_away: dict[str, int] = field(default_factory=dict)  # how many, by sensor
    stale_run: dict[str, int] = field(default_factory=dict)  # stale orientations in a row, by sensor
    cycles: int = 0


class Tares:
    """The tares under way; ``reply(envelope, message)`` answers each when it is done."""

    def __init__(self, reply: Reply):
        self.reply = reply
        self.jobs: list[TareJob] = []

    def busy(self, sensors: Sequence[str]) -> list[str]:
        """Those of ``sensors`` with a tare under way."""
        return [n for n in sensors if any(n in job.sensors for job in self.jobs)]

    def request(self, envelope: list[bytes], sensors: list[str], samples: int) -> None:
        """Start a tare of ``sensors``; ValueError if one of them has a tare under way."""
        busy = self.busy(sensors)
        if busy:
            raise ValueError(f"a tare of {', '.join(busy)} is under way: wait for its reply")
        self.jobs.append(TareJob(envelope, sensors, samples))

    def untare(self, pipelines: Sequence[SensorPipeline]) -> dict[str, list[float]]:
        """Back to the calibrations' own zeros; ValueError if one has a tare under way.
        Returns, by sensor, the wrench (N, Nm) each tare had removed."""
        busy = self.busy([p.name for p in pipelines])
        if busy:
            raise ValueError(f"a tare of {', '.join(busy)} is under way: wait for its reply, then untare")
        removed = {p.name: untare(p) for p in pipelines}
        log.info("untared %s", ", ".join(removed))
        return removed

    def feed(self, sensor: str, flux: np.ndarray, flags: int, gravity: np.ndarray | None = None) -> None:
        """Offer one cycle's flux (T) of ``sensor`` with its sample's flags (those of its
        published wrench: a filtered wrench's include what its filter still holds) and
        gravity (m/s^2, sensor frame; None: unknown) at that sample."""
        for job in self.jobs:
            if sensor not in job.sensors:
                continue
            stale = bool(flags & wire.FLAG_ORIENTATION_STALE)
            job.stale_run[sensor] = job.stale_run.get(sensor, 0) + 1 if stale else 0
            if flags:  # a zero needs every chip fresh, agreeing and within the calibration
                job.seen.setdefault(sensor, Counter()).update(wire.flag_names(flags))
                job.turned_away[sensor] = job.turned_away.get(sensor, 0) + 1
            elif len(job.flux.setdefault(sensor, [])) < job.samples:
                job.flux[sensor].append(flux)
                job.gravity.setdefault(sensor, []).append(gravity)

    def advance(self, pipelines: Sequence[SensorPipeline]) -> None:
        """After a cycle: finish the tares that have their samples, give up on the hopeless."""
        if not self.jobs:
            return
        by_name = {p.name: p for p in pipelines}
        for job in list(self.jobs):
            job.cycles += 1
            if all(len(job.flux.get(n, [])) >= job.samples for n in job.sensors):
                self.jobs.remove(job)
                moved = [
                    m
                    for n in job.sensors
                    if n in by_name
                    for m in [unsteady(by_name[n], np.array(job.flux[n]))]
                    if m
                ]
                if moved:
                    self.reply(
                        job.reply_to,
                        {"ok": False, "error": "tare refused, nothing changed: " + "; ".join(moved)},
                    )
                    continue
                offsets = {
                    n: tare_on(by_name[n], job.flux[n], _mean(job.gravity[n])).round(6).tolist()
                    for n in job.sensors
                    if n in by_name
                }
                self.reply(
                    job.reply_to, {"ok": True, "result": {"tare_wrench": offsets, "samples": job.samples}}
                )
            elif job.cycles > TARE_PATIENCE * job.samples:
                self.jobs.remove(job)
                self.reply(
                    job.reply_to,
                    {
                        "ok": False,
                        "error": f"tare refused after {job.cycles} cycles, "
                        "nothing changed: " + _shortfall(job),
                    },
                )
            elif names := [n for n in job.sensors if job.stale_run.get(n, 0) >= TARE_STALE_RUN]:
                self.jobs.remove(job)
                self.reply(
                    job.reply_to,
                    {
                        "ok": False,
                        "error": (
                            f"tare refused after {job.cycles} cycles, nothing changed: no fresh orientation for "
                            f"{', '.join(names)} in the last {TARE_STALE_RUN} samples (orientation_stale). With "
                            "gravity compensation a tare keeps the tool's orientation at each sample: the "
                            "application must keep sending orientations during it (`ftsensord status`: "
                            "gravity.stream.frames shows the last one's age)"
                        ),
                    },
                )


def tare_on(p: SensorPipeline, flux: Sequence[np.ndarray], gravity: np.ndarray | None = None) -> np.ndarray:
    """Tare ``p`` on its no-load samples' ``flux`` (T, each the stacked channels) and their mean
    ``gravity``: their mean the zero, their count and each channel's variance for the sigma
    (`SensorPipeline.tare`). Returns the wrench the tare removes."""
    samples = np.asarray(flux, dtype=float)
    spread = samples.var(axis=0, ddof=1) if len(samples) > 1 else None
    return p.tare(samples.mean(axis=0), gravity, len(samples), spread)


def _mean(gravity: list[np.ndarray | None]) -> np.ndarray | None:
    """The mean gravity over a tare's samples (the weight is linear in it), None if one was unknown."""
    known = [g for g in gravity if g is not None]
    return np.mean(known, axis=0) if len(known) == len(gravity) else None


def _shortfall(job: TareJob) -> str:
    """Which sensors lacked clean samples, and the flags that turned theirs away."""
    parts = []
    for n in job.sensors:
        got = len(job.flux.get(n, []))
        if got >= job.samples:
            continue
        seen = job.seen.get(n, Counter())
        flags = ", ".join(f"{name} in {count}" for name, count in seen.most_common()) or "none"
        parts.append(
            f"{n} had {got} of {job.samples} samples without a flag (flags seen: {flags}; "
            f"{max(0, job.cycles - got - job.turned_away.get(n, 0))} cycles without an estimate)"
        )
    return "; ".join(parts) + "; a tare takes only samples without any flag"


def unsteady(p: SensorPipeline, flux: np.ndarray) -> str | None:
    """Why ``flux`` (samples x channels, T) is no zero (the load moved), or None."""
    if len(flux) < 2 or p.sigma_t is None:
        return None  # one sample: nothing to compare
    half = len(flux) // 2
    w = p.config.model.wrench(flux)
    diff = w[half:].mean(axis=0) - w[:half].mean(axis=0)
    KA = p.config.model.KA
    sigma_w = np.sqrt(np.einsum("ij,j,ij->i", KA, p.sigma_t**2, KA))  # one sample's noise per axis
    limit = TARE_STEADY_SIGMAS * sigma_w * math.sqrt(1 / half + 1 / (len(flux) - half))
    worst = int(np.argmax(np.abs(diff) / limit))
    if abs(diff[worst]) <= limit[worst]:
        return None
    return (
        f"{p.name}'s load moved during the tare ({AXES[worst]} changed by {diff[worst]:+.4g} between "
        f"its halves, noise allows {limit[worst]:.2g}): hold it still and tare again"
    )


def untare(p: SensorPipeline) -> list[float]:
    """Back to the calibration's own zero; returns the wrench (N, Nm) the tare had removed."""
    removed = p.tare_wrench.round(6).tolist()
    p.untare()
    return removed


def carry_tares(
    old: Sequence[SensorPipeline], new: Sequence[SensorPipeline], after: str = "reload"
) -> dict[str, str]:
    """After a reload (or what ``after`` names, for the log): each tared sensor keeps its tare
    if its calibration is unchanged, else drops it (a zero measured through one calibration
    is no zero for another fitted on other data). Logs and returns what happened, by sensor,
    for the reply."""
    before = {p.name: p for p in old}
    out = {}
    for p in new:
        o = before.get(p.name)
        if o is None or not o.tared:
            continue
        if o.config.calibration.document() == p.config.calibration.document():
            # The samples' spread is the chips' at their settings: another conversion, unknown.
            same = o.sigma_t is not None and p.sigma_t is not None and np.array_equal(o.sigma_t, p.sigma_t)
            p.tare(o.model.zero, o.tare_gravity, o.tare_samples, o.tare_spread if same else None)
            if o.stray is not None and p.stray is not None:
                p.stray = o.stray  # what it learnt, and the gradient at that tare, hold still
            out[p.name] = "kept (calibration unchanged)"
            log.info("%s: %s's tare %s", after, p.name, out[p.name])
        else:
            out[p.name] = "dropped: its calibration changed; tare it again"
            log.warning("%s: %s's tare %s", after, p.name, out[p.name])
    return out
