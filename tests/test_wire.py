"""The wire format against the test vectors of docs/reference/protocol.md."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ftsensord.errors import WireError
from ftsensord.protocol import wire

PROTOCOL = Path(__file__).resolve().parent.parent / "docs" / "reference" / "protocol.md"


def vector(name: str) -> bytes:
    text = PROTOCOL.read_text()
    match = re.search(rf"<!-- vector: {name} -->\s*```\n(.*?)```", text, re.S)
    assert match, f"no test vector {name!r} in {PROTOCOL}"
    return bytes.fromhex(match.group(1).replace("\n", " "))


def test_wrench_vector_matches_the_encoder_and_decodes_to_its_meaning():
    frame = wire.encode(
        "wrench/sensor1",
        wire.KIND_WRENCH,
        42,
        1234.5,
        1763836800.25,
        wire.FLAG_STALE | wire.FLAG_LATE,
        np.array([1.0, -0.5, 0.8, 0.02, -0.01, 0.015]),
    )
    assert frame == vector("wrench") and len(frame) == 103
    s = wire.decode(vector("wrench"))
    assert (s.topic, s.kind, s.seq, s.t_mono, s.t_wall) == ("wrench/sensor1", 1, 42, 1234.5, 1763836800.25)
    assert wire.flag_names(s.flags) == ["stale", "late"]
    assert np.array_equal(s.values, [1.0, -0.5, 0.8, 0.02, -0.01, 0.015])


def test_flux_vector_matches_the_encoder():
    frame = wire.encode(
        "flux/sensor2",
        wire.KIND_FLUX,
        7,
        0.125,
        1763836800.5,
        wire.FLAG_CHIP_MISSING | wire.FLAG_INVALID,
        np.array([1e-5, -2e-5, 1.5e-3]),
    )
    assert frame == vector("flux")
    assert wire.decode(frame).flags == 0x41


def test_sigma_vector_matches_the_encoder_and_an_old_decoder_reads_it_as_six_values():
    frame = wire.encode(
        "sigma/wrench/sensor1",
        wire.KIND_SIGMA,
        42,
        1234.5,
        1763836800.25,
        wire.FLAG_STALE | wire.FLAG_LATE,
        np.array([0.025, 0.031, 0.022, 0.003, 0.0029, np.nan]),
    )
    assert frame == vector("sigma") and len(frame) == 109
    s = wire.decode(frame)  # the header and count are a wrench's: only the kind and topic differ
    assert (s.topic, s.kind, s.seq, s.flags) == ("sigma/wrench/sensor1", 3, 42, 0x24)
    assert np.array_equal(s.values, [0.025, 0.031, 0.022, 0.003, 0.0029, np.nan], equal_nan=True)


def test_every_wrench_stream_has_a_sigma_companion_and_flux_none():
    for stream in ("wrench/sensor1", "wrench/tip", "wrench/sensor1/compensated", "wrench/tip/compensated"):
        assert wire.has_sigma(stream), stream
    for stream in ("flux/sensor1", "wrench/", "wrench//compensated", "wrench/a/b", "sigma/wrench/tip"):
        assert not wire.has_sigma(stream), stream


def test_header_offsets_are_the_documented_ones():
    body = vector("wrench")[len(b"wrench/sensor1\0") :]
    assert body[0:2] == b"\x46\x54" and body[2] == 1 and body[3] == 1
    assert int.from_bytes(body[4:8], "little") == 0x24
    assert int.from_bytes(body[8:16], "little") == 42
    assert int.from_bytes(body[32:34], "little") == 6 and len(body) == 40 + 6 * 8


@given(
    st.text(alphabet="abcdefghijklmnopqrstuvwxyz/0123456789", min_size=1, max_size=30),
    st.integers(0, 2**64 - 1),
    st.integers(0, 2**32 - 1),
    st.lists(st.floats(allow_nan=False), max_size=48),
)
def test_round_trip(topic, seq, flags, values):
    s = wire.decode(wire.encode(topic, wire.KIND_FLUX, seq, 1.5, 2.5, flags, np.array(values)))
    assert (s.topic, s.seq, s.flags) == (topic, seq, flags) and np.array_equal(s.values, values)


@pytest.mark.parametrize(
    "frame",
    [
        b"",
        b"wrench",
        b"wrench\0short",
        vector("wrench")[:-1],
        vector("wrench").replace(b"\x46\x54\x01", b"\x46\x54\x02", 1),
        # the topic is ASCII: a byte past 0x7F raised UnicodeDecodeError (not a
        # WireError), out of Subscriber.receive and the recorder (a SUB to all topics)
        vector("wrench").replace(b"wrench/", b"wrench\xaf", 1),
        vector("wrench").replace(b"wrench/", b"wr\xc3\xa9nch", 1),
    ],
)
def test_malformed_frames_are_refused(frame):
    with pytest.raises(WireError):
        wire.decode(frame)
    with pytest.raises(WireError):
        wire.unpack(frame)
