"""Faults against the truth: does any wrong wrench get through unflagged?

Each fault of the simulated bus, scripted in a scene, over a moving load on sensor1
(slow sinusoids on all six axes, up to half the calibration's largest load), through
the daemon on a virtual clock (100 Hz, overlapped scheduler, 400 kHz), raw and with
averaging and the low-pass. Every published wrench/sensor1 sample without a flag is
compared with the truth: the scene's load, passed through the same filter as the
stream (so the filter's own lag is not counted as an error). Sigma per axis is the
noise at rest of the unfiltered stream, measured first on the same rig (sensor2, at
rest, 1000 samples). Reported: samples, flagged, and unflagged samples more than
5 sigma from the truth (target 0), with the worst unflagged error in sigmas.

    python -m benchmarks.accuracy.faults_truth            # every fault, four filter settings
    python -m benchmarks.accuracy.faults_truth --seconds 4 --only stuck
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.common import SENSOR1, SENSOR2, WRONG_SIGMA, daemon_config, unflagged_error_sigma
from ftsensord.config.file import load_config
from ftsensord.processing.filters import WrenchFilter
from ftsensord.protocol import wire
from ftsensord.sim import load_scene
from ftsensord.sim.scene import default_scene_text
from ftsensord.testing.harness import InProcess

#: Amplitudes (N, Nm) and periods (s) of the moving load: about a twelfth of the calibration's
#: largest load per axis (sim-sensor1: 1.96 N, 1.93 N Fz, 0.14-0.18 Nm). K A's own error
#: grows with the load: on the default scene's as-built sensor in the room it reaches 1.9
#: sigma (Fy) noise-free at twice these amplitudes, an accuracy matter (docs/results/accuracy.md),
#: not a fault's; here it stays within 1 sigma, so what the faults add shows.
AMPLITUDE = np.array([0.175, 0.15, 0.15, 0.01, 0.014, 0.01])
PERIOD_S = np.array([4.0, 5.3, 3.1, 4.7, 6.1, 3.7])


@dataclass
class MovingLoad:
    """Slow sinusoids on every axis, phases apart: the stuck chip sees its field move."""

    scale: float = 1.0

    def wrench(self, t: float) -> np.ndarray:
        return self.scale * AMPLITUDE * np.sin(2 * np.pi * t / PERIOD_S + np.arange(6))


def fault(kind: str, at: float, until: float | None = None, **extra: object) -> str:
    lines = ["[[fault]]", f'kind = "{kind}"', f"at_s = {at}"] + ([f"until_s = {until}"] if until else [])
    return "\n" + "\n".join(lines + [f"{k} = {v}" for k, v in extra.items()]) + "\n"


#: name: (scene faults, tare at s or None, the load is still until this time (s)).
SCENARIOS: dict[str, tuple[str, float | None, float]] = {
    "none": ("", None, 0.0),
    "stuck": (fault("stuck", 1.0, 5.0, address=0x0F), None, 0.0),
    "stuck_early": (fault("stuck", 0.5, 4.5, address=0x0F), None, 0.0),  # where the load moves faster
    "gain_change": (fault("drift_register", 1.0, address=0x10, register=0, value=0x007C), None, 0.0),
    "nack_bursts": (
        fault("nack", 1.0, 1.3, address=0x0E)
        + fault("nack", 2.0, 2.1, address=0x0E)
        + fault("nack", 3.0, 3.6, address=0x0D),
        None,
        0.0,
    ),
    "chip_vanishes": (fault("detach", 1.0, 3.0, address=0x11), None, 0.0),
    "bus_errors": (fault("io_error", 1.0, 1.05) + fault("timeout", 2.5, 2.6), None, 0.0),
    "saturation": (fault("saturate", 1.0, 2.5, address=0x12, field_mt=70), None, 0.0),
    # A tare asked while a chip NACKs and another is stuck (the load held still, then moving).
    "tare_during_fault": (
        fault("nack", 0.5, 0.9, address=0x0E) + fault("stuck", 0.4, 5.0, address=0x0F),
        0.5,
        2.0,
    ),
}
FILTERS = {"raw": (1, 0.0), "avg10": (10, 0.0), "lp5Hz": (1, 5.0), "avg10+lp5Hz": (10, 5.0)}


class Rig(InProcess):
    """The default scene with ``faults``, sensor1 under the moving load (held still until
    ``still_until``), the daemon overlapped at 100 Hz with the filter asked."""

    def __init__(self, folder: Path, faults: str, averaging: int, lowpass_hz: float, still_until: float):
        # The default scene: the room and the part the packaged calibrations were fitted on.
        (folder / "scene.toml").write_text(default_scene_text() + faults)
        (folder / "ftsensord.toml").write_text(
            daemon_config(averaging=averaging, lowpass_hz=lowpass_hz)
            + f"""[[sensor]]
