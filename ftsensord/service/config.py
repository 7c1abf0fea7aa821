"""The daemon's configuration: one TOML file, validated on load.

Every error names the file, the key and what was expected. Relative paths in
the file (scene, calibrations) are relative to the file's folder;
``builtin:NAME`` names a file shipped in the package (the simulated sensors'
calibrations). `config/ftsensord.toml` is a commented example.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np

from ..acquire.board import bus_timing
from ..acquire.bound import DEFAULT_SCHEDULER, SCHEDULERS, CycleBound, burst_readback_stays_fresh, cycle_bound
from ..acquire.bus import parse_bus_spec
from ..acquire.health import stuck_cycles_for
from ..calibration.calfile import Calibration
from ..calibration.dataset import parse_addresses
from ..chip import mlx90393 as mlx
from ..chip.i2c import BusTiming
from ..docfile import Table, load_toml
from ..errors import ConfigError
from ..model.linear import LinearModel
from .frames import TIP, GravityConfig, gravity_config, tool_poses

CONFIG_VERSION = 1
ESTIMATORS = ("linear", "nonlinear")
#: Beside the deflection: the room's field; its gradient's parts a ring tells apart; a world-fixed gradient (`stages.stray`).
STRAY_FIELDS = ("uniform", "gradient", "world")
BUILTIN = "builtin:"


def builtin_path(name: str) -> Path:
    """A file shipped in the package's data folder."""
    return Path(str(resources.files("ftsensord") / "data" / name))


def default_config_path() -> Path:
    """The configuration used when none is given: the simulated bus, default scene."""
    return builtin_path("sim.toml")


def runtime_dir() -> Path:
    """Where the daemon's sockets go: systemd's RuntimeDirectory, else the user's
    ($XDG_RUNTIME_DIR/ftsensord), else /tmp/ftsensord-<uid> (sudo, cron, containers).
    Only a name: `ensure_private_dir` creates and checks it before use."""
    if os.environ.get("RUNTIME_DIRECTORY"):
        return Path(os.environ["RUNTIME_DIRECTORY"].split(":")[0])
    if os.environ.get("XDG_RUNTIME_DIR"):
        return Path(os.environ["XDG_RUNTIME_DIR"]) / "ftsensord"
    return Path(f"/tmp/ftsensord-{os.getuid()}")


def check_private_dir(path: Path, owner: int | None = None) -> None:
    """Refuse a folder for sockets that someone else could swap them in: a symlink, not a
    folder, not owned by ``owner`` (default: this process's user), or writable by its group
    or others. ``owner=-1``: any owner, but then its parent must be root's and not writable
    by others (only root, or systemd for the service, can have made it)."""
    try:
        st = os.lstat(path)
    except FileNotFoundError as exc:
        raise ConfigError(f"{path}: the runtime folder does not exist") from exc
    uid = os.geteuid() if owner is None else owner
    why = None
    if stat.S_ISLNK(st.st_mode):
        why = "is a symbolic link"
    elif not stat.S_ISDIR(st.st_mode):
        why = "is not a folder"
    elif uid != -1 and st.st_uid != uid:
        why = f"belongs to uid {st.st_uid}, not to uid {uid}"
    elif st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        why = f"is writable by {'others' if st.st_mode & stat.S_IWOTH else 'its group'} (mode {st.st_mode & 0o7777:04o})"
    elif uid == -1:
        parent = os.lstat(path.parent)
        if parent.st_uid != 0 or parent.st_mode & stat.S_IWOTH:
            why = f"is in {path.parent}, which root alone does not control"
    if why is not None:
        raise ConfigError(f"{path}: refusing this runtime folder: it {why}; another user could put their "
                          "sockets in place of the daemon's. Remove it (or fix its owner and mode 0700), "
                          "or set RUNTIME_DIRECTORY or XDG_RUNTIME_DIR")


