"""One cycle's results, by chip address (`Readings`): what `Reader.read` returns.

In the usual cycle every chip's reply is a clean measurement (read, no error, none
saturated, no temperature asked); the fields then stay in the one (n, 3) array the block
decoder made, and a chip's `ChipResult` is built only when someone asks for it. Whoever
wants the whole cycle at once (a sensor's stacked flux) takes rows of that array.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from ftsensord.acquire.health import ChipResult
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.driver import MLX90393, Measurement

if TYPE_CHECKING:
    from ftsensord.acquire.transfers import RMRead

_XYZ = mlx.zyxt_items(mlx.ZYXT_XYZ)


class Readings(Mapping[int, ChipResult]):
    """Each chip's `ChipResult` of one cycle, by address, in the reader's chip order.

    ``field`` (n, 3, T, each chip's own frame {S_i}, rows in ``addresses``' order) is
    set only when the cycle was `clean`: every chip read, each reply a measurement of
    X, Y and Z, none saturated. ``words`` and ``statuses`` are then the replies' words
    and status bytes, row by row. Otherwise the results are given (``results``).
    """

    __slots__ = ("addresses", "index", "field", "words", "statuses", "_made")

    def __init__(
        self,
        addresses: tuple[int, ...],
        index: dict[int, int],
        *,
        results: dict[int, ChipResult] | None = None,
        field: np.ndarray | None = None,
        words: Sequence[tuple[int, ...]] | None = None,
        statuses: bytes | list[int] | None = None,
    ):
        self.addresses, self.index = addresses, index  # index: address -> row, shared by every cycle
        self.field, self.words, self.statuses = field, words, statuses
        self._made: dict[int, ChipResult] = {} if results is None else results

    @classmethod
    def of_block(
        cls, rm: RMRead, chips: list[MLX90393], addresses: tuple[int, ...], index: dict[int, int]
    ) -> Readings | None:
        """The cycle as arrays when its RM read every one of ``chips`` cleanly
        (`RMRead.clean`) and its block's rows are those chips in order; else None."""
        decoder = rm.plan.decoder
        if not rm.clean or len(rm.rows) != len(chips) or decoder.chips != chips:
            return None
        return cls(
            addresses,
            index,
            field=decoder.field,
            words=decoder.xyz_words(),
            statuses=decoder.replies[:: decoder.reply_len],
        )

    @classmethod
    def of_field(cls, addresses: tuple[int, ...], field: np.ndarray) -> Readings:
        """A clean cycle of a known ``field`` (T, every channel: n x 3, or flat, in
        ``addresses``' order), words and statuses zero: a flux replayed or computed, fed to
        the pipelines as the reader's would be."""
        n = len(addresses)
        return cls(
            addresses,
            {a: i for i, a in enumerate(addresses)},
            field=field.reshape(n, 3),
            words=[(0, 0, 0)] * n,
            statuses=bytes(n),
        )

    @property
    def clean(self) -> bool:
        """Every chip read, each a measurement of X, Y, Z, none saturated: ``field`` holds them all."""
        return self.field is not None

    def fail(self, address: int, result: ChipResult) -> None:
        """``address``'s result is ``result`` after all (its words were stuck): the cycle is no longer clean."""
        if self.field is not None:
            self._made = {a: self[a] for a in self.addresses}
            self.field = None
        self._made[address] = result

    def rows(self, addresses: tuple[int, ...]) -> slice | list[int]:
        """The rows of ``addresses``, a slice where they are consecutive (a view, no copy)."""
        return _rows(self.addresses, addresses)

    def __getitem__(self, address: int) -> ChipResult:
        r = self._made.get(address)
        if r is None:
            if self.field is None or address not in self.index:
                raise KeyError(address)
            i = self.index[address]
            assert self.words is not None and self.statuses is not None  # set with the field
            m = Measurement(
                mlx.STATUSES[self.statuses[i]],
                self.field[i],
                np.zeros(3, dtype=bool),
                None,
                self.words[i],
                _XYZ,
                False,
            )
            r = self._made[address] = ChipResult(address, m)
        return r

    def __iter__(self) -> Iterator[int]:
        return iter(self.addresses)

    def __len__(self) -> int:
        return len(self.addresses)


@functools.lru_cache(maxsize=16)
def _rows(order: tuple[int, ...], addresses: tuple[int, ...]) -> slice | list[int]:
    """`Readings.rows`, worked out once per sensor rather than every cycle."""
    rows = [order.index(a) for a in addresses]
    if rows == list(range(rows[0], rows[0] + len(rows))):
        return slice(rows[0], rows[0] + len(rows))
    return rows
