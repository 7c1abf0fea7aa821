"""What several benchmarks share: the repository's folders, the host's description, a
stand-in bus and publisher, the default scene's parts and daemon configurations, and the
figures that judge a wrench against its noise.

A benchmark imports it as ``from benchmarks.common import ...`` and runs from the
repository's root as ``python -m benchmarks.<folder>.<name>``.
"""

from __future__ import annotations

import ctypes
import importlib.util
import os
import platform
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from ftsensord.chip import mlx90393 as mlx
from ftsensord.config.file import Config
from ftsensord.docfile import load_toml
from ftsensord.model import se3
from ftsensord.protocol import wire
from ftsensord.sim import NoiseModel, default_scene
from ftsensord.sim.chip import FieldSource
from ftsensord.sim.loads import fibonacci_directions
from ftsensord.sim.scene import default_scene_path

#: The repository's root, its docs/ and the folder of the pages the benchmarks generate.
ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
RESULTS = DOCS / "results"


# --- the host --------------------------------------------------------------------------


def machine() -> str:
    """The host in a few words: cores, architecture and Python."""
    return f"{os.cpu_count()}-core {platform.machine()}, Python {platform.python_version()}"


def pin_to_core(cpu: int | None) -> int:
    """This process pinned to core ``cpu`` (None: the last one it may use), so that it does
    not migrate between cores while it is measured; the core."""
    core = cpu if cpu is not None else max(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {core})
    return core