name = "sensor1"
addresses = [{SENSOR1}]
calibration = "builtin:sim-sensor1.json"
[[sensor]]
name = "sensor2"
addresses = [{SENSOR2}]
calibration = "builtin:sim-sensor2.json"
"""
        )
        moving = MovingLoad()
        self.still_until = still_until
        self.load = _Held(moving, still_until)
        scene = load_scene(folder / "scene.toml")
        scene.set_load("sensor1", self.load)  # type: ignore[union-attr]
        super().__init__(load_config(folder / "ftsensord.toml"), scene, subscribe=b"wrench/")

    def run(
        self, seconds: float, tare_at: float | None = None
    ) -> tuple[dict[str, list[wire.Sample]], dict | None]:
        out: dict[str, list[wire.Sample]] = {}
        reply = None
        asked = False
        for _ in range(int(seconds * 100)):
            if tare_at is not None and not asked and self.clock.now() >= tare_at:
                self.req.send(json.dumps({"cmd": "tare", "sensor": "sensor1", "samples": 30}).encode())
                asked = True
            deadline = self.clock.now() + self.daemon.period_s
            self.daemon.cycle()
            self.daemon.handle_control()
            self.clock.wait_until(deadline)
            while self.sub.poll(0):
                s = wire.decode(self.sub.recv())
                out.setdefault(s.topic, []).append(s)
            if asked and reply is None and self.req.poll(0):
                reply = json.loads(self.req.recv())
        return out, reply


@dataclass
class _Held:
    """The moving load, held at its value at ``until`` before then (a still sensor for a tare)."""

    moving: MovingLoad
    until: float

    def wrench(self, t: float) -> np.ndarray:
        return self.moving.wrench(max(t, self.until))


def noise_at_rest(folder: Path) -> np.ndarray:
    rig = Rig(folder, "", 1, 0.0, 0.0)
    out, _ = rig.run(10.0)
    rig.close()
    return np.std([s.values for s in out["wrench/sensor2"]], axis=0)


def truth(
    rig: Rig, samples: list[wire.Sample], averaging: int, lowpass_hz: float, tare_wrench: np.ndarray
) -> np.ndarray:
    """The scene's load at each sample, through the stream's filter (restarted where the stream's was)."""
    f = WrenchFilter(averaging, lowpass_hz, 100.0)
    out = []
    for s in samples:
        # The chips convert through the cycle; the sample is stamped after its reads: 4 ms is mid-cycle.
        w = rig.load.wrench(s.t_mono - 0.004) - tare_wrench
        if s.flags & wire.FLAG_INVALID:
            f.reset()
            out.append(np.full(6, np.nan))
        else:
            out.append(f.update(w)[0])
    return np.array(out)


def measure(folder: Path, name: str, filt: str, sigma: np.ndarray, seconds: float) -> dict:
    faults, tare_at, still = SCENARIOS[name]
    averaging, lowpass = FILTERS[filt]
    rig = Rig(folder, faults, averaging, lowpass, still)
    out, reply = rig.run(seconds, tare_at)
    w = out["wrench/sensor1"]
    tare_wrench = rig.daemon.sensors[0].tare_wrench
    tared_from = next((s.seq for s in w if reply and s.t_mono >= tare_at), None) if tare_at else None
    rig.close()
    values = np.array([s.values for s in w])
    flags = np.array([s.flags & ~wire.FLAG_LATE for s in w])  # late: timing, not value
    t = truth(rig, w, averaging, lowpass, tare_wrench)
    if tare_at is not None and reply and reply.get("ok"):
        done = next(i for i, s in enumerate(w) if s.t_mono >= tare_at + 0.35)  # after the tare's 30 samples
        clean = np.zeros(len(w), dtype=bool)
        clean[done:] = flags[done:] == 0
    else:
        clean = flags == 0
    worst = unflagged_error_sigma(values, t, sigma, clean)
    return {
        "scenario": name,
        "filter": filt,
        "samples": len(w),
        "flagged": int(np.sum(flags != 0)),
        "inconsistent": int(np.sum(flags & wire.FLAG_INCONSISTENT != 0)),
        "unflagged_over_5sigma": int(np.sum(worst > WRONG_SIGMA)),
        "worst_unflagged_sigma": float(np.max(worst)),
        "tare": None if tare_at is None else (reply or {}).get("ok", reply),
        "tared_seq": tared_from,
        "tare_error": (reply or {}).get("error"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--only", help="one scenario")
    args = ap.parse_args()
    logging.disable(logging.WARNING)  # the daemon logs every fault it meets: hundreds of lines here
    with tempfile.TemporaryDirectory() as tmp:
        sigma = noise_at_rest(Path(tmp))
        print("sigma at rest (wrench/sensor2, 1000 samples):", " ".join(f"{v:.4g}" for v in sigma))
        print(
            f"{'scenario':18} {'filter':12} {'samples':>7} {'flagged':>7} {'incons':>6} {'>5sig':>5} {'worst':>6}"
        )
        total = 0
        for name in [args.only] if args.only else SCENARIOS:
            for filt in FILTERS:
                r = measure(Path(tmp), name, filt, sigma, args.seconds)
                total += r["unflagged_over_5sigma"]
                print(
                    f"{name:18} {filt:12} {r['samples']:7d} {r['flagged']:7d} {r['inconsistent']:6d} "
                    f"{r['unflagged_over_5sigma']:5d} {r['worst_unflagged_sigma']:6.2f}"
                    + (f"  tare ok={r['tare']}" if r["tare"] is not None else ""),
                    flush=True,
                )
                if r["tare_error"] and filt == "raw":
                    print("    tare reply:", r["tare_error"])
        print("unflagged samples > 5 sigma, all runs:", total)


if __name__ == "__main__":
    main()
