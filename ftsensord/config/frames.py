"""The tool's frames and its weight, as the configuration gives them.

``[tool]``: each sensor's pose in the tip frame (``T_tip,s``: position in m and a
rotation vector in degrees), from which the tip's wrench is summed; the older
``[tool.offsets_m]`` (positions only, frames parallel) still reads.
``[gravity]``: the tool's mass and centre of mass per sensor and for the tip, and
where the orientations come from (fixed mounts, or the orientation stream,
`protocol.orientation`). `processing.gravity` does the compensating.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ftsensord.chip import mpu6050
from ftsensord.docfile import Table
from ftsensord.model import se3

TIP = "tip"  # the tip's name in [gravity] and in orientation messages
#: Standard gravity (m/s^2), the default |g| (the local value differs by up to 0.3 %).
STANDARD_G = 9.80665
ORIENTATION_SOURCES = ("mount", "stream")
#: Longest frame name an orientation message carries (its 32-byte field keeps a NUL).
MAX_FRAME_NAME = 31
#: An orientation stream's 1-sigma per axis (deg) unless configured: an MPU-6050's tilt from one
#: accelerometer reading, its datasheet noise (`mpu6050.noise_g`, 6.4 mg RMS with the digital
#: low-pass off) over 1 g, in rad: the cheapest IMU a tool carries. The stream's messages say
#: nothing of their noise; an encoder-fed haptic device is far better (set it lower).
STREAM_SIGMA_DEG = float(np.degrees(mpu6050.noise_g()))
#: Farthest a sensor or a payload's centre of mass lies from the frame it is given in (m):
#: a hand-held or robot-carried tool is well within it; more is a unit mistake (30 for 30 mm).
MAX_LEVER_M = 2.0


@dataclass
class Payload:
    """What hangs on a frame: ``mass_kg`` at ``com_m`` (m, in that frame)."""

    mass_kg: float
    com_m: np.ndarray

    def wrench(self, g: np.ndarray) -> np.ndarray:
        """The weight's wrench [f; m] (N, Nm) in the frame, for gravity ``g`` (m/s^2) seen
        in the frame: f = m g at the centre of mass, m = c x f (`se3.wrench_transform`).
        Several at once: ``g`` n x 3, the wrenches n x 6."""
        f = self.mass_kg * np.asarray(g, dtype=float)
        return np.concatenate([f, np.cross(self.com_m, f)], axis=-1)


@dataclass
class GravityConfig:
    """Gravity compensation: which frames (sensor names, "tip") carry a payload, and
    where their orientations (R_world,frame) come from."""

    source: str  # "mount" or "stream"
    payloads: dict[str, Payload]
    mounts: dict[str, np.ndarray] = field(default_factory=dict)  # R_world,frame of the fixed ones
    gravity_mps2: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -STANDARD_G]))  # world frame
    stale_after_s: float = 0.05
    endpoint: str | None = None  # the orientation stream's, when source = "stream"
    #: Each orientation's 1-sigma about each of the frame's axes (rad), independent from one
    #: cycle to the next: 0 (exact) for the mounts unless configured (`STREAM_SIGMA_DEG`).
    orientation_sigma_rad: float = 0.0


def tool_poses(tool: Table, sensors: list[str]) -> tuple[dict[str, np.ndarray], str]:
    """``[tool]``: each sensor's pose in the tip frame (4x4 T_tip,s) and the tip frame's name."""
    tool.only({"offsets_m", "pose", "frame"})
    if ("offsets_m" in tool.doc) == ("pose" in tool.doc):
        raise tool.fail(
            "pose",
            "either [tool.pose.<sensor>] tables (position_m, rotvec_deg) or the older "
            "[tool.offsets_m], one of them",
            sorted(tool.doc),
        )
    poses: dict[str, np.ndarray] = {}
    if "offsets_m" in tool.doc:  # the first form: translations, frames parallel
        offsets = tool.table("offsets_m")
        for name in offsets.doc:
            _known(offsets, name, sensors)
            poses[name] = se3.pose(p=_lever(offsets, name, "m, the sensor's origin in the tip frame"))
    else:
        table = tool.table("pose")
        for name in table.doc:
            _known(table, name, sensors)
            t = table.table(name)
            t.only({"position_m", "rotvec_deg"})
            p = _lever(t, "position_m", "m, the sensor's origin in the tip frame")
            rotvec = np.radians(
                t.numbers("rotvec_deg", 3, [0.0, 0.0, 0.0], unit="deg, the sensor's axes in the tip frame")
            )
            poses[name] = se3.pose(se3.exp_so3(rotvec), p)
    return poses, tool.string("frame", TIP)


def _lever(t: Table, name: str, unit: str) -> np.ndarray:
    """A position (m) within `MAX_LEVER_M` of the frame's origin."""
    p = np.array(t.numbers(name, 3, unit=unit))
    if not (
        np.abs(p).max() <= MAX_LEVER_M and np.linalg.norm(p) <= MAX_LEVER_M
    ):  # max first: squaring 1e308 overflows
        raise t.fail(name, f"a position within {MAX_LEVER_M:g} m of the frame's origin ({unit})", p.tolist())
    return p


