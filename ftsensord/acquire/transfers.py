"""The transfers of one bus, as wide as its adapter takes, and what they cost in Python.

`probe_shapes` asks the adapter what it takes in one ioctl (harmless register reads);
`Transfers` sends SM and RM to many chips in as few ioctls as that allows. The RM of the
chips is planned once (`RMPlan`): its messages are built once and reused every cycle,
whichever of the chips are read and in whichever order, each chip's reply lands in its row
of one shared block, and the block is decoded in one numpy pass
(`chip.block.BlockDecoder`), so a cycle spends little per-chip Python on messages and
decoding, and faults (chips leaving and coming back) build no new plans but at a chip's
reset and return.
"""

from __future__ import annotations

import ctypes
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from smbus2 import i2c_msg

from ftsensord.acquire.bound import Shapes
from ftsensord.acquire.health import ChipResult
from ftsensord.chip import mlx90393 as mlx
from ftsensord.chip.block import BlockDecoder
from ftsensord.chip.driver import MLX90393, bus_error
from ftsensord.chip.i2c import I2C_M_RD, SHAPE_REFUSED, Bus
from ftsensord.errors import ChipError

log = logging.getLogger("ftsensord")

#: One ioctl of an RM plan: the rows it reads and its messages.
Transfer = tuple[list[int], list[i2c_msg]]
#: Orders an RM plan keeps (`RMPlan.reading`): the usual cycle needs one per chip (the chip
#: read back is read last); faults add subsets, forgotten past this.
MAX_ORDERS = 64


@dataclass
class RMRead:
    """One `Transfers.read_block`: the plan whose block holds the replies (converted:
    `BlockDecoder.convert`), the rows read, the chips that failed on the bus, and whether
    it was clean (every row a measurement of X, Y, Z, none saturated, none failed)."""

    plan: RMPlan
    rows: list[int]
    failed: dict[int, ChipError]
    clean: bool


def _rr_tref(chip: MLX90393) -> tuple[i2c_msg, i2c_msg]:
    # RR of TREF: harmless in every mode (refused in burst mode, which changes nothing).
    return chip.messages(bytes([mlx.CMD_RR, mlx.REG_TREF << 2]), 3)


def _accepted(bus: Bus, msgs: list[i2c_msg]) -> bool | None:
    """True: the adapter took the transfer; False: it refused its shape; None: no answer (NACK, I/O)."""
    try:
        bus.i2c_rdwr(*msgs)
    except OSError as exc:
        return False if exc.errno in SHAPE_REFUSED else None
    return True


def probe_shapes(bus: Bus, chips: list[MLX90393], tries: int = 4) -> Shapes | None:
    """What the adapter takes in one ioctl, asked with harmless register reads.

    A chip that answers a plain (write, read) is asked two pairs in one ioctl
    (a read that is not last: i2c-bcm2835 refuses), then with a second chip
    that answers, a write to each and one read (two addresses: i2c-designware
    refuses). EOPNOTSUPP and EINVAL mean "not this shape"; a NACK or I/O error
    says nothing, and the next chip is tried (at most ``tries``). None when no
    chip answered at all.
    """
    answering = [c for c in chips[:tries] if _accepted(bus, list(_rr_tref(c)))]
    if not answering:
        return None
    a = answering[0]
    reads_inside = _accepted(bus, [*_rr_tref(a), *_rr_tref(a)]) is True
    many = False
    for b in answering[1:]:
        took = _accepted(bus, [_rr_tref(a)[0], *_rr_tref(b)])
        if took is not None:
            many = took
            break
    return Shapes(reads_inside=reads_inside, many_addresses=many)


