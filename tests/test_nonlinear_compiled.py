"""The compiled nonlinear solve (ftsensord/model/_nlsolve.c through nlcompiled.py) against
numpy's, the reference: the forward model and its Jacobian, then whole sequences of
estimates (moving loads, at rest, unusable chips, 6 and 9 unknowns, a singular J^T J, NaN
input, cold starts at full range), each sample's decision and end point compared.

The library is compiled here from the source (as an install builds it); without a C
compiler these tests skip, and under CI (which has one) they fail instead. Under CI the
installed package must carry the library its install built."""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest

from ftsensord.errors import ConfigError
from ftsensord.model import nlcompiled, nonlinear, se3
from ftsensord.model.geometry import SensorGeometry
from ftsensord.model.linear import SENSOR_RANGE
from ftsensord.model.nonlinear import FluxModel, NonlinearEstimator
from ftsensord.model.se3 import continued
from ftsensord.sim.physics import PAPER_STIFFNESS_DIAG, PhysicalScene, SimSensor

G = SensorGeometry.ring()
K = np.diag(PAPER_STIFFNESS_DIAG)
SCENE = PhysicalScene([SimSensor("s", tuple(range(0x0C, 0x14)))])  # each chip's own magnet the exact cylinder
# A channel's noise (T): the MLX90393's 1-3 uT a reading at the daemon's settings, docs/design/physics.md.
NOISE_T = 1e-6
#: End points within 1e-3 of the noise's own scatter of the estimate. Both solvers take the
#: same steps, so they differ by round-off (1e-16 relative, measured 1e-9 of the scatter at
#: most); where round-off tips a branch the other way at its threshold (a Jacobian kept or
#: made anew, a step judged the last), the end points may part by the stopping tolerances
#: (1e-8 m, 1e-6 rad: 1e-3 and 1e-4 of the scatter here) but not by the chord's own error.
SCATTER_FRACTION = 1e-3


@pytest.fixture(scope="module")
def library(tmp_path_factory) -> object:
    if nlcompiled.compiler() is None:
        if os.environ.get("CI"):
            pytest.fail("no C compiler (cc or gcc) on PATH: CI must build and test the compiled solver")
        pytest.skip("no C compiler (cc or gcc) on PATH")
    return nlcompiled.compile_library(tmp_path_factory.mktemp("nlsolve"))


def pair(library, model: FluxModel, **kwargs) -> tuple[NonlinearEstimator, NonlinearEstimator]:
    """Two estimators of ``model``: numpy's solve and the compiled one (each its own state)."""
    reference = NonlinearEstimator(model, K, solver="numpy", **kwargs)
    compiled = NonlinearEstimator(model, K, **kwargs)
    nlcompiled.attach(compiled, "compiled", library)
    assert compiled.compiled is not None
    return reference, compiled