def _known(t: Table, name: str, sensors: list[str]) -> None:
    if name not in sensors:
        raise t.fail(name, f"one of the sensors {', '.join(sensors)}", name)


def gravity_config(
    g: Table, sensors: list[str], tool: dict[str, np.ndarray], default_endpoint: str
) -> GravityConfig:
    """``[gravity]``: payloads per frame, the orientations' source and its checks."""
    frames = [*sensors, *([TIP] if tool else [])]
    g.only({"orientation", "endpoint", "stale_after_s", "gravity_mps2", "orientation_sigma_deg", *frames})
    source = g.string("orientation", choices=ORIENTATION_SOURCES)
    gravity = np.array(g.numbers("gravity_mps2", 3, [0.0, 0.0, -STANDARD_G], unit="m/s^2, world frame"))
    # 9.7-9.9 m/s^2 is every place on Earth's surface; other magnitudes are a unit or sign mistake.
    if not 9.7 <= np.linalg.norm(gravity) <= 9.9:
        raise g.fail(
            "gravity_mps2",
            "gravity in the orientations' world frame, |g| 9.7-9.9 m/s^2 "
            "(z up: [0, 0, -9.81]; y up: [0, -9.81, 0])",
            gravity.tolist(),
        )
    config = GravityConfig(
        source,
        {},
        gravity_mps2=gravity,
        stale_after_s=g.number("stale_after_s", 0.05, low=1e-3, high=60.0, unit="s"),
        endpoint=g.string("endpoint", default_endpoint) if source == "stream" else None,
        # 10 deg is far beyond any IMU's or encoder's noise: more is a unit mistake (rad for deg).
        orientation_sigma_rad=float(
            np.radians(
                g.number(
                    "orientation_sigma_deg",
                    STREAM_SIGMA_DEG if source == "stream" else 0.0,
                    low=0.0,
                    high=10.0,
                    unit="deg, each orientation's 1-sigma about each axis",
                )
            )
        ),
    )
    for name in frames:
        if name not in g.doc:
            continue
        t = g.table(name)
        t.only({"mass_kg", "com_m", "mount_rotvec_deg"})
        if len(name) > MAX_FRAME_NAME or not name.isascii():
            raise g.fail(
                name,
                f"a sensor named in ASCII, at most {MAX_FRAME_NAME} characters (orientation "
                "messages carry the name)",
                name,
            )
        # 10 kg is far beyond what a sensor of 50 N range carries: a unit mistake (g for kg).
        config.payloads[name] = Payload(
            t.number("mass_kg", low=0.0, high=10.0, unit="kg"), _lever(t, "com_m", "m, in this frame")
        )
        if "mount_rotvec_deg" in t.doc:
            if source != "mount":
                raise t.fail(
                    "mount_rotvec_deg",
                    'no mount with orientation = "stream" (the stream gives it)',
                    t.get("mount_rotvec_deg"),
                )
            rotvec = np.radians(t.numbers("mount_rotvec_deg", 3, unit="deg, the frame's axes in the world"))
            config.mounts[name] = se3.exp_so3(rotvec)
    if not config.payloads:
        raise g.fail(
            "orientation",
            f"at least one [gravity.<frame>] table (frames: {', '.join(frames)})",
            sorted(g.doc),
        )
    if source == "mount":
        tool_frames = {*tool, TIP}
        for name in config.payloads:
            if name not in config.mounts and not (name in tool_frames and config.mounts.keys() & tool_frames):
                raise g.table(name).fail(
                    "mount_rotvec_deg",
                    "the frame's orientation in the world (orientation = "
                    '"mount"), here or on another frame of the tool',
                    None,
                )
    return config
