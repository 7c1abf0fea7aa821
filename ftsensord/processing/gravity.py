"""Gravity compensation: the tool's weight taken out of a wrench, as the tool turns.

A sensor's wrench holds its offset (what the calibration's zero misses), the
weight of what hangs on it, and the load. Tare removes the offset, compensation
the weight. For a frame with a payload (mass m at c, `frames.Payload`) and
gravity g_f (m/s^2) seen in that frame, the weight is W(g) = [m g; c x m g]; the
published compensated wrench is

    w_comp = w + W(g_tare) - W(g_now)

where w is the (tared) raw wrench and g_tare the mean gravity over the tare's
samples (zero when not tared): a tare at any orientation zeroed the offset *and*
the weight as it then was, so the weight at the tare is given back and the
weight now taken off. g_now = R_world,f^T g_world, R from a fixed mount or the
orientation stream (`protocol.orientation`). The tip's tare gravity follows from
the tool's sensors' (one rigid tool: R_tip,s g_s agree when they were tared at
one orientation); otherwise it is unknown and the tip's compensated wrench is
NaN, flagged invalid, until they are tared together (or all untared).

The weight goes through a filter like the raw wrench's (averaging, low-pass), so
both lag alike as the tool turns.

Each compensated sample carries a 1-sigma per axis (`Compensated.sigma`, N and Nm): the
raw sample's and the compensation's, independent, added in variance (`weight_variance`
for the orientations' part). The payloads are configured values, taken as exact; the
orientations are as exact as `GravityConfig.orientation_sigma_rad` says.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from ftsensord.config.frames import TIP, GravityConfig, Payload
from ftsensord.model import se3
from ftsensord.processing.filters import WrenchFilter
from ftsensord.processing.pipeline import SensorPipeline, SensorSample
from ftsensord.protocol import wire
from ftsensord.protocol.orientation import OrientationReceiver

#: The tool's sensors' tare gravities (rotated into the tip frame) are one orientation's
#: when they agree within this fraction of |g|: 1e-3 rad, which moves a 50 g tool's
#: weight by 0.5 mN (a fiftieth of the noise); tares at different orientations differ
#: by far more (a hand holding a tool still wanders by degrees between two tares).
TARE_AGREE = 1e-3
NAN6 = np.full(6, np.nan)
NAN6.setflags(write=False)


class Compensated(NamedTuple):
    """One compensated stream's sample of a cycle."""

    topic: str  # wrench/<frame>/compensated
    flags: int
    wrench: np.ndarray  # N, Nm, in the frame; NaN invalid
    sigma: np.ndarray  # its 1-sigma per axis (N, Nm); NaN unknown


def weight_variance(payload: Payload, g: np.ndarray, sigma_rad: float | np.ndarray) -> np.ndarray:
    """The variance per axis (6; N^2, Nm^2) of the weight W(g) (`Payload.wrench`) when g
    (m/s^2, in the frame) comes from an orientation off by a small rotation d (rad, about the
    frame's axes, each of 1-sigma ``sigma_rad``, independent). Several independent ones at
    once, summed: ``g`` n x 3 and ``sigma_rad`` n.

    The frame's gravity is R^T g_world; with R = R_true Exp(d) it is Exp(-d) g = g + g x d
    to first order, so its error g x d = [g]x d has covariance sigma^2 [g]x [g]x^T (nothing
    along g: a turn about the vertical leaves the weight as it is; an error d about the world's
    axes instead, R = Exp(d) R_true, has the same covariance, d's being isotropic). W is linear
    in g, so W's covariance is sigma^2 J [g]x [g]x^T J^T, J = dW/dg; its column k is
    W(sigma g x e_k)."""
    # [g]x's columns g x e_k are minus its rows (skew), a sign the squares drop: hat builds
    # them for less than np.cross against the identity, and this runs each cycle on each frame.
    turned = se3.hat(np.reshape(g, (-1, 3))) * np.reshape(sigma_rad, (-1, 1, 1))  # rows: -sigma g x e_k
    return np.sum(np.square(payload.wrench(turned.reshape(-1, 3))), axis=0)