class Transfers:
    """The transfers of one bus as wide as its adapter takes (`Shapes`), learnt by
    `probe_shapes` at start and again after a refusal, so a refused ioctl is paid
    once, not every cycle."""

    def __init__(self, bus: Bus, order: list[MLX90393]):
        self.bus, self.order = bus, order  # order: the reader's chips, which an RM plan's rows follow
        self.shapes = Shapes()  # the narrowest until `learn` has asked
        self.reprobe = True
        self.probe_at = 0  # the cycle of the next probe while none has answered
        self._plans: dict[tuple[int, int], RMPlan] = {}  # per (zyxt, pairs per transfer)

    def learn(self, chips: list[MLX90393], cycle: int) -> None:
        if cycle < self.probe_at:
            return
        found = probe_shapes(self.bus, chips)
        if found is not None:
            self.shapes, self.reprobe = found, False
        else:  # no chip answered: the narrowest meanwhile, asked again in 100 cycles (1 s at 100 Hz)
            self.probe_at = cycle + 100

    def start_all(self, chips: list[MLX90393], zyxt: int) -> dict[int, ChipResult]:
        """SM to ``chips``, each with its status read; the refusals (a chip missing from
        the result started).

        The status is read for every SM, as wide as the adapter takes (on i2c-bcm2835,
        one chip's write and read an ioctl, its read last): the datasheet asks for the
        status of the first SM after power-up or reset "in order to get valid measurement
        data back", and a chip that browned out and came back has reset without the
        driver knowing, so no SM can be known not to be the first. An SM sent as a write
        alone (the 42-a-ioctl batch bcm2835 would take) could return wrong data that
        nothing flags; the emulator does not start it (docs/design/simulator.md).
        """
        started = self.batch(chips, lambda c: c.sm_messages(zyxt), self._decode_sm)
        return {a: ChipResult(a, error=e) for a, e in started.items() if isinstance(e, ChipError)}

    def read_block(self, chips: list[MLX90393], zyxt: int) -> RMRead:
        """RM from ``chips``: as wide transfers as the adapter takes, their replies
        landing in one block that is converted at once (`BlockDecoder.convert`); when a
        transfer of several fails, each of its chips on its own."""
        plan, rows, transfers = self._rm_plan(chips, zyxt)
        failed: dict[int, ChipError] = {}
        alone: list[int] = []
        for members, msgs in transfers:
            if len(members) > 1:
                try:
                    self.bus.i2c_rdwr(*msgs)
                    continue
                except OSError as exc:
                    self.refused(exc)
            alone.extend(members)  # one chip, or which one failed? ask each on its own
        for i in alone:
            write, read = plan.pairs[i]
            try:
                self.bus.i2c_rdwr(write, read)
            except OSError as exc:
                a = plan.decoder.chips[i].address
                failed[a] = bus_error(a, plan.command, exc)
        clean = plan.decoder.convert(plan.block)
        return RMRead(plan, rows, failed, clean and not failed)

    @staticmethod
    def results(read: RMRead) -> dict[int, ChipResult]:
        """A `ChipResult` for each chip of ``read``: its measurement, or why not."""
        plan, rows = read.plan, read.rows
        decoded = plan.decoder.measurements(plan.block, rows)
        chips = [plan.decoder.chips[i] for i in rows]
        if not read.failed and plan.decoder.clean:  # every reply a measurement
            return {chip.address: ChipResult(chip.address, m) for chip, m in zip(chips, decoded)}  # type: ignore[arg-type]
        out = {}
        for chip, m in zip(chips, decoded):
            a = chip.address
            e = read.failed.get(a)
            if e is not None:
                out[a] = ChipResult(a, error=e)
            elif isinstance(m, ChipError):
                out[a] = ChipResult(a, error=m)
            else:
                out[a] = ChipResult(a, m)
        return out

    def _rm_plan(self, chips: list[MLX90393], zyxt: int) -> tuple[RMPlan, list[int], list[Transfer]]:
        """The RM plan at the learnt shapes that holds ``chips``, their rows in it and
        the transfers that read them in their order.

        One plan per (zyxt, shapes), reused whichever of its chips are read, so a fault
        costs no plan; rebuilt when one of ``chips`` is not in it (a chip back from a
        reset) or one of its chips' settings changed (a reset clears them): one plan's
        memory, whatever the faults. Its rows follow ``order`` (the reader's chips), so
        with every chip in it row i is the reader's chip i, whatever order they are read in."""
        per = self.shapes.pairs_per_transfer
        plan = self._plans.get((zyxt, per))
        if plan is not None and plan.decoder.valid_for(plan.decoder.chips):
            got = plan.reading(chips)
            if got is not None:
                return plan, *got
        members = set(chips)
        plan = self._plans[zyxt, per] = RMPlan([c for c in self.order if c in members] or chips, zyxt, per)
        got = plan.reading(chips)
        assert got is not None  # built to hold them
        return plan, *got

    def refused(self, exc: OSError) -> None:
        """A transfer failed: a refused shape (not a NACK) means the adapter takes less
        than was learnt; ask again at the next cycle, the narrowest shape until then."""
        if exc.errno in SHAPE_REFUSED:
            log.warning("the I2C adapter refused a transfer (%s): learning again what it takes", exc)
            self.shapes, self.reprobe = Shapes(), True

    @staticmethod
    def _decode_sm(chip: MLX90393, reply: bytes) -> None:
        status = mlx.status_of(reply[0])
        if status.error and status.sm_mode:
            return  # it got the SM before its batch failed, and is converting
        chip.decode_sm(reply)

    def batch(self, chips: list[MLX90393], messages: Callable, decode: Callable) -> dict[int, Any]:
        """One transfer per as many chips as the adapter takes (`Shapes`); when one
        of several fails, each of its chips on its own.

        Returns per address what ``decode(chip, reply)`` gave, or the `ChipError`.
        """
        out: dict[int, Any] = {}
        alone: list[MLX90393] = []
        per = self.shapes.pairs_per_transfer
        for k in range(0, len(chips), per):
            group = chips[k : k + per]
            if len(group) == 1:
                alone.extend(group)  # one chip: its own transfer, its own error
                continue
            pairs = [messages(c) for c in group]
            try:
                self.bus.i2c_rdwr(*[m for pair in pairs for m in pair])
            except OSError as exc:
                self.refused(exc)
                alone.extend(group)  # which one failed? ask each on its own
                continue
            for chip, (_, read) in zip(group, pairs):
                out[chip.address] = _decoded(decode, chip, read.buf[: read.len])
        for chip in alone:
            write, read = messages(chip)
            try:
                out[chip.address] = _decoded(decode, chip, chip.transfer(bytes(write), len(read)))
            except ChipError as exc:
                out[chip.address] = exc
        return out


