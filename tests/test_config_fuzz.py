"""Hypothesis against the files the daemon reads: one or two mutations of a valid
configuration (every key of every table: wrong types, huge, negative, NaN, unicode, deleted,
unknown siblings) and of a packaged calibration (its checksum recomputed, so the mutation
reaches the checks behind it). The contract: the file loads, or a ConfigError names the file
and a key of the mutated path; never another exception."""

from __future__ import annotations

import copy
import json
import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ftsensord.calibration.calfile import Calibration, checksum
from ftsensord.config.file import load_config
from ftsensord.config.sensors import Calibrations
from ftsensord.errors import ConfigError
from ftsensord.protocol.paths import builtin_path

CONFIG = {
    "version": 1,
    "bus": "sim",
    "bus_hz": 400000,
    "rate_hz": 100,
    "averaging": 1,
    "lowpass_hz": 0.0,
    "temperature_every": 100,
    "readback_every": 1,
    "max_missing_chips": 2,
    "chip": {"gain_sel": 0, "hallconf": 12, "res": [3, 3, 3], "osr": 1, "dig_filt": 2, "osr2": 0},
    "sensor": [
        {
            "name": "sensor1",
            "addresses": list(range(0x0C, 0x14)),
            "calibration": "builtin:sim-sensor1.json",
            "frame": "s1",
            "estimator": "linear",
            "stray_field": "uniform",
        },
        {"name": "sensor2", "addresses": list(range(0x14, 0x1C)), "calibration": "builtin:sim-sensor2.json"},
    ],
    "tool": {"frame": "tip", "offsets_m": {"sensor1": [0.0, 0.0, -0.2], "sensor2": [0.0, 0.0, -0.1]}},
    "gravity": {
        "orientation": "stream",
        "stale_after_s": 0.1,
        "gravity_mps2": [0, 0, -9.81],
        "orientation_sigma_deg": 0.3,
        "sensor1": {"mass_kg": 0.1, "com_m": [0, 0, 0.01]},
    },
    "security": {"allow_insecure_control": False, "public_stream": False},
}
VALUES = st.recursive(
    st.one_of(
        st.integers(-(2**64), 2**64),
        st.floats(),
        st.booleans(),
        st.text(max_size=12),
        st.sampled_from(
            [
                "",
                "builtin:",
                "ipc://",
                "tcp://127.0.0.1:*",
                "tcp://0.0.0.0:1",
                "ipc://@x",
                "nonlinear",
                "world",
                "mount",
                "sensor1",
                "tip",
                "\u00e9",
                0.5,
                2.5,
                -0.0,
                1e308,
                12,
                27,
                28,
            ]
        ),
    ),
    lambda inner: st.one_of(
        st.lists(inner, max_size=9),
        st.dictionaries(st.sampled_from(["name", "x", "sensor1"]), inner, max_size=2),
    ),
    max_leaves=8,
)


def _paths(doc, prefix=()) -> list[tuple]:
    out = []
    for k, v in doc.items() if isinstance(doc, dict) else enumerate(doc):
        out.append(prefix + (k,))
        if isinstance(v, (dict, list)) and not (isinstance(v, list) and len(v) > 9):
            out += _paths(v, prefix + (k,))
    return out


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return (
            "nan"
            if math.isnan(value)
            else "inf"
            if value == math.inf
            else "-inf"
            if value == -math.inf
            else repr(value)
        )
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):  # JSON's escapes are TOML's, but for surrogate pairs (kept raw) and DEL
        return json.dumps(value, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(value, list):
        return "[" + ", ".join(map(_toml, value)) + "]"
    return "{" + ", ".join(f"{_toml(k)} = {_toml(v)}" for k, v in value.items()) + "}"


def _mutate(doc, mutations) -> list[tuple]:
    done = []
    for path, delete, value in mutations:
        parent = doc
        try:
            for k in path[:-1]:
                parent = parent[k]
            if delete:
                del parent[path[-1]]
            else:
                parent[path[-1]] = value
        except (KeyError, IndexError, TypeError):
            continue
        done.append(path)
    return done


def _assert_names_a_key(exc: ConfigError, path, mutated: list[tuple]) -> None:
    msg = str(exc)
    assert str(path) in msg, msg
    keys = {str(k) for p in mutated for k in p if isinstance(k, str)}
    assert not keys or any(k in msg for k in keys), (mutated, msg)


@pytest.fixture(scope="module")
def calibrations() -> Calibrations:
    return Calibrations()


@settings(max_examples=300, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(st.lists(st.tuples(st.sampled_from(_paths(CONFIG)), st.booleans(), VALUES), min_size=1, max_size=2))
def test_a_mutated_configuration_loads_or_names_its_file_and_key(tmp_path_factory, calibrations, mutations):
    doc = copy.deepcopy(CONFIG)
    mutated = _mutate(doc, mutations)
    path = tmp_path_factory.mktemp("config") / "ftsensord.toml"
    path.write_text("".join(f"{_toml(k)} = {_toml(v)}\n" for k, v in doc.items()), encoding="utf-8")
    try:
        load_config(path, calibrations)
    except ConfigError as exc:
        _assert_names_a_key(exc, path, mutated)


CALIBRATION = json.loads(builtin_path("sim-sensor1.json").read_text())


@settings(max_examples=200, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(
    st.lists(
        st.tuples(
            st.sampled_from([p for p in _paths(CALIBRATION) if p[0] != "checksum"]), st.booleans(), VALUES
        ),
        min_size=1,
        max_size=2,
    )
)
def test_a_mutated_calibration_loads_or_names_its_file_and_key(tmp_path_factory, mutations):
    doc = copy.deepcopy(CALIBRATION)
    mutated = _mutate(doc, mutations)
    doc["checksum"] = checksum(doc) if all(math.isfinite(v) for v in _floats(doc)) else doc["checksum"]
    path = tmp_path_factory.mktemp("cal") / "cal.json"
    path.write_text(json.dumps(doc))
    try:
        Calibration.load(path)
    except ConfigError as exc:
        _assert_names_a_key(exc, path, mutated)


def _floats(doc):
    if isinstance(doc, dict):
        for v in doc.values():
            yield from _floats(v)
    elif isinstance(doc, list):
        for v in doc:
            yield from _floats(v)
    elif isinstance(doc, float):
        yield doc