def flux(w: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
    b = SCENE.chip_fields(G, se3.exp_se3(np.linalg.solve(K, w))).ravel()
    return b if rng is None else b + rng.normal(0, NOISE_T, b.shape)


def compare(
    reference: NonlinearEstimator, compiled: NonlinearEstimator, samples, usable=None, start=None
) -> dict:
    """Each sample through both in turn: the same decision, iterations and background
    field's presence; end points gathered for the caller's tolerance."""
    xi_a, xi_b, converged, iterations = [], [], [], []
    for k, b in enumerate(samples):
        chips = usable[k] if isinstance(usable, list) else usable
        a, c = reference.estimate(b, chips, start), compiled.estimate(b, chips, start)
        assert (a.converged, a.iterations) == (c.converged, c.iterations), (k, a, c)
        assert (
            np.array_equal(np.isfinite(a.xi), np.isfinite(c.xi))
            and a.background_t.shape == c.background_t.shape
        )
        xi_a.append(a.xi)
        xi_b.append(c.xi)
        converged.append(a.converged)
        iterations.append(a.iterations)
        if a.converged:
            # The field as the pose: the same steps, round-off apart; a thousandth of a channel's noise.
            assert np.allclose(a.background_t, c.background_t, rtol=0, atol=1e-3 * NOISE_T), k
    return {
        "reference": np.array(xi_a),
        "compiled": np.array(xi_b),
        "converged": converged,
        "iterations": np.mean(iterations),
    }


def assert_within_scatter(result: dict, scatter: np.ndarray) -> None:
    diff = np.abs(result["reference"] - result["compiled"]).max(axis=0)
    assert np.all(diff < SCATTER_FRACTION * scatter), diff / scatter


def rest_scatter(model: FluxModel, w: np.ndarray) -> np.ndarray:
    """The estimate's own scatter (m, rad) under the noise at load ``w``: from the Jacobian,
    sqrt(diag((J^T J)^-1)) sigma, the Gauss-Newton covariance."""
    _, J = model.predict_and_jacobian(se3.exp_se3(np.linalg.solve(K, w)))
    return np.sqrt(np.diag(np.linalg.inv(J.T @ J))) * NOISE_T


def c_model(library, model: FluxModel) -> tuple[nlcompiled.CompiledSolve, object]:
    est = NonlinearEstimator(model, K, solver="numpy")
    solve = nlcompiled.solver_for("compiled", library)
    assert solve is not None
    solve._pack(est, nlcompiled._tunables(vars(nonlinear), est.max_iterations), nonlinear.PLAUSIBLE_WRENCH)
    return solve, ctypes.c_void_p(solve._model.ctypes.data)


@pytest.mark.parametrize(
    "octupole,crosstalk,matrix", [(True, True, True), (False, True, False), (True, False, False)]
)
def test_the_forward_model_and_its_jacobian_are_fluxmodels(library, octupole, crosstalk, matrix):
    rng = np.random.default_rng(1)
    scale = (
        rng.normal(1, 0.05, (8, 3, 3)) if matrix else rng.normal(1, 0.05, (8, 3))
    )  # a full response per chip
    model = FluxModel(
        G, G.magnet_moment_am2, scale, rng.normal(0, 20e-6, (8, 3)), crosstalk=crosstalk, octupole=octupole
    )
    solve, at = c_model(library, model)
    for _ in range(20):
        T = se3.exp_se3(rng.uniform(-1, 1, 6) * [3e-3, 3e-3, 2e-3, 0.03, 0.03, 0.03])
        u = rng.normal(0, 50e-6, 3)
        pred, J = np.empty(24), np.empty((48, 9))  # rows for _nlsolve.c's 16 chips
        solve.lib.nl_predict_and_jacobian(
            at,
            ctypes.c_void_p(T.ctypes.data),
            ctypes.c_void_p(u.ctypes.data),
            ctypes.c_void_p(pred.ctypes.data),
            ctypes.c_void_p(J.ctypes.data),
        )
        want, want_J = model.predict_and_jacobian(T, u, True)
        # The same formulas summed in another order: round-off, 1e-15 of the largest term.
        assert np.allclose(pred, want, rtol=0, atol=1e-12 * np.abs(want).max())
        assert np.allclose(J[:24], want_J, rtol=0, atol=1e-12 * np.abs(want_J).max(axis=0))


@pytest.mark.parametrize("background", [True, False], ids=["9 unknowns", "6 unknowns"])
@pytest.mark.parametrize("seed", [6, 7, 8, 9, 10])
def test_a_moving_load_gives_the_same_fits(library, seed, background):
    """tests/test_nonlinear.py's moving load (40 % of range on every axis, 1.3 Hz, 100 Hz
    samples) on the cylinder scene with the octupole model, warm-started sample by sample."""
    rng = np.random.default_rng(seed)
    t = np.arange(80) / 100.0
    loads = 0.4 * SENSOR_RANGE * np.sin(2 * np.pi * 1.3 * t[:, None] + np.arange(6) * np.pi / 3)
    samples = [flux(w, rng) for w in loads]
    model = FluxModel(G, G.magnet_moment_am2)
    result = compare(*pair(library, model, background=background), samples)
    assert all(result["converged"])
    assert_within_scatter(result, rest_scatter(model, loads[0]))


def test_at_rest_the_same_fits(library):
    rng = np.random.default_rng(3)
    samples = [flux(np.array([3.0, -2.0, 1.0, 0.01, 0.0, -0.01]), rng) for _ in range(100)]
    model = FluxModel(G, G.magnet_moment_am2)
    result = compare(*pair(library, model), samples)
    assert all(result["converged"])
    assert_within_scatter(result, result["reference"][1:].std(axis=0))


def test_chips_leaving_and_coming_back_give_the_same_fits(library):
    """A chip unusable for a stretch (its reading junk), then two, then all back: the
    masked solves (damped, no chord gains) and the kept Jacobians around them."""
    rng = np.random.default_rng(11)
    loads = np.linspace([0, 0, 0, 0, 0, 0], [20.0, 10.0, -5.0, 0.05, -0.05, 0.1], 60)
    samples, usable = [], []
    for k, w in enumerate(loads):
        b, ok = flux(w, rng), np.ones(8, bool)
        ok[[2] if 15 <= k < 30 else [0, 5] if 30 <= k < 45 else []] = False
        b.reshape(-1, 3)[~ok] = [0.05, np.nan, -0.05]  # junk where unusable: it must not be read
        samples.append(b)
        usable.append(ok)
    model = FluxModel(G, G.magnet_moment_am2)
    result = compare(*pair(library, model), samples, usable)
    assert all(result["converged"])
    assert_within_scatter(result, rest_scatter(model, loads[-1]))


@pytest.mark.parametrize(
    "w",
    [
        [45.0, 0, 12.0, 0, 0.1, 0],
        [0, -40.0, -15, 0.1, 0, 0],
        [35.0, -35, 14, 0.14, -0.14, 0.14],
        [0, 0, 0, 0, 0, 0.2],
    ],
)
def test_cold_starts_at_full_range_give_the_same_fits(library, w):
    samples = [flux(np.array(w), np.random.default_rng(2))]
    model = FluxModel(G, G.magnet_moment_am2)
    result = compare(*pair(library, model), samples, start=np.eye(4))
    assert all(result["converged"])
    assert_within_scatter(result, rest_scatter(model, np.array(w)))


@pytest.mark.parametrize("masked", [False, True], ids=["chord gains", "damped solve"])
@pytest.mark.parametrize("background", [True, False], ids=["9 unknowns", "6 unknowns"])
def test_a_singular_normal_matrix_is_the_same_refusal(library, masked, background):
    """Every chip's response zero: J^T J's pose block is exactly zero, which numpy's solve
    refuses (LinAlgError) and the compiled LU finds as a zero pivot; both end the fit
    unconverged at its first iteration, the pose where it started."""
    model = FluxModel(G, G.magnet_moment_am2, scale=np.zeros((8, 3)))
    usable = np.array([0, 1, 1, 1, 1, 1, 1, 1], bool) if masked else None
    reference, compiled = pair(library, model, background=background)
    b = flux(np.zeros(6))
    a, c = reference.estimate(b, usable), compiled.estimate(b, usable)
    assert not a.converged and not c.converged and a.iterations == c.iterations >= 1
    assert np.array_equal(a.pose, np.eye(4)) and np.array_equal(c.pose, np.eye(4))


def test_nan_input_is_the_same_refusal_and_an_unused_nan_is_ignored(library):
    model = FluxModel(G, G.magnet_moment_am2)
    reference, compiled = pair(library, model)
    b = flux(np.array([5.0, 0, 0, 0, 0, 0]))
    bad = b.copy()
    bad[4] = np.nan
    for est in (reference, compiled):
        e = est.estimate(bad)
        assert not e.converged and e.iterations == 0 and e.rms_residual_t == np.inf
    without = np.ones(8, bool)
    without[1] = False  # the NaN's chip left out: the rest give the pose
    result = compare(reference, compiled, [bad, b], [without, None])
    assert all(result["converged"])
    few = np.zeros(8, bool)
    few[:2] = True  # 6 channels for 9 unknowns: a refusal before any step
    assert not compiled.estimate(b, few).converged and compiled.estimate(b, few).iterations == 0


def test_garbage_gives_the_same_decisions(library):
    """Random flux of the chips' range: both refuse (or, rarely, both fit) the same samples."""
    rng = np.random.default_rng(0)
    samples = [rng.uniform(-3e-3, 3e-3, 24) for _ in range(20)]
    result = compare(*pair(library, FluxModel(G, G.magnet_moment_am2)), samples)
    assert not all(result["converged"])


def test_the_solver_is_chosen_by_name(tmp_path, library):
    model = FluxModel(G, G.magnet_moment_am2)
    assert NonlinearEstimator(model, K, solver="numpy").compiled is None
    assert nlcompiled.solver_for("auto", library) is not None
    assert nlcompiled.solver_for("auto", tmp_path / "none.so") is None  # absent: numpy's, silently
    other = tmp_path / "other.c"  # a library that is not this source's (a stale or foreign build)
    other.write_text("int nl_model_doubles(void) { return 0; }\n")
    subprocess.run(
        [nlcompiled.compiler(), "-shared", "-fPIC", "-o", str(tmp_path / "other.so"), str(other)], check=True
    )
    assert nlcompiled.load(tmp_path / "other.so") is None
    assert nlcompiled.solver_for("auto", tmp_path / "other.so") is None
    with pytest.raises(ConfigError, match="compiled.*none.so.*C compiler"):
        nlcompiled.solver_for("compiled", tmp_path / "none.so")
    with pytest.raises(ConfigError, match="'fast' is not one of auto, numpy, compiled"):
        NonlinearEstimator(model, K, solver="fast")
    with pytest.raises(ConfigError, match="17 chips, at most 16"):  # _nlsolve.c's NMAX
        nlcompiled.solver_for("compiled", library, chips=17)
    assert nlcompiled.solver_for("auto", library, chips=17) is None


@pytest.mark.parametrize(
    "edit",
    [
        (
            "double chip_p[NMAX][3], magnet_p[NMAX][3];",
            "double magnet_p[NMAX][3], chip_p[NMAX][3];",
        ),  # same size
        ("X(MAX_STEP_M) X(MAX_STEP_RAD)", "X(MAX_STEP_RAD) X(MAX_STEP_M)"),  # two tunables swapped
    ],
    ids=["fields swapped", "tunables swapped"],
)
def test_a_library_whose_layout_differs_field_by_field_is_not_used(tmp_path, edit):
    """Its total size the same, the library's nl_model or tunables in another order: the
    loader compares each field's offset and each tunable's index, and takes numpy's solve."""
    for source in (*nlcompiled.SOURCES, nlcompiled.SOURCES[0].with_name("_nlsolve.h")):
        text = source.read_text()
        if source.suffix == ".h":
            assert edit[0] in text
            text = text.replace(edit[0], edit[1])
        (tmp_path / source.name).write_text(text)
    out = tmp_path / "_nlsolve.so"
    subprocess.run(
        [
            nlcompiled.compiler(),
            "-std=c99",
            "-shared",
            "-fPIC",
            "-o",
            str(out),
            str(tmp_path / "_nlsolve.c"),
            str(tmp_path / "_nlmodel.c"),
            "-lm",
        ],
        check=True,
    )
    assert nlcompiled.load(out) is None
    assert nlcompiled.solver_for("auto", out) is None


def test_an_install_carries_the_library_it_built():
    """CI installs the package with pip (`.ci/run`): setup.py must have compiled the solve
    into it (a compiler is there), beside the installed nlcompiled.py where `auto` looks.
    (The tests import the source tree's package, which has none: the installed one is
    looked up in the environment's site-packages.)"""
    if not os.environ.get("CI"):
        pytest.skip("the installed package is checked under CI, where pip installed it")
    installed = Path(sysconfig.get_paths()["platlib"]) / "ftsensord" / "model"
    assert (installed / "nlcompiled.py").is_file(), f"ftsensord is not installed in {installed.parent.parent}"
    built = nlcompiled.library_path(installed)
    assert built is not None and nlcompiled.load(built) is not None, sorted(
        p.name for p in installed.iterdir()
    )


PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN = 65, 1  # linux/prctl.h (Linux 6.3): what MemoryDenyWriteExecute= sets
MDWE_CHILD = """
import mmap, sys, numpy as np
from pathlib import Path
try:
    mmap.mmap(-1, 4096, prot=mmap.PROT_READ | mmap.PROT_WRITE | mmap.PROT_EXEC)  # what a JIT needs
    print("writable and executable memory was granted")
except PermissionError:
    pass
else:
    sys.exit(3)
from ftsensord.model import nlcompiled, se3
from ftsensord.model.geometry import SensorGeometry
from ftsensord.model.nonlinear import FluxModel, NonlinearEstimator
g = SensorGeometry.ring()
model = FluxModel(g, g.magnet_moment_am2)
est = NonlinearEstimator(model, np.eye(6))  # any K: the wrench is not what is tested
nlcompiled.attach(est, "compiled", Path(sys.argv[1]))
b = model.predict(se3.exp_se3(np.array([1e-4, 0, 2e-4, 0, 0.01, 0])), np.zeros(3))
print(est.estimate(b).converged)
"""


def test_the_compiled_solve_runs_where_memory_may_not_be_written_and_executed(library):
    """The unit's MemoryDenyWriteExecute=yes (systemd sets the kernel's PR_SET_MDWE where
    it has one): the process started under it refuses writable executable memory (what
    numba's JIT or a ctypes callback needs), and the library loads and solves all the same."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_MDWE, 0, 0, 0, 0) == -1 and ctypes.get_errno() == 22:  # EINVAL: no PR_SET_MDWE
        pytest.skip("this kernel has no PR_SET_MDWE (Linux 6.3+)")

    def deny() -> None:
        if libc.prctl(PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_MDWE)")

    done = subprocess.run(
        [sys.executable, "-c", MDWE_CHILD, str(library)],
        preexec_fn=deny,
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parent.parent,
    )
    assert done.returncode == 0 and done.stdout.split() == ["True"], (
        done.returncode,
        done.stdout,
        done.stderr,
    )


def test_the_motion_continued_is_se3s(library):
    """The warm start's prediction (`se3.continued`) in C: the same pose and sizes."""
    solve = nlcompiled.solver_for("compiled", library)
    assert solve is not None
    rng = np.random.default_rng(5)
    for scale in (1e-6, 1e-3, 1.0):  # the series near zero, a sample's motion, a large turn
        before = se3.exp_se3(rng.normal(0, 1, 6) * [1e-3, 1e-3, 1e-3, 0.02, 0.02, 0.02])
        pose = se3.exp_se3(rng.normal(0, scale, 6) * [1e-3, 1e-3, 1e-3, 0.5, 0.5, 0.5]) @ before
        want, c = continued(before, pose), solve.continued(before, pose)
        assert np.allclose(c[0], want[0], rtol=0, atol=1e-15)  # round-off of unit-size entries
        assert np.allclose(
            c[1:], want[1:], rtol=1e-12, atol=1e-20
        )  # norms of the same twist, round-off apart


def test_status_says_which_solve_the_daemon_runs(library):
    """`status`' `nonlinear_solver`: numpy's without the library, compiled with it, null
    without a nonlinear calibration (an operator sees whether the install built it)."""
    from ftsensord.config.file import builtin_path, load_config
    from ftsensord.daemon.status import sensor_status
    from ftsensord.processing.filters import WrenchFilter
    from ftsensord.processing.pipeline import SensorPipeline

    s = load_config(builtin_path("sim.toml")).sensors[0]
    p = SensorPipeline.build(s, WrenchFilter(), 2)
    assert p.nonlinear is not None  # the packaged calibrations have one
    nlcompiled.attach(p.nonlinear, "numpy")
    assert sensor_status(p)["nonlinear_solver"] == "numpy"
    nlcompiled.attach(p.nonlinear, "compiled", library)
    assert sensor_status(p)["nonlinear_solver"] == "compiled"
    p.nonlinear = None
    assert sensor_status(p)["nonlinear_solver"] is None