def ensure_private_dir(path: Path) -> Path:
    """Create ``path`` mode 0700 if missing (its missing parents too), then check it with
    `check_private_dir` (lstat: a symlink put there meanwhile is refused, never followed)."""
    if not os.path.lexists(path):
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        try:
            os.mkdir(path, 0o700)  # one syscall: exists already (someone else's?) or ours
        except FileExistsError:
            pass  # made meanwhile: the check below decides
    check_private_dir(path)
    return path


@dataclass
class Security:
    """Who may reach the endpoints when they leave loopback (docs/protocol.md)."""

    curve_server_cert: Path | None = None  # zmq certificate with the server's secret key
    curve_clients_dir: Path | None = None  # public certificates of the clients allowed to control
    allow_insecure_control: bool = False  # control off loopback without CURVE: logged loudly
    public_stream: bool = False  # the (read-only) wrench stream may leave loopback

    @property
    def curve(self) -> bool:
        return self.curve_server_cert is not None


@dataclass
class SensorConfig:
    name: str
    addresses: tuple[int, ...]
    calibration_path: Path
    calibration: Calibration
    frame: str  # the frame its wrench is expressed in (default: the calibration's)
    estimator: str = "linear"  # "linear" (K A) or "nonlinear" (the flux model, docs/tradeoff.md)
    stray_field: str = "uniform"  # `STRAY_FIELDS`

    @property
    def model(self) -> LinearModel:  # the run time's: the calibration's, `LinearModel.with_gradient` if asked
        return self.calibration.model.with_gradient() if self.stray_field == "gradient" else self.calibration.model


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
    stuck_cycles: int = 0  # load_config's default: stuck_cycles_for(settings)
    readback_every: int = 1
    max_missing_chips: int = 2

    @property
    def orientation_endpoint(self) -> str | None:
        """Where the orientation stream comes in (gravity from the stream), else None."""
        return self.gravity.endpoint if self.gravity is not None else None

    @property
    def addresses(self) -> list[int]:
        return [a for s in self.sensors for a in s.addresses]

    def bound(self, timing: BusTiming | None = None) -> CycleBound:
        """The scheduler's bound on this bus: ``timing`` is what was measured on the
        board (`acquire.board`); else what the bus string says (a simulated board),
        else the configured ``bus_hz`` and ``bus_overhead_us``, counted with the
        adapter's rules where the system names its driver (unknown: the narrowest)."""
        known = bus_timing(self.bus)
        if timing is not None:
            known = BusTiming(timing.adapter or known.adapter,
                              timing.ioctl_s if timing.ioctl_s is not None else known.ioctl_s,
                              timing.clock_hz or known.clock_hz)
        return cycle_bound(self.scheduler, len(self.addresses), self.settings, known.clock_hz or self.bus_hz,
                           self.bus_overhead_s if known.ioctl_s is None else known.ioctl_s,
                           readback=self.readback_every > 0, temperature=self.temperature_every > 0,
                           adapter=known.adapter)


def check_rate(config: Config, rate_hz: float, where: str = "rate_hz", timing: BusTiming | None = None) -> None:
    """Refuse a rate above what the scheduler can achieve, naming the bound and the fixes."""
    bound = config.bound(timing)
    if rate_hz <= bound.rate_hz:
        return
    others = ", ".join(f"{s} {replace(config, scheduler=s).bound(timing).rate_hz:.0f} Hz"
                       for s in SCHEDULERS if s != config.scheduler)
    bare = replace(config, readback_every=0).bound(timing).rate_hz  # the register read-back's part of the cycle
    raise ConfigError(f"{where}: {rate_hz:g} Hz cannot be met: {bound.describe()}. Lower the rate, change the "
                      f"scheduler ({others}), read no register back (readback_every = 0: {bare:.0f} Hz), shorten "
                      f"the conversion (lower OSR or DIG_FILT), or use a faster bus")


