"""The nonlinear estimator's solve compiled: `_nlsolve.c` and `_nlmodel.c` (plain C, no Python headers)
built at install into a shared library beside this module (setup.py, optional: absent
where no C compiler was), loaded through ctypes and called with pointers to float64
arrays kept here. ctypes' plain calls write no executable memory (a systemd unit's
MemoryDenyWriteExecute holds); no callbacks are made.

`solver_for` chooses: "numpy" the reference (`NonlinearEstimator._solve`), "compiled"
this one (an error when it is absent), "auto" this one when it loads. The fit is the
same: the same steps, tolerances (nonlinear.py's, handed in every call) and decisions;
the end points differ only by round-off's path (tests/test_nonlinear_compiled.py).
"""

from __future__ import annotations

import ctypes
import importlib.machinery
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np

from ftsensord.errors import ConfigError
from ftsensord.model import se3

__all__ = ["SOLVERS", "CompiledSolve", "attach", "compile_library", "library_path", "load", "solver_for"]

#: The C sources (setup.py builds the same), with _nlsolve.h beside them.
SOURCES = (Path(__file__).with_name("_nlsolve.c"), Path(__file__).with_name("_nlmodel.c"))
STEM = "_nlsolve"
SOLVERS = ("auto", "numpy", "compiled")
NMAX = 16  # _nlsolve.h's NMAX: chips a sensor may have
#: _nlsolve.h's NL_TUNABLES, by name, in the order nl_model.tun holds them (checked at load).
TUNABLES = (
    "MAX_STEP_M",
    "MAX_STEP_RAD",
    "STEP_TOL",
    "STEP_TOL_RAD",
    "CONTRACTION",
    "REUSE_M",
    "REUSE_TRACE",
    "REUSE_T",
    "MAX_RESIDUAL_T",
    "BACKGROUND_LIMIT_T",
    "PRIOR_WEIGHT",
    "LINEAR_STEP_T",
    "UNDAMPED",
    "SMALL_ANGLE",
    "NEAR_PI",
    "MAX_ITERATIONS",
)
#: _nlsolve.h's nl_model, field by field, in doubles (checked at load against nl_model_offset).
LAYOUT = {
    "head": 4,
    "chip_p": 3 * NMAX,
    "magnet_p": 3 * NMAX,
    "m": 3 * NMAX,
    "axis": 3 * NMAX,
    "half_q": NMAX,
    "inv_m": NMAX,
    "resp": 9 * NMAX,
    "offset": 3 * NMAX,
    "K": 36,
    "zero_twist": 6,
    "plausible": 6,
    "tun": 16,
}
_AT = {name: sum(list(LAYOUT.values())[:i]) for i, name in enumerate(LAYOUT)}
_DOUBLES = sum(LAYOUT.values())
_P = ctypes.c_void_p


def library_path(folder: Path | None = None) -> Path | None:
    """The built library in ``folder`` (default beside this module), or None."""
    folder = Path(__file__).parent if folder is None else folder
    for suffix in (*importlib.machinery.EXTENSION_SUFFIXES, ".so"):
        if (folder / (STEM + suffix)).is_file():
            return folder / (STEM + suffix)
    return None


def load(path: Path | None = None) -> ctypes.CDLL | None:
    """The library at ``path`` (default `library_path()`), its calls typed; None when
    there is none or it is not this source's (a call missing, or its model layout differs)."""
    path = library_path() if path is None else path
    if path is None:
        return None
    try:
        lib = ctypes.CDLL(str(path))
        lib.nl_state_bytes.restype = lib.nl_model_doubles.restype = ctypes.c_size_t
        lib.nl_solve.argtypes = [_P, _P, _P, _P, _P, _P, ctypes.c_int, ctypes.c_double, ctypes.c_int, _P]
        lib.nl_solve.restype = ctypes.c_int
        lib.nl_continued.argtypes = [_P, _P, ctypes.c_double, ctypes.c_double, _P, _P]
        lib.nl_continued.restype = None
        lib.nl_kept_jacobian.argtypes = [_P, _P, _P, _P, _P]
        lib.nl_kept_jacobian.restype = ctypes.c_long
        lib.nl_chord_gains.argtypes = [_P, _P, _P, _P]
        lib.nl_chord_gains.restype = ctypes.c_int
        lib.nl_model_offset.argtypes = lib.nl_tunable_index.argtypes = [ctypes.c_char_p]
        lib.nl_model_offset.restype = lib.nl_tunable_index.restype = ctypes.c_long
    except (OSError, AttributeError):  # not loadable, or built from another source (a call missing)
        return None
    return lib if _layout_matches(lib) else None


