"""Live plots of the daemon's streams: forces (N), moments (Nm) and flags, scrolling.

One column per stream. A wrench stream has three panels: fx fy fz (N), mx my mz
(Nm) and its flags (one row per flag, a mark at each sample that carries it); a
flux stream has each chip's field magnitude and z component (mT) and its flags.
Time runs along x in seconds before the newest sample, on the daemon's
monotonic clock (``t_mono``), so the picture scrolls as samples come.

`snapshot` collects some seconds and writes a PNG with the Agg canvas (no
display needed: the tests use it); `live` opens a window and redraws ten times
a second. Needs matplotlib (the ``plot`` extra).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ftsensord.client import Subscriber
from ftsensord.errors import ConfigError
from ftsensord.protocol import wire

#: Redraw period of the live plot, s: smooth to the eye, light on the CPU.
REFRESH_S = 0.1
#: Highest rate a history is sized for, Hz (ring buffers: memory stays flat).
MAX_RATE_HZ = 1000.0
FLAG_BITS = sorted(wire.FLAG_NAMES)
AXES = "xyz"


#: matplotlib's backends that draw no window: what it falls back to with no display.
NON_INTERACTIVE = frozenset({"agg", "cairo", "pdf", "pgf", "ps", "svg", "template"})


def require_matplotlib() -> None:
    """Before any data is collected: matplotlib is there, or the command that installs it."""
    try:
        import matplotlib  # noqa: F401
    except ImportError as exc:
        raise ConfigError(
            "plot needs matplotlib, the 'plot' extra: pip install 'ftsensord[plot]' "
            "(from a checkout: .venv/bin/pip install '.[plot]')"
        ) from exc


def require_display() -> None:
    """A live window needs a display: over ssh matplotlib falls back to a backend that draws
    none, and the window would silently never open."""
    import matplotlib.pyplot as plt

    backend = plt.get_backend().lower()
    if backend in NON_INTERACTIVE:
        raise ConfigError(
            f"no display for a live plot (matplotlib's backend is {backend!r}: DISPLAY and "
            "WAYLAND_DISPLAY unset?). Without one: `ftsensord plot STREAM --png plot.png "
            "[--seconds 5]` writes a snapshot; or log in with `ssh -X`"
        )


@dataclass
class History:
    """The last ``window_s`` of one stream, in ring buffers."""

    window_s: float
    t: deque = field(default_factory=deque)
    values: deque = field(default_factory=deque)
    flags: deque = field(default_factory=deque)
    kind: int = wire.KIND_WRENCH
    samples: int = 0
    missed: int = 0
    last_seq: int | None = None

    def __post_init__(self) -> None:
        n = int(self.window_s * MAX_RATE_HZ) + 1
        self.t, self.values, self.flags = deque(maxlen=n), deque(maxlen=n), deque(maxlen=n)

    def add(self, sample: wire.Sample) -> None:
        if self.last_seq is not None and sample.seq > self.last_seq + 1:
            self.missed += sample.seq - self.last_seq - 1
        self.last_seq, self.kind = sample.seq, sample.kind
        self.t.append(sample.t_mono)
        self.values.append(sample.values)
        self.flags.append(sample.flags)
        self.samples += 1

    def arrays(self, now: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(time before ``now`` in s, values, flags) of the samples within the window."""
        t = np.fromiter(self.t, float, len(self.t))
        keep = t >= now - self.window_s
        values = np.array(self.values, dtype=float).reshape(len(t), -1)[keep] if len(t) else np.zeros((0, 6))
        return t[keep] - now, values, np.fromiter(self.flags, np.int64, len(t))[keep]