class Gravity:
    """The compensated streams of one configuration; orientations from ``receiver``
    (source "stream") or the configured mounts."""

    def __init__(
        self,
        config: GravityConfig,
        poses: dict[str, np.ndarray],
        receiver: OrientationReceiver,
        averaging: int = 1,
        lowpass_hz: float = 0.0,
        rate_hz: float = 100.0,
    ):
        self.config, self.poses, self.receiver = config, poses, receiver
        self.tool = {*poses, TIP} if poses else set()
        self.filters = {frame: WrenchFilter(averaging, lowpass_hz, rate_hz) for frame in config.payloads}

    def configure(self, averaging: int, lowpass_hz: float, rate_hz: float) -> None:
        for f in self.filters.values():
            f.configure(averaging, lowpass_hz, rate_hz)

    def restart(self) -> None:
        """Forget the weights' past (a gap in the input: `Daemon.cycle`)."""
        for f in self.filters.values():
            f.reset()

    def _R_tip(self, frame: str) -> np.ndarray:
        return np.eye(3) if frame == TIP else self.poses[frame][:3, :3]

    def orientation(self, frame: str, now: float) -> tuple[np.ndarray | None, bool]:
        """R_world,frame (None: unknown) and whether it is stale: its newest source is older
        than ``stale_after_s``. Sources: the frame's own mount or message, or any other frame
        of the tool's (R_w,b = R_w,a R_tip,a^T R_tip,b: the tool is rigid); the newest wins."""
        sources: dict[str, tuple[np.ndarray, float]] = {f: (R, np.inf) for f, R in self.config.mounts.items()}
        if self.config.source == "stream":
            sources = {f: (r.R, r.t_arrival) for f, r in self.receiver.latest.items()}
        best: tuple[np.ndarray, float] | None = sources.get(frame)
        if frame in self.tool:
            for a in self.tool & sources.keys():
                R, t = sources[a]
                if best is None or t > best[1]:
                    best = (R @ self._R_tip(a).T @ self._R_tip(frame), t)
        if best is None:
            return None, True
        return best[0], now - best[1] > self.config.stale_after_s

    def gravity(self, frame: str, now: float) -> tuple[np.ndarray | None, int]:
        """Gravity (m/s^2) seen in ``frame`` (None: unknown), flagged orientation_stale when stale."""
        R, stale = self.orientation(frame, now)
        return (
            None if R is None else R.T @ self.config.gravity_mps2
        ), wire.FLAG_ORIENTATION_STALE if stale else 0

    def needs(self, sensor: str) -> bool:
        """Whether a compensated stream depends on ``sensor``'s orientation at its tare."""
        return sensor in self.config.payloads or (sensor in self.poses and TIP in self.config.payloads)

    def tare_input(self, sensor: str, now: float) -> tuple[int, np.ndarray | None]:
        """What a tare of ``sensor`` records this cycle: flags that turn the sample away (a
        stale orientation where one is needed) and the gravity (None: unknown)."""
        g, flags = self.gravity(sensor, now)
        if flags and not self.needs(sensor):
            return 0, None
        return flags, g

    def tip_tare(self, pipelines: Sequence[SensorPipeline]) -> tuple[np.ndarray | None, int | None]:
        """The tip's gravity at the tool's sensors' tares (m/s^2, tip frame), None unless they
        agree, and how many samples the one it is taken from averaged (`compensate`'s ``tare``)."""
        tool = [p for p in pipelines if p.name in self.poses]
        gs = [
            p.tare_gravity if p.tare_gravity is None else self._R_tip(p.name) @ p.tare_gravity for p in tool
        ]
        if not gs or any(g is None for g in gs):
            return None, None
        limit = TARE_AGREE * float(np.linalg.norm(self.config.gravity_mps2))
        agree = all(np.max(np.abs(g - gs[0])) <= limit for g in gs)  # type: ignore[operator]
        return (gs[0], tool[0].tare_samples) if agree else (None, None)

    def compensate(
        self,
        frame: str,
        raw: np.ndarray,
        flags: int,
        sigma: np.ndarray,
        tare: tuple[np.ndarray | None, int | None],
        now: float,
    ) -> tuple[np.ndarray, int, np.ndarray]:
        """``frame``'s compensated wrench (N, Nm), flags and 1-sigma per axis (N, Nm; NaN
        unknown) from its raw (tared) one and that one's sigma. ``tare``: the gravity
        (m/s^2, frame) over the tare's samples (None: unknown) and how many samples it
        averaged (None: unknown or untared, and the tare's orientation noise is left out, as
        the raw sigma leaves out the tare's own noise then).

        The variance per axis: the raw one, the weight's now (`weight_variance` times the
        weight filter's variance factor: each cycle's orientation taken as a fresh,
        independent draw, and the filter's inputs as of one variance, the tool turning
        little within its window) and the tare's (the mean of n draws: 1 / n of it). An
        orientation sender slower than the loop repeats its draws: the filter then shrinks
        their noise less than the factor says."""
        payload, weights = self.config.payloads[frame], self.filters[frame]
        g_tare, n_tare = tare
        g, stale = self.gravity(frame, now)
        if g is None or g_tare is None or not np.all(np.isfinite(raw)):
            weights.reset()  # no weight to follow: start again with the next one
            return NAN6, flags | stale | wire.FLAG_INVALID, NAN6
        weight, wflags = weights.update(payload.wrench(g), stale)
        values, flags = raw + payload.wrench(g_tare) - weight, flags | wflags
        s = self.config.orientation_sigma_rad
        if s == 0.0:  # exact orientations (a mount's): the raw sample's sigma alone
            return values, flags, sigma
        # The weight now (through its filter) and at the tare, independent: one call for both.
        gs, scales = [g], [s * np.sqrt(weights.variance_factor())]
        if n_tare:
            gs.append(g_tare)
            scales.append(s / np.sqrt(n_tare))
        return (
            values,
            flags,
            np.sqrt(np.square(sigma) + weight_variance(payload, np.array(gs), np.array(scales))),
        )

    def streams(
        self,
        samples: dict[str, SensorSample],
        tip: tuple[np.ndarray, int] | None,
        tip_sigma: np.ndarray | None,
        pipelines: Sequence[SensorPipeline],
        now: float,
    ) -> list[Compensated]:
        """This cycle's compensated streams, from the raw samples, the tip's wrench and flags
        and its sigma (N, Nm; NaN or None unknown)."""
        out = []
        for p in pipelines:
            if p.name in self.config.payloads:
                s = samples[p.name]
                tare = (p.tare_gravity, p.tare_samples)
                values, flags, sigma = self.compensate(p.name, s.wrench, s.flags, s.sigma.sigma, tare, now)
                out.append(Compensated(f"wrench/{p.name}/compensated", flags, values, sigma))
        if tip is not None and TIP in self.config.payloads:
            raw_sigma = NAN6 if tip_sigma is None else tip_sigma
            values, flags, sigma = self.compensate(
                TIP, tip[0], tip[1], raw_sigma, self.tip_tare(pipelines), now
            )
            out.append(Compensated("wrench/tip/compensated", flags, values, sigma))
        return out

    def status(self, pipelines: Sequence[SensorPipeline], now: float) -> dict[str, Any]:
        """The `status` reply's ``gravity``: source, payloads, orientations' ages, drops."""
        tares = {p.name: p.tare_gravity for p in pipelines}
        if TIP in self.config.payloads:
            tares[TIP] = self.tip_tare(pipelines)[0]
        frames = {}
        for f, payload in self.config.payloads.items():
            R, stale = self.orientation(f, now)
            g_tare = tares[f]
            # Gravity in the frame now (what the compensation takes off, beside the tare's),
            # so a mis-sent orientation shows at once, not only as a wrong wrench.
            g_now = None if R is None else R.T @ self.config.gravity_mps2
            frames[f] = {
                "mass_kg": payload.mass_kg,
                "com_m": payload.com_m.tolist(),
                "orientation_known": R is not None,
                "orientation_stale": stale,
                "gravity_now_mps2": None if g_now is None else np.round(g_now, 6).tolist(),
                "tare_gravity_mps2": None if g_tare is None else np.round(g_tare, 6).tolist(),
            }
        return {
            "orientation": self.config.source,
            "endpoint": self.config.endpoint,
            "stale_after_s": self.config.stale_after_s,
            "gravity_mps2": self.config.gravity_mps2.tolist(),
            "orientation_sigma_deg": float(np.degrees(self.config.orientation_sigma_rad)),
            "frames": frames,
            "stream": self.receiver.status(now),
        }