def _layout_matches(lib: ctypes.CDLL) -> bool:
    """Whether the library's nl_model is `LAYOUT`, field by field, and its tunables are
    `TUNABLES`, name by name, in order: a library built from another source is not used."""
    return (
        lib.nl_model_doubles() == _DOUBLES
        and all(lib.nl_model_offset(name.encode()) == at for name, at in _AT.items())
        and all(lib.nl_tunable_index(name.encode()) == i for i, name in enumerate(TUNABLES))
        and lib.nl_tunable_index(b"") == -1
        and LAYOUT["tun"] == len(TUNABLES)
    )


def compiler() -> str | None:
    """A C compiler on PATH (cc, else gcc), or None."""
    return shutil.which("cc") or shutil.which("gcc")


def compile_library(folder: Path, cc: str | None = None) -> Path:
    """Build `SOURCES` into ``folder`` with warnings as errors, for tests and benchmarks
    run from a source tree (an install builds it beside this module: setup.py)."""
    out = Path(folder) / (STEM + ".so")
    cmd = [
        cc or compiler() or "cc",
        "-std=c99",
        "-O2",
        "-Wall",
        "-Wextra",
        "-Werror",
        "-shared",
        "-fPIC",
        "-o",
        str(out),
        *map(str, SOURCES),
        "-lm",
    ]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    return out


def solver_for(solver: str, path: Path | None = None, chips: int = 8) -> CompiledSolve | None:
    """The compiled solve for ``solver`` ("auto", "numpy" or "compiled") of a sensor with
    ``chips`` chips, None for numpy's (always for "numpy"; for "auto" when the library is
    absent or the sensor has more chips than it takes)."""
    if solver not in SOLVERS:
        raise ConfigError(f"solver: {solver!r} is not one of {', '.join(SOLVERS)}")
    if solver == "numpy":
        return None
    lib = load(path) if chips <= NMAX else None
    if lib is None and solver == "compiled":
        why = (
            f"{chips} chips, at most {NMAX}"
            if chips > NMAX
            else f"no compiled solver at "
            f"{path or Path(__file__).parent} (built at install where a C compiler is present)"
        )
        raise ConfigError(f"solver 'compiled': {why}; 'auto' falls back to numpy's")
    return None if lib is None else CompiledSolve(lib)


def attach(estimator: Any, solver: str, path: Path | None = None) -> None:
    """Make ``estimator`` (a `NonlinearEstimator`: not imported, it imports this module) solve
    with ``solver``, the library at ``path`` (default beside this module): tests and
    benchmarks set one they built."""
    estimator.compiled = solver_for(solver, path, estimator.model.geometry.n_chips)


