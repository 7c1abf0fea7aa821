"""The daemon's configuration: one TOML file, validated on load.

Every error names the file, the key and what was expected. Relative paths in
the file (scene, calibrations) are relative to the file's folder;
``builtin:NAME`` names a file shipped in the package (the simulated sensors'
calibrations). `config/ftsensord.toml` is a commented example.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ftsensord.acquire import choice
from ftsensord.acquire.board import bus_timing
from ftsensord.acquire.bound import SCHEDULERS, CycleBound
from ftsensord.acquire.bus import parse_bus_spec
from ftsensord.acquire.choice import Bus as ChoiceBus
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.i2c import BusTiming
from ftsensord.config.frames import TIP, GravityConfig, gravity_config, tool_poses
from ftsensord.config.ros2conf import Ros2Config, parse_ros2
from ftsensord.config.sensors import Calibrations, SensorConfig, sensor_tables
from ftsensord.docfile import Table, load_toml
from ftsensord.errors import ConfigError
from ftsensord.protocol.endpoints import Security, endpoint, security_table
from ftsensord.protocol.paths import builtin_path, resolve_file, runtime_dir

CONFIG_VERSION = 1


def default_config_path() -> Path:
    """The configuration used when none is given: the simulated bus, default scene."""
    return builtin_path("sim.toml")


@dataclass
class Config:
    """A validated configuration (units in the names: Hz, s, m)."""

    path: Path
    bus: str
    bus_hz: float
    bus_overhead_s: float
    rate_hz: float
    scheduler: str
    averaging: int
    lowpass_hz: float
    settings: mlx.Settings
    sensors: list[SensorConfig]
    publish: list[str]
    control: str
    tool_poses: dict[str, np.ndarray] = field(default_factory=dict)  # sensor: T_tip,s (4x4, m)
    tool_frame: str = TIP  # the tip frame's name (wrench/tip is in it)
    gravity: GravityConfig | None = None  # gravity compensation ([gravity]), off when None
    security: Security = field(default_factory=Security)
    temperature_every: int = 100
    #: Identical readings that mean a stuck chip; None (not in the file): as the conversion
    #: asks (`acquire.health.stuck_cycles_for`), also after it changes.
    stuck_cycles: int | None = None
    readback_every: int = 1
    max_missing_chips: int = 2
    #: What the file names of ``scheduler`` and ``readback_every``; the daemon chooses the rest (`choose`).
    named: frozenset[str] = frozenset({"scheduler", "readback_every"})
    ros2: Ros2Config | None = None  # the streams on the ROS 2 graph ([ros2]), off when None
    choice: str = ""  # how ``scheduler`` and ``readback_every`` were decided, for the log and `status`

    @property
    def orientation_endpoint(self) -> str | None:
        """Where the orientation stream comes in (gravity from the stream), else None."""
        return self.gravity.endpoint if self.gravity is not None else None

    @property
    def addresses(self) -> list[int]:
        return [a for s in self.sensors for a in s.addresses]

    def bus_levers(
        self, timing: BusTiming | None = None
    ) -> ChoiceBus:  # (the field `choice` hides the module in annotations)
        """What the bound depends on: ``timing`` is what was measured on the board
        (`acquire.board`); else what the bus string says (a simulated board), else the
        configured ``bus_hz`` and ``bus_overhead_us``, counted with the adapter's rules
        where the system names its driver (unknown: the narrowest)."""
        known = bus_timing(self.bus)
        if timing is not None:
            known = BusTiming(
                timing.adapter or known.adapter,
                timing.ioctl_s if timing.ioctl_s is not None else known.ioctl_s,
                timing.clock_hz or known.clock_hz,
            )
        return choice.Bus(
            len(self.addresses),
            self.settings,
            known.clock_hz or self.bus_hz,
            self.bus_overhead_s if known.ioctl_s is None else known.ioctl_s,
            known.adapter,
            self.temperature_every > 0,
        )

    def bound(self, timing: BusTiming | None = None) -> CycleBound:
        """The configured scheduler's bound on this bus (`bus_levers`)."""
        return self.bus_levers(timing).bound(self.scheduler, self.readback_every > 0)

    def choose(
        self,
        timing: BusTiming | None = None,
        where: str = "rate_hz",
        running: str | None = None,
        strict: bool = True,
    ) -> None:
        """Set what the file leaves unnamed of ``scheduler`` and ``readback_every`` to what
        holds ``rate_hz`` with the most margin (`acquire.choice.choose`; keeping the
        read-back while it can); a named one is checked. ``running``: the scheduler a
        running daemon keeps (only a restart chooses it again). When nothing holds:
        ConfigError naming every lever, or with ``strict`` off (a board measured slower
        than the file says, where the loop runs anyway), the fastest option."""
        levers = self.bus_levers(timing)
        named = (
            self.scheduler if "scheduler" in self.named else running,
            self.readback_every if "readback_every" in self.named else None,
        )
        try:
            picked = choice.choose(levers, self.rate_hz, *named)
        except ConfigError as exc:
            if strict:
                raise ConfigError(f"{where}: {exc}") from exc
            picked = choice.fastest(choice.options(levers, self.rate_hz, *named))
        self.scheduler, self.readback_every = picked.scheduler, picked.readback_every
        unnamed = sorted({"scheduler", "readback_every"} - self.named)
        self.choice = choice.explain(levers, picked, self.rate_hz, *named) + (
            f" (chosen: {', '.join(unnamed)} not in the file)" if unnamed else " (as configured)"
        )