def load_c_build() -> ModuleType:
    """clients/c/build.py as a module: how the C clients find libzmq and are compiled."""
    spec = importlib.util.spec_from_file_location("ftsensord_c_build", ROOT / "clients" / "c" / "build.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


# --- stand-ins for the bus and the publisher -------------------------------------------

#: Readings a chip cycles through: at the default settings' noise (a third of the words'
#: 6 uT LSB) the same words come back often, never for as many cycles as the stuck test needs.
READINGS = 64


class InstantBus:
    """Answers like healthy chips at once: RM from `READINGS` precomputed readings a chip,
    in turn (the default scene's flux at rest with the emulated chip's noise, quantised as
    the chip does: healthy readings, so the redundancy check passes as it does on a sensor
    at rest and no chip looks stuck), RR from the configured registers, the real chip's
    status bytes otherwise."""

    def __init__(self, config: Config):
        settings = config.settings
        self.regs = settings.to_registers()
        scene = default_scene()  # the room and part the packaged calibrations were fitted on
        rng = np.random.default_rng(0)
        noise = NoiseModel()
        self.replies: dict[tuple[int, int], list[bytes]] = {}
        for a in config.addresses:
            truth_ut = scene.field_t(a, 0.0) * 1e6
            data = [
                b"".join(
                    mlx.counts_to_raw(
                        round(
                            (b + rng.normal(0.0, noise.sigma_ut(ax, settings.tconvm_us())))
                            / settings.sensitivity_ut(ax)
                        ),
                        settings.raw_format(ax),
                    ).to_bytes(2, "big")
                    for b, ax in zip(truth_ut, "xyz")
                )
                for _ in range(READINGS)
            ]
            self.replies[(a, 7)] = [bytes([0x02]) + d for d in data]
            self.replies[(a, 9)] = [bytes([0x03]) + (46244).to_bytes(2, "big") + d for d in data]
        self.turn = dict.fromkeys(config.addresses, 0)

    def i2c_rdwr(self, *msgs: Any) -> None:
        # As cheap as Python allows (the first bytes only, no copies): the bus is not measured.
        write, address = None, 0
        for m in msgs:
            if m.flags & 1:
                reply = self._reply(address, write, m.len)
                ctypes.memmove(m.buf, reply, m.len)
            else:
                write, address = m, m.addr

    def _reply(self, address: int, write: Any, n: int) -> bytes:
        op = write.buf[0][0] & 0xF0
        if op == mlx.CMD_RM:
            k = self.turn[address] = (self.turn[address] + 1) % READINGS
            return self.replies[(address, n)][k]
        if op == mlx.CMD_RR:
            reg = write.buf[1][0] >> 2
            value = self.regs.get(reg, mlx.TREF_TYPICAL if reg == mlx.REG_TREF else 0)
            return b"\x00" + value.to_bytes(2, "big")
        # The real chip's D1:D0 in replies without data (docs/design/simulator.md).
        return {mlx.CMD_RT: b"\x05", mlx.CMD_SM: b"\x21", mlx.CMD_SB: b"\x81"}.get(op, b"\x01")

    def sleep(self, s: float) -> None:
        pass

    def monotonic(self) -> float:
        return time.monotonic()

    def close(self) -> None:
        pass


class Capture:
    """Stands in for the publisher socket: keeps each topic's last sample."""

    def __init__(self) -> None:
        self.last: dict[str, wire.Sample] = {}

    def send(self, frame: bytes, flags: int = 0) -> None:
        sample = wire.decode(frame)
        self.last[sample.topic] = sample


# --- the default scene's parts and daemon configurations -------------------------------

#: The default scene (ftsensord/data/scene-default.toml) as its TOML tables.
SCENE = load_toml(default_scene_path())
#: The default scene's sensors' addresses, as a configuration file lists them.
SENSOR1 = "0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x11, 0x12, 0x13"
SENSOR2 = "0x14, 0x15, 0x16, 0x17, 0x18, 0x19, 0x1A, 0x1B"

#: The chip settings (OSR, DIG_FILT) of the speed-accuracy trade (docs/results/tradeoff.md):
#: DIG_FILT 0 to 7.
FULL_CHIP = [(0, 2), (1, 2), (1, 3), (2, 0), (2, 1), (2, 2), (2, 4), (3, 4), (3, 6), (3, 7)]

#: Quick runs of a benchmark that calibrates parts by the documented commands (CI, through
#: ``python -m benchmarks regenerate --quick``): `ftsensord dataset`'s options for a small
#: dataset, whose fit is kept whatever it gives: the page's structure, not its figures.
QUICK_DATASET = [
    "--poses",
    "60",
    "--validation-poses",
    "15",
    "--samples",
    "20",
    "--check-poses",
    "3",
    "--hold-s",
    "0",
]

#: The paper's Table II: RMSE per axis (N, Nm) at its 100 g validation loads.
PAPER = np.array([0.2338, 0.1136, 0.3775, 4.1e-3, 10.6e-3, 8.5e-3])

#: 48 orientations: the shaft along Fibonacci directions, turned about itself.
SWEEP = [
    se3.exp_so3(
        np.cross([0, 0, 1.0], d)
        / max(np.linalg.norm(np.cross([0, 0, 1.0], d)), 1e-12)
        * np.arccos(np.clip(d[2], -1, 1))
    )
    @ se3.exp_so3(np.array([0, 0, 2.4 * k]))
    for k, d in enumerate(fibonacci_directions(48))
]


def part_table(seed: int) -> str:
    """The default scene's room, and its sensor1's tolerances with ``seed``: one part."""
    tol = dict(SCENE["sensor"][0]["tolerances"], seed=seed)
    return (
        f'version = 1\nkind = "sensors"\nexternal_field_ut = {SCENE["external_field_ut"]}\n'
        f'[[sensor]]\nname = "sensor1"\naddresses = [{SENSOR1}]\n[sensor.tolerances]\n'
        + "".join(f"{k} = {v}\n" for k, v in tol.items())
    )


def tilted(axis: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Each magnet glued 2-7 deg off its pocket's axis, about a random direction across it."""
    out = []
    for a in axis:
        across = np.cross(a, rng.normal(size=3))
        out.append(se3.exp_so3(across / np.linalg.norm(across) * np.radians(rng.uniform(2, 7))) @ a)
    return np.array(out)


def daemon_config(**keys: object) -> str:
    """The head of a configuration file for the simulated bus of ``scene.toml`` beside it,
    at 100 Hz with the overlapped scheduler, and ``keys`` (TOML values as Python writes
    them); the caller adds its ``[[sensor]]`` tables."""
    return 'version = 1\nbus = "sim:scene.toml"\nrate_hz = 100\nscheduler = "overlapped"\n' + "".join(
        f"{k} = {v}\n" for k, v in keys.items()
    )


# --- a wrench against its noise --------------------------------------------------------

#: An unflagged sample further than this from the truth on any axis, in sigmas of one
#: sample's noise, is a wrong wrench (under Gaussian noise alone 5.7e-7 per axis-sample).
WRONG_SIGMA = 5.0


def unflagged_error_sigma(
    values: np.ndarray, truth: np.ndarray, sigma: np.ndarray, clean: np.ndarray
) -> np.ndarray:
    """Each sample's largest error over the axes, in ``sigma`` (one sample's noise per axis):
    ``values`` and ``truth`` (n, 6) in N, Nm; 0 where ``clean`` (n,) is false (a flagged
    sample is not judged), infinite for an unflagged NaN (a wrench that is not there)."""
    err = np.nan_to_num(np.abs(values - truth) / sigma, nan=np.inf)
    return np.max(np.where(clean[:, None], err, 0.0), axis=1, initial=0.0)


CHUNK = 200_000  # samples drawn at once: 200,000 x 24 doubles, 38 MB


def wrench_noise(
    config: Config, scene: FieldSource, samples: int, settings: mlx.Settings | None = None, seed: int = 0
) -> dict[str, np.ndarray]:
    """Per wrench stream (``wrench/<sensor>``, ``wrench/tip`` when the tool has poses), the
    deviation of ``samples`` simulated wrenches from their mean (samples, 6; N, Nm)."""
    settings = settings or config.settings
    noise = NoiseModel()
    rng = np.random.default_rng(seed)
    out: dict[str, np.ndarray] = {}
    for s in config.sensors:
        field_ut = np.concatenate([np.asarray(scene.field_t(a, 0.0)) for a in s.addresses]) * 1e6
        sigma_ut = np.tile([noise.sigma_ut(a, settings.tconvm_us()) for a in "xyz"], len(s.addresses))
        lsb_ut = np.tile([settings.sensitivity_ut(a) for a in "xyz"], len(s.addresses))
        KA = s.calibration.model.KA
        chunks = []
        for n in [CHUNK] * (samples // CHUNK) + [samples % CHUNK]:
            readings = (
                np.round((field_ut + rng.standard_normal((n, len(field_ut))) * sigma_ut) / lsb_ut) * lsb_ut
            )
            chunks.append(readings * 1e-6 @ KA.T)
        w = np.concatenate(chunks)
        out[f"wrench/{s.name}"] = w - w.mean(axis=0)
    if config.tool_poses:
        out["wrench/tip"] = sum(
            out[f"wrench/{n}"] @ se3.wrench_transform(T).T for n, T in config.tool_poses.items()
        )
    return out


def tail_rate(deviations: np.ndarray, sigmas: float) -> float:
    """The share of samples beyond ``sigmas`` of their own spread on any axis."""
    return float(np.mean(np.max(np.abs(deviations) / deviations.std(axis=0), axis=1) > sigmas))
