"""Tare: averaging a sensor's no-load flux over a number of cycles and making it the zero.

A tare request waits while its samples come in, one a cycle, then is
answered through the reply function it was given (the control endpoint's).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import wire
from .pipeline import SensorPipeline

#: A tare gives up when its sensor has been invalid for this many times the samples asked.
TARE_PATIENCE = 10

Reply = Callable[[list[bytes], dict[str, Any]], None]


@dataclass
class TareJob:
    reply_to: list[bytes]
    sensors: list[str]
    samples: int
    flux: dict[str, list[np.ndarray]] = field(default_factory=dict)
    cycles: int = 0


class Tares:
    """The tares under way; ``reply(envelope, message)`` answers each when it is done."""

    def __init__(self, reply: Reply):
        self.reply = reply
        self.jobs: list[TareJob] = []

    def request(self, envelope: list[bytes], sensors: list[str], samples: int) -> None:
        self.jobs.append(TareJob(envelope, sensors, samples))

    def feed(self, sensor: str, flux: np.ndarray, flags: int) -> None:
        """Offer one cycle's flux (T) of ``sensor`` with its sample's flags."""
        if flags & (wire.FLAG_STALE | wire.FLAG_DEGRADED):
            return  # a zero needs every chip's fresh reading
        for job in self.jobs:
            if sensor in job.sensors and len(job.flux.setdefault(sensor, [])) < job.samples:
                job.flux[sensor].append(flux)

    def advance(self, pipelines: Sequence[SensorPipeline]) -> None:
        """After a cycle: finish the tares that have their samples, give up on the hopeless."""
        for job in list(self.jobs):
            job.cycles += 1
            if all(len(job.flux.get(n, [])) >= job.samples for n in job.sensors):
                offsets = {p.name: p.tare(np.mean(job.flux[p.name], axis=0)).round(6).tolist()
                           for p in pipelines if p.name in job.sensors}
                self.jobs.remove(job)
                self.reply(job.reply_to, {"ok": True, "result": {"tare_wrench": offsets, "samples": job.samples}})
            elif job.cycles > TARE_PATIENCE * job.samples:
                self.jobs.remove(job)
                self.reply(job.reply_to, {"ok": False, "error": f"tare gave up after {job.cycles} cycles: "
                                                                "the sensor had too few valid samples"})