def load_config(path: str | Path | None = None, calibrations: Calibrations | None = None) -> Config:
    """Read and validate a configuration (default: the packaged simulated one);
    ``calibrations``: files already read, reused where unchanged."""
    path = Path(path) if path is not None else default_config_path()
    doc = Table(load_toml(path), path)
    doc.only(
        {
            "version",
            "bus",
            "bus_hz",
            "bus_overhead_us",
            "rate_hz",
            "scheduler",
            "averaging",
            "lowpass_hz",
            "temperature_every",
            "stuck_cycles",
            "readback_every",
            "max_missing_chips",
            "publish",
            "publish_tcp",
            "control",
            "chip",
            "sensor",
            "tool",
            "gravity",
            "security",
            "ros2",
        }
    )
    doc.integer("version", what=str(CONFIG_VERSION), low=CONFIG_VERSION, high=CONFIG_VERSION)
    bus = doc.string("bus")
    try:
        kind, arg = parse_bus_spec(bus)
    except ConfigError as exc:
        raise doc.fail("bus", str(exc).split("; ", 1)[-1], bus) from exc
    if kind == "sim" and arg:
        options = bus.partition("?")[2]  # the simulated board's options stay
        bus = f"sim:{resolve_file(doc, 'bus', arg)}" + (f"?{options}" if options else "")
    chip = doc.table("chip", {})
    chip.only({"gain_sel", "hallconf", "res", "osr", "dig_filt", "osr2"})
    res = chip.numbers("res", 3, [3, 3, 3])
    if any(r != int(r) for r in res):  # int() would read 2.5 as RES 2
        raise chip.fail("res", "3 integers (RES_X, RES_Y, RES_Z)", chip.get("res"))
    settings = mlx.Settings(
        gain_sel=chip.integer("gain_sel", 0),
        hallconf=chip.integer("hallconf", 0xC),
        res_x=int(res[0]),
        res_y=int(res[1]),
        res_z=int(res[2]),
        osr=chip.integer("osr", 1),
        dig_filt=chip.integer("dig_filt", 2),
        osr2=chip.integer("osr2", 0),
    )
    try:
        settings.validate()
    except ConfigError as exc:
        raise ConfigError(f"{path}: chip: {exc}") from exc
    sensors = sensor_tables(doc, calibrations)
    security = security_table(doc)
    rt = runtime_dir()
    stream_why = "set [security] public_stream = true to publish the wrench stream beyond this host"
    publish = [
        endpoint(doc, "publish", f"ipc://{rt}/wrench", off_loopback=security.public_stream, why=stream_why)
    ]
    if "publish_tcp" in doc.doc:
        publish.append(endpoint(doc, "publish_tcp", "", off_loopback=security.public_stream, why=stream_why))
    config = Config(
        path=path,
        bus=bus,
        bus_hz=doc.number("bus_hz", 400e3, low=1e3, high=3.4e6, unit="Hz"),
        bus_overhead_s=doc.number("bus_overhead_us", 0.0, low=0, high=1e5, unit="us") * 1e-6,
        rate_hz=doc.number("rate_hz", 100.0, low=0.1, high=10e3, unit="Hz"),
        scheduler=doc.string(
            "scheduler", SCHEDULERS[-1], choices=SCHEDULERS
        ),  # unnamed: `choose` below decides
        averaging=doc.integer("averaging", 1, low=1, high=10_000, what="an integer from 1 to 10000"),
        lowpass_hz=doc.number("lowpass_hz", 0.0, low=0, unit="Hz (0: off)"),
        settings=settings,
        sensors=sensors,
        publish=publish,
        security=security,
        control=endpoint(
            doc,
            "control",
            f"ipc://{rt}/control",
            off_loopback=security.curve or security.allow_insecure_control,
            why="control beyond this host needs [security] curve_server_cert and curve_clients_dir "
            "(or allow_insecure_control = true, which is logged)",
        ),
        temperature_every=doc.integer("temperature_every", 100, low=0, what="cycles (0: never)"),
        stuck_cycles=doc.integer("stuck_cycles", low=0, what="cycles (0: no stuck detection)")
        if "stuck_cycles" in doc.doc
        else None,
        readback_every=doc.integer("readback_every", 1, low=0, what="cycles (0: no register read-back)"),
        named=frozenset({"scheduler", "readback_every"} & doc.doc.keys()),
        max_missing_chips=doc.integer(
            "max_missing_chips", 2, low=0, high=5, what="0 to 5 chips (degraded mode; 0: off)"
        ),
    )
    names = [s.name for s in sensors]
    if "tool" in doc.doc:
        config.tool_poses, config.tool_frame = tool_poses(doc.table("tool"), names)
    if "gravity" in doc.doc:
        config.gravity = gravity_config(
            doc.table("gravity"), names, config.tool_poses, f"ipc://{rt}/orientation"
        )
        if config.gravity.endpoint is not None:
            config.gravity.endpoint = endpoint(
                doc.table("gravity"),
                "endpoint",
                config.gravity.endpoint,
                why="orientations decide the compensated wrench: this host only",
            )
    world = [s.table for s in sensors if s.stray_field == "world" and s.table is not None]
    if world and (config.gravity is None or config.gravity.source != "stream"):
        raise world[0].fail(
            "stray_field", '"uniform" or "gradient" ("world" needs [gravity] orientation = "stream")', "world"
        )
    config.ros2 = parse_ros2(doc, path)
    config.choose(where=f"{path}: rate_hz")
    return config