def _resolve(table: Table, key: str, value: str) -> Path:
    if value.startswith(BUILTIN):
        path = builtin_path(value[len(BUILTIN):])
    else:
        path = Path(value).expanduser()
        if not path.is_absolute():
            path = table.path.parent / path
    if not path.is_file():
        raise table.fail(key, "an existing file (relative to the configuration's folder, or builtin:NAME)", value)
    return path


LOOPBACK = ("127.0.0.1", "localhost", "[::1]")


def is_loopback(endpoint: str) -> bool:
    return not endpoint.startswith("tcp://") or endpoint[len("tcp://"):].rsplit(":", 1)[0] in LOOPBACK


def _endpoint(table: Table, key: str, default: str, *, off_loopback: bool = False, why: str = "") -> str:
    """An ipc:// or tcp:// endpoint; TCP only on loopback unless ``off_loopback``."""
    value = table.string(key, default)
    if not value.startswith(("ipc://", "tcp://")):
        raise table.fail(key, "an ipc:// or tcp:// endpoint", value)
    if value.startswith("ipc://@"):  # Linux's abstract namespace: no file, so no mode, group or lock
        raise table.fail(key, "an ipc:// endpoint with a path (an abstract socket, ipc://@name, has no file "
                              "permissions: anyone on the host could connect)", value)
    if not off_loopback and not is_loopback(value):
        raise table.fail(key, f"a loopback TCP endpoint (127.0.0.1, localhost or [::1]); {why}", value)
    return value


def _security(doc: Table) -> Security:
    if "security" not in doc.doc:
        return Security()
    t = doc.table("security")
    t.only({"curve_server_cert", "curve_clients_dir", "allow_insecure_control", "public_stream"})
    cert = _resolve(t, "curve_server_cert", t.string("curve_server_cert")) if "curve_server_cert" in t.doc else None
    clients = None
    if "curve_clients_dir" in t.doc:
        clients = Path(t.string("curve_clients_dir")).expanduser()
        clients = clients if clients.is_absolute() else t.path.parent / clients
        if not clients.is_dir():
            raise t.fail("curve_clients_dir", "a folder of the allowed clients' public certificates",
                         t.get("curve_clients_dir"))
    if (cert is None) != (clients is None):
        raise t.fail("curve_server_cert" if cert is None else "curve_clients_dir",
                     "both curve_server_cert and curve_clients_dir, or neither", "only one of them")
    flags = {}
    for key in ("allow_insecure_control", "public_stream"):
        value = t.get(key, False)
        if not isinstance(value, bool):
            raise t.fail(key, "true or false", value)
        flags[key] = value
    return Security(cert, clients, **flags)


class Calibrations:
    """Calibration files by path, read again only when changed: a reload that changes a
    rate reuses the checked calibrations (and their pipelines' precomputed checks) instead
    of parsing them again, so it fits between two cycles. Changed means another size,
    modification time or inode: an editor or `ftsensord calibrate -o` changes them all."""

    def __init__(self) -> None:
        self._seen: dict[Path, tuple[tuple[int, ...], Calibration]] = {}

    @staticmethod
    def _signature(path: Path) -> tuple[int, ...]:
        st = path.stat()
        return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns

    def remember(self, config: Config) -> Calibrations:
        """Take ``config``'s calibrations as their files are now; returns self."""
        for s in config.sensors:
            self._seen[s.calibration_path] = (self._signature(s.calibration_path), s.calibration)
        return self

    def load(self, path: Path) -> Calibration:
        seen = self._seen.get(path)
        try:
            signature = self._signature(path)
        except OSError:
            signature = ()  # Calibration.load names the file and the error
        if seen is not None and seen[0] == signature:
            return seen[1]
        calibration = Calibration.load(path)
        if signature:
            self._seen[path] = (signature, calibration)
        return calibration