class CompiledSolve:
    """One estimator's compiled solve: its state (kept Jacobians, the last fit's flux) and
    the model's constants packed as _nlsolve.c reads them, repacked when they change."""

    def __init__(self, lib: ctypes.CDLL):
        self.lib = lib
        self._state = np.zeros(lib.nl_state_bytes(), np.uint8)
        self._model = np.zeros(_DOUBLES)
        self._T, self._u, self._b = np.empty(16), np.empty(3), np.empty(3 * NMAX)
        self._usable, self._out, self._sizes = np.empty(NMAX), np.empty(9), np.empty(2)
        self._sizes_at = self._sizes.ctypes.data
        self._J = np.empty((3 * NMAX, 9))  # `jacobian`'s and `chord_gains`' J (PMAX columns)
        self._J_at = self._J.ctypes.data
        self._G = np.empty((9, 3 * NMAX))  # `chord_gains`', as nl_chord_gains writes it
        self._G_at = self._G.ctypes.data
        self._addresses = [
            a.ctypes.data for a in (self._model, self._state, self._b, self._usable, self._T, self._u)
        ]
        self._packed: tuple = ()  # what the model was packed from
        #: The last converged fit's pose, field and kind: a start from those two objects
        #: takes the flux kept in the state (as `NonlinearEstimator._end`).
        self._end: tuple[np.ndarray, np.ndarray, bool] | None = None

    def solve(
        self,
        est: Any,
        b: np.ndarray,
        usable: np.ndarray | None,
        start: np.ndarray,
        u0: np.ndarray,
        background: bool,
        damping: float,
        constants: dict[str, Any],
    ) -> tuple[np.ndarray, np.ndarray, bool, int, float, np.ndarray]:
        """`NonlinearEstimator._solve` for ``est``: (xi, T, converged, iterations, rms,
        background field), ``est.pose`` and ``est.background_t`` set when it converged;
        ``constants`` nonlinear.py's (its globals, read every call as its own solve does)."""
        self._pack(est, _tunables(constants, est.max_iterations), constants["PLAUSIBLE_WRENCH"])
        n3 = 3 * (len(b) // 3)
        self._b[:n3] = b
        self._T[:] = np.ravel(start)
        self._u[:] = u0
        usable_at = None
        if usable is not None:
            self._usable[: n3 // 3] = usable
            usable_at = self._addresses[3]
        end = self._end
        known = end is not None and end[0] is start and end[1] is u0 and end[2] == background
        model, state, b_at, _, T_at, u_at = self._addresses
        self.lib.nl_solve(
            model,
            state,
            b_at,
            usable_at,
            T_at,
            u_at,
            int(background),
            damping,
            int(known),
            self._out.ctypes.data,
        )
        out = self._out.tolist()
        T, u, converged = self._T.reshape(4, 4).copy(), self._u.copy(), out[8] != 0
        if converged:
            est.pose, est.background_t = T, u.copy()
            self._end = (T, est.background_t, background)
        return self._out[:6].copy(), T, converged, int(out[7]), out[6], u

    def jacobian(
        self, est: Any, T: np.ndarray, u: np.ndarray, constants: dict[str, Any], known: int | None = None
    ) -> tuple[int, np.ndarray | None]:
        """`NonlinearEstimator.jacobian_at` for ``est``: the Jacobian with the background field's
        columns (3n x 9) its solve keeps at pose ``T`` and field ``u`` (a copy; None when its
        count is ``known``), made and kept in the state only where the solve would make one,
        and its count in this state (`nl_kept_jacobian`'s id). With the model and tolerances
        the last solve packed (its kept Jacobians are theirs); packed here before the first."""
        if not self._packed:
            self._pack(est, _tunables(constants, est.max_iterations), constants["PLAUSIBLE_WRENCH"])
        self._T[:] = T.ravel()
        self._u[:] = u
        model, state, _, _, T_at, u_at = self._addresses
        count = self.lib.nl_kept_jacobian(model, state, T_at, u_at, self._J_at)
        if count == known:
            return count, None
        return count, self._J[: 3 * int(self._model[0])].copy()  # the packed chips' (nl_model.n)

    def chord_gains(self, J: np.ndarray) -> np.ndarray:
        """`NonlinearEstimator.gains` with every channel: (J^T J + P)^-1 J^T (9 x 3n) for J
        (`jacobian`'s), from the chord steps' factors when J is the kept one; LinAlgError
        when J^T J + P is singular (as numpy's solve)."""
        n3 = 3 * int(self._model[0])
        if J.shape != (n3, 9) or not self._packed:
            raise ValueError(f"a Jacobian of {J.shape} for a packed model of {n3} channels")
        self._J[:n3] = J  # into the buffer whose address is kept: no ctypes object a call
        model, state = self._addresses[:2]
        if not self.lib.nl_chord_gains(model, state, self._J_at, self._G_at):
            raise np.linalg.LinAlgError("Singular matrix")
        return self._G[:, :n3].copy()

    def continued(self, before: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, float, float]:
        """`se3.continued` in C: ``pose`` moved on by the motion from ``before`` to it,
        that motion's translation (m) and turn (rad)."""
        before, pose = np.ascontiguousarray(before, dtype=float), np.ascontiguousarray(pose, dtype=float)
        ahead = np.empty((4, 4))
        self.lib.nl_continued(
            before.ctypes.data,
            pose.ctypes.data,
            se3.SMALL_ANGLE,
            se3.NEAR_PI,
            ahead.ctypes.data,
            self._sizes_at,
        )
        moved, turned = self._sizes.tolist()
        return ahead, moved, turned

    def _pack(self, est: Any, tunables: tuple[float, ...], plausible: np.ndarray) -> None:
        """The model's constants into `_model` when any changed (as `FluxModel._constants`
        follows its arrays, and the offset, stiffness and tolerances besides)."""
        model = est.model
        c = model._constants
        key = (
            model.offset_t.tobytes(),
            est.stiffness.tobytes(),
            est.zero_twist.tobytes(),
            plausible.tobytes(),
            tunables,
        )
        if self._packed and self._packed[0] is c and self._packed[1] == key:
            return
        m = self._model
        m[:] = 0.0
        m[:4] = (c.n, c.half_q is not None, c.own_only is not None, 0.0)
        parts = {
            "chip_p": c.chip_p,
            "magnet_p": c.magnet_p,
            "m": c.m,
            "axis": c.axis,
            "half_q": np.zeros(c.n) if c.half_q is None else c.half_q,
            "inv_m": c.inv_m,
            "resp": c.response_chip,
            "offset": model.offset_t,
            "K": est.stiffness,
            "zero_twist": est.zero_twist,
            "plausible": plausible,
            "tun": np.array(tunables),
        }
        for name, value in parts.items():
            flat = np.asarray(value, dtype=float).ravel()
            m[_AT[name] : _AT[name] + flat.size] = flat
        self._packed = (c, key)


def _tunables(nl: dict[str, Any], max_iterations: int) -> tuple[float, ...]:
    """nonlinear.py's tolerances and limits (``nl``, its globals) in `TUNABLES`' order."""
    value = {
        "MAX_STEP_M": nl["MAX_STEP_M"],
        "MAX_STEP_RAD": nl["MAX_STEP_RAD"],
        "STEP_TOL": nl["STEP_TOL"],
        "STEP_TOL_RAD": nl["STEP_TOL_RAD"],
        "CONTRACTION": nl["CONTRACTION"],
        "REUSE_M": nl["JACOBIAN_REUSE_M"],
        "REUSE_TRACE": nl["JACOBIAN_REUSE_TRACE"],
        "REUSE_T": nl["JACOBIAN_REUSE_T"],
        "MAX_RESIDUAL_T": nl["MAX_RESIDUAL_T"],
        "BACKGROUND_LIMIT_T": nl["BACKGROUND_LIMIT_T"],
        "PRIOR_WEIGHT": nl["PRIOR_WEIGHT"],
        "LINEAR_STEP_T": nl["LINEAR_STEP_T"],
        "UNDAMPED": nl["UNDAMPED"],
        "SMALL_ANGLE": se3.SMALL_ANGLE,
        "NEAR_PI": se3.NEAR_PI,
        "MAX_ITERATIONS": float(max_iterations),
    }
    return tuple(value[name] for name in TUNABLES)
