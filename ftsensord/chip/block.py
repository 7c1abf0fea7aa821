"""RM replies of many chips decoded together (`BlockDecoder`): the reader's usual cycle.

Split from ``driver.py``, whose per-chip decoder (`MLX90393.decode_measurement`) stays
the reference: a reply the block decoder does not take as it comes (an error, a wrong
D1:D0) goes there, so every error is raised by the same code.
"""

from __future__ import annotations

import functools
import struct
from typing import cast

import numpy as np

from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393, Measurement
from ftsensord.errors import ChipError, ChipProtocolError

#: An RM reply of X, Y, Z: the status byte, then three big-endian words.
_XYZ_REPLY = struct.Struct(">x3H")


class BlockDecoder:
    """RM replies of many chips decoded together: one numpy pass over an (n, L) block.

    Built for one list of chips and one zyxt; per chip and axis the word's coding
    and tesla per count are fixed by `MLX90393.configure`, so the decoder holds them
    as arrays and is valid while every chip keeps the settings it was built with
    (`valid_for`). A reply whose status byte has ERROR set, or whose D1:D0 does not
    announce the words asked for, is left to `MLX90393.decode_measurement` (the
    same error, raised the same way); the rest need no per-chip decoding.
    """

    def __init__(self, chips: list[MLX90393], zyxt: int):
        self.chips, self.zyxt = chips, zyxt
        self.items = mlx.zyxt_items(zyxt)
        self.reply_len = 1 + 2 * len(self.items)
        self.settings = [c.settings for c in chips]
        self.changes = MLX90393.settings_changes
        if any(s is None for s in self.settings):
            raise ChipProtocolError(chips[0].address, "a block decoder built before configure()")
        n = len(chips)
        self.columns = [self.items.index(a) for a in "xyz" if a in self.items]
        self.axes = [i for i, a in enumerate("xyz") if a in self.items]
        self.t_column = self.items.index("t") if "t" in self.items else None
        # D1:D0 as it must read for these items: 2 * D + 2 data bytes (`Status.data_bytes`).
        self.d_expected = len(self.items) - 1
        fmts = [[c._decoding[a][0] for a in self.axes] for c in chips]
        self.signed = np.array([[f.signed for f in row] for row in fmts], dtype=bool).reshape(n, -1)
        self.zero = np.array([[f.zero for f in row] for row in fmts], dtype=np.int32).reshape(n, -1)
        self.span = np.array([[f.span for f in row] for row in fmts], dtype=np.int32).reshape(n, -1)
        self.scale = np.array([[c._decoding[a][1] for a in self.axes] for c in chips]).reshape(n, -1)
        self.bad_status = _bad_status(self.d_expected)
        # The status bytes a reply may carry to be taken as it comes (`convert`'s one translate).
        self.good_status = bytes(np.flatnonzero(~self.bad_status).astype(np.uint8))
        self.xyz_only = self.columns == [0, 1, 2] and self.axes == [0, 1, 2]
        self.unsigned = not self.signed.any()
        self.clean = False  # the last `decode` found no error and no temperature: every entry a Measurement
        # The last `convert`'s arrays (see there); empty until the first.
        empty: np.ndarray = np.empty(0)
        self.status = self.words = self.field = self.saturated = empty
        self.bad: np.ndarray | None = np.empty(0, dtype=bool)
        self.replies = b""  # the block's bytes, when the last `convert` was of X, Y, Z alone
        # Saturated where |counts| reaches the span or the Hall limit: the least |counts|
        # whose tesla (counts x scale, as decoded) reach it, found once per chip and axis.
        self.saturates_at = np.minimum(
            self.span,
            np.array([[_hall_limit_counts(s) for s in row] for row in self.scale], dtype=np.int64).reshape(
                n, -1
            ),
        )

    def xyz_words(self) -> list[tuple[int, int, int]]:
        """Each row's X, Y, Z words as read (the last `convert`'s block, of X, Y, Z alone)."""
        return list(_XYZ_REPLY.iter_unpack(self.replies))

    def valid_for(self, chips: list[MLX90393]) -> bool:
        """True while ``chips`` are the ones built for, with the same settings."""
        if self.changes == MLX90393.settings_changes and chips == self.chips:
            return True  # no chip's settings changed since: no need to ask each
        valid = len(chips) == len(self.chips) and all(
            c is d and c.settings is s for c, d, s in zip(chips, self.chips, self.settings)
        )
        if valid:
            self.changes = MLX90393.settings_changes
        return valid

    def convert(self, block: np.ndarray) -> bool:
        """One numpy pass over ``block`` ((n, L) uint8: each row one chip's reply, status
        byte first), kept in ``field`` (n, 3, T, NaN where not read), ``saturated``,
        ``words`` (uint16, a view of ``block``), ``status`` and ``bad`` (replies left to
        the per-chip decoder). True when every row is a measurement of X, Y and Z, none
        saturated: then ``field`` is all anyone needs of this cycle."""
        self.status = status = block[:, 0]
        # The words big-endian after the status byte: a view, no arithmetic (uint16, as read).
        self.words = words = block[:, 1:].view(">u2")
        if self.xyz_only and self.unsigned:  # the usual RM: X, Y, Z and nothing else, offset words
            # The replies as bytes: their status bytes checked and their words read as Python
            # ints (`xyz_words`) each in one call, where numpy takes two or more.
            self.replies = replies = block.tobytes()
            self.bad = None  # (worked out by `measurements` when it is asked)
            counts = words - self.zero  # int32, the zero's type: no uint16 wrap below the zero
            self.field = counts * self.scale
            self.saturated = saturated = np.abs(counts) >= self.saturates_at
            return not replies[:: self.reply_len].translate(None, self.good_status) and not saturated.any()
        self.bad = self.bad_status[status]
        n = len(self.chips)
        self.field = field = np.full((n, 3), np.nan)
        self.saturated = saturated = np.zeros((n, 3), dtype=bool)
        if self.columns:
            w = words[:, self.columns].astype(np.int32)
            counts = np.where(self.signed, w - ((w & 0x8000) << 1), w - self.zero)
            field[:, self.axes] = counts * self.scale
            saturated[:, self.axes] = np.abs(counts) >= self.saturates_at
        return False

    def decode(self, block: np.ndarray, rows: list[int] | None = None) -> list[Measurement | ChipError]:
        """Per chip, in order: its `Measurement`, or the `ChipError` its reply gives.

        ``block`` as `convert` takes it. ``rows``: the rows read this time, in the order
        wanted (default: all, in order); the others hold older replies, decoded with the
        rest (one numpy pass costs the same) but never looked at.
        """
        self.convert(block)
        return self.measurements(block, rows)

    def measurements(self, block: np.ndarray, rows: list[int] | None = None) -> list[Measurement | ChipError]:
        """`decode`'s answer from the arrays the last `convert` of ``block`` left."""
        saturated, field, words = self.saturated, self.field, self.words
        bad = self.bad if self.bad is not None else self.bad_status[self.status]
        # Per row, as Python objects, each in one call (row views, lists): no per-chip numpy.
        sat_any = (
            cast("list[bool]", saturated.any(axis=1).tolist())
            if saturated.any()
            else [False] * len(self.chips)
        )
        raw = cast("list[tuple[int, ...]]", list(map(tuple, words.tolist())))
        statuses = self.status.tolist()
        fields, sats = list(field), list(saturated)
        items, status_of = self.items, mlx.STATUSES.__getitem__
        order = range(len(self.chips)) if rows is None else rows
        bad_rows = cast("list[bool]", bad.tolist()) if bad.any() else None
        self.clean = self.t_column is None and (bad_rows is None or not any(bad_rows[i] for i in order))
        if self.clean:  # no error, no temperature
            return [
                Measurement(status_of(statuses[i]), fields[i], sats[i], None, raw[i], items, sat_any[i])
                for i in order
            ]
        t_column = self.t_column
        out: list[Measurement | ChipError] = []
        for i in order:
            chip = self.chips[i]
            if bad_rows is not None and bad_rows[i]:
                try:  # the per-chip decoder raises the error it always raised
                    out.append(chip.decode_measurement(bytes(block[i]), self.zyxt))
                except ChipError as exc:
                    out.append(exc)
                continue
            row = raw[i]
            temp = None if t_column is None else mlx.raw_to_celsius(row[t_column], chip.tref)
            out.append(Measurement(status_of(statuses[i]), fields[i], sats[i], temp, row, items, sat_any[i]))
        return out


@functools.lru_cache(maxsize=4)
def _bad_status(d_expected: int) -> np.ndarray:
    """Per status byte: True where it leaves the reply to the per-chip decoder (ERROR set,
    or D1:D0 other than ``d_expected``). Read-only, shared by every decoder."""
    table = np.array(
        [(b & mlx.STATUS_ERROR) != 0 or (b & mlx.STATUS_D_MASK) != d_expected for b in range(256)]
    )
    table.setflags(write=False)
    return table


def _hall_limit_counts(tesla_per_count: float) -> int:
    """The least counts c >= 0 with c x ``tesla_per_count`` >= `mlx.HALL_SATURATION_FLAG_T`
    in floating point, as the decoders compute it (the test is monotone in c)."""
    c = int(mlx.HALL_SATURATION_FLAG_T / tesla_per_count)
    while c > 0 and (c - 1) * tesla_per_count >= mlx.HALL_SATURATION_FLAG_T:
        c -= 1
    while c * tesla_per_count < mlx.HALL_SATURATION_FLAG_T:
        c += 1
    return c