def load_config(path: str | Path | None = None, calibrations: Calibrations | None = None) -> Config:
    """Read and validate a configuration (default: the packaged simulated one);
    ``calibrations``: files already read, reused where unchanged."""
    path = Path(path) if path is not None else default_config_path()
    doc = Table(load_toml(path), path)
    doc.only({"version", "bus", "bus_hz", "bus_overhead_us", "rate_hz", "scheduler", "averaging",
              "lowpass_hz", "temperature_every", "stuck_cycles", "readback_every", "max_missing_chips", "publish", "publish_tcp",
              "control", "chip", "sensor", "tool", "gravity", "security"})
    doc.integer("version", what=str(CONFIG_VERSION), low=CONFIG_VERSION, high=CONFIG_VERSION)
    bus = doc.string("bus")
    try:
        kind, arg = parse_bus_spec(bus)
    except ConfigError as exc:
        raise doc.fail("bus", str(exc).split("; ", 1)[-1], bus) from exc
    if kind == "sim" and arg:
        options = bus.partition("?")[2]  # the simulated board's options stay
        bus = f"sim:{_resolve(doc, 'bus', arg)}" + (f"?{options}" if options else "")
    chip = doc.table("chip", {})
    chip.only({"gain_sel", "hallconf", "res", "osr", "dig_filt", "osr2"})
    res = chip.numbers("res", 3, [3, 3, 3])
    settings = mlx.Settings(gain_sel=chip.integer("gain_sel", 0), hallconf=chip.integer("hallconf", 0xC),
                            res_x=int(res[0]), res_y=int(res[1]), res_z=int(res[2]),
                            osr=chip.integer("osr", 1), dig_filt=chip.integer("dig_filt", 2),
                            osr2=chip.integer("osr2", 0))
    try:
        settings.validate()
    except ConfigError as exc:
        raise ConfigError(f"{path}: chip: {exc}") from exc
    sensors: list[SensorConfig] = []
    seen: set[int] = set()
    world: list[Table] = []  # the sensors whose stray field needs the orientation stream
    for t in doc.tables("sensor"):
        t.only({"name", "addresses", "calibration", "frame", "estimator", "stray_field"})
        addresses = parse_addresses(t, "addresses")
        for a in addresses:
            if a in seen:
                raise t.fail("addresses", "addresses no other sensor uses", f"0x{a:02X}")
            seen.add(a)
        cal_path = _resolve(t, "calibration", t.string("calibration"))
        calibration = calibrations.load(cal_path) if calibrations is not None else Calibration.load(cal_path)
        if calibration.addresses != addresses:
            raise t.fail("calibration", f"a calibration for the chips {[f'0x{a:02X}' for a in addresses]} in "
                                        f"this order", f"{cal_path} (for {[f'0x{a:02X}' for a in calibration.addresses]})")
        name = t.string("name")
        if any(s.name == name for s in sensors):
            raise t.fail("name", "a name no other sensor has", name)
        estimator = t.string("estimator", "linear", choices=ESTIMATORS)
        if estimator == "nonlinear" and calibration.nonlinear is None:
            raise t.fail("estimator", f'"linear": {cal_path} has no nonlinear calibration '
                                      "(make one with `ftsensord calibrate` without --linear-only)", estimator)
        stray_field = t.string("stray_field", "uniform", choices=STRAY_FIELDS)
        if stray_field != "uniform" and calibration.model.H is None:
            raise t.fail("stray_field", f'"uniform": {cal_path} has no flux model H', stray_field)
        world += [t] if stray_field == "world" else []
        sensors.append(SensorConfig(name, addresses, cal_path, calibration, t.string("frame", calibration.frame),
                                    estimator, stray_field))
    security = _security(doc)
    rt = runtime_dir()
    stream_why = "set [security] public_stream = true to publish the wrench stream beyond this host"
    publish = [_endpoint(doc, "publish", f"ipc://{rt}/wrench", off_loopback=security.public_stream, why=stream_why)]
    if "publish_tcp" in doc.doc:
        publish.append(_endpoint(doc, "publish_tcp", "", off_loopback=security.public_stream, why=stream_why))
    config = Config(
        path=path, bus=bus, bus_hz=doc.number("bus_hz", 400e3, low=1e3, high=3.4e6, unit="Hz"),
        bus_overhead_s=doc.number("bus_overhead_us", 0.0, low=0, high=1e5, unit="us") * 1e-6,
        rate_hz=doc.number("rate_hz", 100.0, low=0.1, high=10e3, unit="Hz"),
        scheduler=doc.string("scheduler", DEFAULT_SCHEDULER, choices=SCHEDULERS),
        averaging=doc.integer("averaging", 1, low=1, high=10_000, what="an integer from 1 to 10000"),
        lowpass_hz=doc.number("lowpass_hz", 0.0, low=0, unit="Hz (0: off)"),
        settings=settings, sensors=sensors, publish=publish, security=security,
        control=_endpoint(doc, "control", f"ipc://{rt}/control",
                          off_loopback=security.curve or security.allow_insecure_control,
                          why="control beyond this host needs [security] curve_server_cert and curve_clients_dir "
                              "(or allow_insecure_control = true, which is logged)"),
        temperature_every=doc.integer("temperature_every", 100, low=0, what="cycles (0: never)"),
        stuck_cycles=doc.integer("stuck_cycles", stuck_cycles_for(settings), low=0, what="cycles (0: no stuck detection)"),
        readback_every=doc.integer("readback_every", 1, low=0, what="cycles (0: no register read-back)"),
        max_missing_chips=doc.integer("max_missing_chips", 2, low=0, high=5,
                                      what="0 to 5 chips (degraded mode; 0: off)"))
    names = [s.name for s in sensors]
    if "tool" in doc.doc:
        config.tool_poses, config.tool_frame = tool_poses(doc.table("tool"), names)
    if "gravity" in doc.doc:
        config.gravity = gravity_config(doc.table("gravity"), names, config.tool_poses, f"ipc://{rt}/orientation")
        if config.gravity.endpoint is not None:
            config.gravity.endpoint = _endpoint(doc.table("gravity"), "endpoint", config.gravity.endpoint,
                                                why="orientations decide the compensated wrench: this host only")
    if world and (config.gravity is None or config.gravity.source != "stream"):
        raise world[0].fail("stray_field", '"uniform" or "gradient" ("world" needs [gravity] orientation = "stream")', "world")
    if config.scheduler == "burst" and "readback_every" not in doc.doc and not burst_readback_stays_fresh(
            config.bound(), config.settings, config.rate_hz, config.temperature_every > 0):
        # A chip read back in burst mode (EX, RR, SB) restarts its burst: with no time for
        # a new result before the next cycle, every sample would have a stale chip.
        config.readback_every = 100
    check_rate(config, config.rate_hz, f"{path}: rate_hz")
    return config


def needs_restart(old: Config, new: Config) -> list[str]:
    """What differs between two configurations that a reload cannot change (the bus,
    its chips, the scheduler, the endpoints); empty when a reload can take ``new``."""
    return [name for name, a, b in (
        ("bus", new.bus, old.bus), ("bus_hz", new.bus_hz, old.bus_hz),
        ("scheduler", new.scheduler, old.scheduler), ("chip", new.settings, old.settings),
        ("sensor addresses", [(s.name, s.addresses) for s in new.sensors], [(s.name, s.addresses) for s in old.sensors]),
        ("endpoints", (new.publish, new.control, new.orientation_endpoint),
         (old.publish, old.control, old.orientation_endpoint))) if a != b]


def reload_config(old: Config, calibrations: Calibrations | None = None) -> Config:
    """Re-read ``old``'s file; ConfigError when it is bad or changes what needs a restart."""
    new = load_config(old.path, calibrations)
    fixed = needs_restart(old, new)
    if fixed:
        raise ConfigError(f"{new.path}: changing {', '.join(fixed)} needs a restart; nothing was changed")
    return new