def needs_restart(old: Config, new: Config) -> list[str]:
    """What differs between two configurations that a reload cannot change (the bus,
    its chips, their settings but the conversion, the scheduler, the endpoints); empty when
    a reload can take ``new``. The conversion (OSR, DIG_FILT) is written to running chips."""
    return [
        name
        for name, a, b in (
            ("bus", new.bus, old.bus),
            ("bus_hz", new.bus_hz, old.bus_hz),
            ("scheduler", new.scheduler, old.scheduler),
            (
                "chip",
                replace(new.settings, osr=old.settings.osr, dig_filt=old.settings.dig_filt),
                old.settings,
            ),
            (
                "sensor addresses",
                [(s.name, s.addresses) for s in new.sensors],
                [(s.name, s.addresses) for s in old.sensors],
            ),
            (
                "endpoints",
                (new.publish, new.control, new.orientation_endpoint),
                (old.publish, old.control, old.orientation_endpoint),
            ),
        )
        if a != b
    ]


def reload_config(
    old: Config,
    calibrations: Calibrations | None = None,
    timing: BusTiming | None = None,
    adjust: Callable[[Config, BusTiming | None], object] | None = None,
) -> Config:
    """Re-read ``old``'s file; ConfigError when it is bad or changes what needs a restart.
    What the file leaves unnamed is chosen again on the board's ``timing``, keeping the
    running scheduler (a reload cannot change it). ``adjust(new, timing)``: what the daemon
    sets from the file before that (the settings a sensor's ``accuracy`` chooses, as at start)."""
    new = load_config(old.path, calibrations)
    if adjust is not None:
        adjust(new, timing)
    if new.named != {"scheduler", "readback_every"}:  # as at start: a slow board runs late, not refused
        new.choose(timing, f"{new.path}: rate_hz", running=old.scheduler, strict=False)
    fixed = needs_restart(old, new)
    if fixed:
        raise ConfigError(f"{new.path}: changing {', '.join(fixed)} needs a restart; nothing was changed")
    return new