class StreamPlot:
    """The panels of one stream in a figure column, and how to redraw them."""

    def __init__(self, fig: Any, grid: Any, column: int, stream: str, kind: int):
        self.stream, self.kind = stream, kind
        top, mid, bottom = (fig.add_subplot(grid[row, column]) for row in range(3))
        self.axes = [top, mid, bottom]
        if kind == wire.KIND_WRENCH:
            self.lines = [top.plot([], [], label=f"f{a}")[0] for a in AXES]
            self.lines += [mid.plot([], [], label=f"m{a}")[0] for a in AXES]
            top.set_ylabel("force (N)")
            mid.set_ylabel("moment (Nm)")
        else:  # flux: chips are known at the first sample; lines are made then
            self.lines = []
            top.set_ylabel("|B| per chip (mT)")
            mid.set_ylabel("B_z per chip (mT)")
        top.set_title(stream)
        self.flag_lines = [
            bottom.plot([], [], "|", markersize=8, label=wire.FLAG_NAMES[bit])[0] for bit in FLAG_BITS
        ]
        bottom.set_yticks(range(len(FLAG_BITS)), [wire.FLAG_NAMES[b] for b in FLAG_BITS], fontsize=7)
        bottom.set_ylim(-0.7, len(FLAG_BITS) - 0.3)
        bottom.set_ylabel("flags")
        bottom.set_xlabel("time (s), 0: newest sample")
        for ax in self.axes:
            ax.grid(True, alpha=0.3)

    def draw(self, history: History, now: float) -> None:
        t, values, flags = history.arrays(now)
        if self.kind == wire.KIND_FLUX and not self.lines and values.shape[1]:
            chips = values.shape[1] // 3
            self.lines = [self.axes[0].plot([], [], lw=0.8, label=f"chip {i}")[0] for i in range(chips)]
            self.lines += [self.axes[1].plot([], [], lw=0.8)[0] for _ in range(chips)]
        if self.kind == wire.KIND_WRENCH:
            series = [values[:, i] for i in range(6)]
        else:
            b = values.reshape(len(t), -1, 3) * 1e3  # T to mT
            series = list(np.linalg.norm(b, axis=2).T) + list(b[:, :, 2].T)
        for line, y in zip(self.lines, series):
            line.set_data(t, y)
        for line, bit, row in zip(self.flag_lines, FLAG_BITS, range(len(FLAG_BITS))):
            line.set_data(t, np.where(flags & bit, row, np.nan))
        for ax in self.axes[:2]:
            ax.relim()
            ax.autoscale_view(scalex=False)
            if ax.get_legend() is None and any(not ln.get_label().startswith("_") for ln in ax.lines):
                ax.legend(loc="upper left", fontsize=7, ncol=len(ax.lines))
        self.axes[0].set_title(
            f"{self.stream}: {history.samples} samples, {history.missed} missed", fontsize=9
        )
        for ax in self.axes:
            ax.set_xlim(-history.window_s, 0)


def make_figure(streams: list[str], kinds: dict[str, int], fig: Any = None) -> tuple[Any, list[StreamPlot]]:
    """A figure with a column per stream (a new Agg-backed Figure unless ``fig`` is given)."""
    if fig is None:
        from matplotlib.figure import Figure

        fig = Figure(figsize=(5.5 * len(streams), 7.5), layout="constrained")
    grid = fig.add_gridspec(3, len(streams), height_ratios=[3, 3, 2])
    plots = [
        StreamPlot(
            fig, grid, i, s, kinds.get(s, wire.KIND_WRENCH if s.startswith("wrench/") else wire.KIND_FLUX)
        )
        for i, s in enumerate(streams)
    ]
    return fig, plots


def draw(plots: list[StreamPlot], histories: dict[str, History]) -> None:
    newest = [h.t[-1] for h in histories.values() if h.t]
    now = max(newest) if newest else 0.0
    for p in plots:
        p.draw(histories[p.stream], now)


def take(sub: Subscriber, histories: dict[str, History], limit: int = 10_000) -> int:
    """Add what is queued (without waiting) to the histories; return how many."""
    n = 0
    while n < limit:
        sample = sub.receive(timeout_s=0)
        if sample is None:
            break
        if sample.topic in histories:
            histories[sample.topic].add(sample)
        n += 1
    return n


@dataclass
class Snapshot:
    figure: Any
    histories: dict[str, History]


def snapshot(
    streams: list[str],
    seconds: float,
    png: str | Path | None = None,
    *,
    endpoint: str | None = None,
    timeout_s: float = 3.0,
) -> Snapshot:
    """Collect ``seconds`` of the streams, draw them and write ``png`` (if given); headless."""
    require_matplotlib()
    histories = {s: History(seconds) for s in streams}
    with Subscriber(endpoint, streams) as sub:
        start = last = time.monotonic()
        while time.monotonic() - start < seconds and time.monotonic() - last < timeout_s:
            sample = sub.receive(timeout_s=min(REFRESH_S, seconds))
            if sample is not None and sample.topic in histories:
                histories[sample.topic].add(sample)
                last = time.monotonic()
    fig, plots = make_figure(streams, {s: h.kind for s, h in histories.items()})
    draw(plots, histories)
    if png is not None:
        fig.savefig(png, dpi=100)
    return Snapshot(fig, histories)


def live(streams: list[str], window_s: float, *, endpoint: str | None = None) -> int:
    """A window that scrolls until it is closed or Ctrl-C; returns the exit status."""
    require_matplotlib()
    require_display()
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation

    histories = {s: History(window_s) for s in streams}
    with Subscriber(endpoint, streams) as sub:
        fig = plt.figure(figsize=(5.5 * len(streams), 7.5), layout="constrained")
        if fig.canvas.manager is not None:
            fig.canvas.manager.set_window_title("ftsensord plot " + " ".join(streams))
        plots: list[StreamPlot] = []

        def update(_frame: int) -> list:
            take(sub, histories)
            if not plots and all(h.t for h in histories.values()):  # kinds known: lay the panels out
                plots.extend(make_figure(streams, {s: h.kind for s, h in histories.items()}, fig)[1])
            if plots:
                draw(plots, histories)
            return []

        anim = FuncAnimation(fig, update, interval=REFRESH_S * 1000, cache_frame_data=False)
        try:
            plt.show()
        except KeyboardInterrupt:
            pass
        del anim
    return 0
