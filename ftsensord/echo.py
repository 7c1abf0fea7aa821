"""`ftsensord echo`: a stream's samples printed live, one aligned line each under a header."""

from __future__ import annotations

import sys

from ftsensord.client import Subscriber, check_streams
from ftsensord.protocol import wire
from ftsensord.recording.columns import value_columns

#: A wrench's values as printed (N, Nm), and a flux's (uT: the tesla's digits are all leading zeros).
WRENCH_WIDTH, FLUX_WIDTH = 10, 9
_NO_SIGMA = [float("nan")] * 6


def header(sample: wire.Sample) -> str:
    """The columns' names and units, each over its column; ``#`` first, so that tools that
    read numbers (numpy.loadtxt, gnuplot, awk with a test) skip it."""
    if sample.kind == wire.KIND_WRENCH:
        values = [f"{n:>{WRENCH_WIDTH}}" for n in value_columns("wrench/", len(sample.values))]
    else:
        values = [
            f"{n.removesuffix('_T') + '_uT':>{FLUX_WIDTH}}"
            for n in value_columns("flux/", len(sample.values))
        ]
    if sample.kind == wire.KIND_WRENCH:  # its sigma's, column by column (`wire.KIND_SIGMA`)
        values += [f"{'s_' + n:>{WRENCH_WIDTH}}" for n in value_columns("wrench/", 6)]
    return f"#{'seq':>7} {'t_mono_s':>14} {' '.join(values)}  flags"


def line(sample: wire.Sample) -> str:
    if sample.kind == wire.KIND_WRENCH:
        values = " ".join(f"{v:+{WRENCH_WIDTH}.4f}" for v in sample.values)
        sigma = _NO_SIGMA if sample.sigma is None else sample.sigma  # nan: not received
        values += " " + " ".join(f"{v:{WRENCH_WIDTH}.4f}" for v in sigma)
    else:
        values = " ".join(f"{v * 1e6:+{FLUX_WIDTH}.1f}" for v in sample.values)
    return f"{sample.seq:8d} {sample.t_mono:14.6f} {values}  {','.join(wire.flag_names(sample.flags))}"


def echo(stream: str, endpoint: str | None, control: str | None, count: int | None, timeout_s: float) -> int:
    """Print ``stream``'s samples until ``count`` (None: until Ctrl-C); 1 when none comes in ``timeout_s``.
    A stream the daemon does not publish is refused at once (`check_streams`)."""
    check_streams([stream], endpoint, control, timeout_s=min(timeout_s, 1.0))
    n = 0
    with Subscriber(endpoint, [stream]) as sub:
        try:
            while count is None or n < count:
                sample = sub.receive(timeout_s=timeout_s)
                if sample is None:
                    print(f"ftsensord: no sample on {stream} within {timeout_s:g} s", file=sys.stderr)
                    return 1
                if n == 0:
                    print(header(sample))
                print(line(sample), flush=True)
                n += 1
        except KeyboardInterrupt:  # Ctrl-C is how one stops a live echo: its normal end
            print(f"ftsensord: {n} samples", file=sys.stderr)
        if sub.gaps:
            print(f"gaps: {sub.gaps}", file=sys.stderr)
    return 0