class RMPlan:
    """The RM of a list of chips, built once: each chip's read message points into its
    row of one (n, L) block (``block``, uint8), so a cycle's replies are decoded in one
    pass by ``decoder``; `reading` groups the (write, read) pairs of the rows read,
    ``per`` chips an ioctl."""

    def __init__(self, chips: list[MLX90393], zyxt: int, per: int):
        self.per = per
        self.row = {c: i for i, c in enumerate(chips)}  # keyed by the object: MLX90393 compares by identity
        self.decoder = BlockDecoder(chips, zyxt)
        L = self.decoder.reply_len
        self.command = bytes([mlx.CMD_RM | zyxt])
        self.block = np.zeros((len(chips), L), dtype=np.uint8)
        base = self.block.ctypes.data
        self.pairs = [
            (
                c.messages(self.command, L)[0],
                i2c_msg(
                    addr=c.address,
                    flags=I2C_M_RD,
                    len=L,
                    buf=ctypes.cast(base + i * L, ctypes.POINTER(ctypes.c_char)),
                ),
            )
            for i, c in enumerate(chips)
        ]
        self._orders: dict[tuple[MLX90393, ...], tuple[list[int], list[Transfer]]] = {}

    def reading(self, chips: list[MLX90393]) -> tuple[list[int], list[Transfer]] | None:
        """The rows of ``chips`` and the transfers that read them in their order; None
        when one is not in this plan. Kept per order: a read-back's chip read last gives
        one order per chip, each worked out once."""
        key = tuple(chips)
        got = self._orders.get(key)
        if got is None:
            get = self.row.get
            rows = [get(c) for c in chips]
            if None in rows:
                return None
            if len(self._orders) >= MAX_ORDERS:  # faults make subsets: forget rather than grow
                self._orders.clear()
            known = cast("list[int]", rows)  # (no None among them: returned above)
            got = self._orders[key] = (known, self._grouped(known))
        return got

    def _grouped(self, rows: list[int]) -> list[Transfer]:
        per, pairs = self.per, self.pairs
        return [
            (rows[k : k + per], [m for i in rows[k : k + per] for m in pairs[i]])
            for k in range(0, len(rows), per)
        ]


def _decoded(decode: Callable, chip: MLX90393, reply: bytes) -> Any:
    try:
        return decode(chip, reply)
    except ChipError as exc:
        return exc
