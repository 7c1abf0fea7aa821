"""clients/c/build.py on a new user's machine: the system's libzmq preferred over the copy
inside a venv, that copy used only when there is no other (and the output says the program
then depends on the venv), and, with neither, a failure naming both fixes.

This host may or may not have a system libzmq; the decision is tested with what was found
given as arguments, and end to end with pkg-config pointed at an empty folder and, where a
system libzmq is wanted, one the compiler finds through CPATH and LIBRARY_PATH (the
environment gcc reads by itself)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from .test_c_client import CDIR, build

INSTALL = "sudo apt install libzmq3-dev"
VENV_PYTHON = ".venv/bin/python clients/c/build.py"


def test_the_system_libzmq_wins_and_only_pyzmqs_copy_carries_a_venv_note():
    system = build.Libzmq([], ["-lzmq"], "system")
    bundled = build.Libzmq(
        ["-DFTSENSORD_NO_ZMQ_H"], ["/v/pyzmq.libs/libzmq-abc.so.5"], "pyzmq", venv=Path("/v")
    )
    assert build.choose(system, bundled) is system
    assert build.choose(system, None) is system
    assert build.venv_note(system) is None
    assert build.choose(None, bundled) is bundled
    note = build.venv_note(bundled)
    assert note is not None and "/v" in note and "removed" in note and INSTALL in note
    with pytest.raises(LookupError) as exc:
        build.choose(None, None)
    assert INSTALL in str(exc.value) and VENV_PYTHON in str(exc.value)


def test_pyzmq_is_looked_at_only_when_no_system_libzmq_is_found(monkeypatch):
    found = {name: build.Libzmq([], [f"-l{name}"], name) for name in ("pkg", "compiler", "loader", "pyzmq")}
    asked: list[str] = []

    def finder(name: str, result: bool):
        def find():
            asked.append(name)
            return found[name] if result else None

        return find

    # The dynamic loader's runtime libzmq is the system's too: it outlives any venv.
    for present in (
        ("pkg", "compiler", "loader", "pyzmq"),
        ("compiler", "loader", "pyzmq"),
        ("loader", "pyzmq"),
        ("pyzmq",),
    ):
        asked.clear()
        monkeypatch.setattr(build, "_pkg_config", finder("pkg", "pkg" in present))
        monkeypatch.setattr(build, "_compiler_default", finder("compiler", "compiler" in present))
        monkeypatch.setattr(build, "_loader", finder("loader", "loader" in present))
        monkeypatch.setattr(build, "_pyzmq_bundled", finder("pyzmq", "pyzmq" in present))
        assert build.find_libzmq() is found[present[0]], present
        assert ("pyzmq" in asked) == (present == ("pyzmq",)), (present, asked)


def run_build(
    tmp_path: Path, *python_flags: str, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess:
    """build.py run as a user runs it, pkg-config finding nothing (its search path an empty folder)."""
    empty = tmp_path / "no-pkgconfig"
    empty.mkdir(exist_ok=True)
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    full = {**os.environ, "PKG_CONFIG_LIBDIR": str(empty), "PKG_CONFIG_PATH": "", **(env or {})}
    return subprocess.run(
        [sys.executable, *python_flags, str(CDIR / "build.py"), "--out", str(out)],
        env=full,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def runpath(program: Path) -> str:
    """The program's RPATH/RUNPATH entries, "" when it has none."""
    dynamic = subprocess.run(
        ["readelf", "-d", str(program)], capture_output=True, text=True, check=True
    ).stdout
    return " ".join(line for line in dynamic.splitlines() if "RPATH" in line or "RUNPATH" in line)


def system_libzmq_here(monkeypatch, tmp_path: Path) -> object:
    """The system libzmq build.py finds on this host with pkg-config finding none, or None."""
    monkeypatch.setenv("PKG_CONFIG_LIBDIR", str(tmp_path))
    monkeypatch.setenv("PKG_CONFIG_PATH", "")
    return build.find_system_libzmq()


def test_without_pyzmq_and_without_a_system_libzmq_build_py_names_both_fixes(tmp_path, monkeypatch):
    # -I -S: no site-packages, so no pyzmq: the system python of a fresh machine.
    done = run_build(tmp_path, "-I", "-S")
    if system_libzmq_here(monkeypatch, tmp_path) is not None:  # a host with libzmq installed builds with it
        assert done.returncode == 0, done.stderr
        assert "note:" not in done.stdout and sys.prefix not in runpath(tmp_path / "out" / "example")
        return
    assert done.returncode != 0 and not (tmp_path / "out" / "example").exists()
    assert INSTALL in done.stderr and VENV_PYTHON in done.stderr, done.stderr


def test_with_only_pyzmqs_libzmq_the_output_says_the_program_depends_on_the_venv(tmp_path, monkeypatch):
    done = run_build(tmp_path)
    assert done.returncode == 0, done.stderr
    program = tmp_path / "out" / "example"
    if system_libzmq_here(monkeypatch, tmp_path) is not None:
        assert "note:" not in done.stdout and sys.prefix not in runpath(program)
        return
    venv = str(Path(sys.prefix).resolve())
    assert venv in runpath(program)  # what breaks when the venv is rebuilt ...
    note = [line for line in done.stdout.splitlines() if line.startswith("note:")]
    assert note and venv in note[0] and INSTALL in note[0], done.stdout  # ... and the output says so


# The one declaration build.py's test compile needs; ftsensord.h, seeing no
# ZMQ_VERSION_MAJOR, declares the calls it makes itself.
FAKE_ZMQ_H = "void *zmq_ctx_new(void);\n"


def fake_system_libzmq(tmp_path: Path) -> Path:
    """A prefix with include/zmq.h and lib/libzmq.so, as libzmq3-dev installs them under /usr,
    made of pyzmq's library under the usual names."""
    bundled = build._pyzmq_bundled()
    if bundled is None:
        pytest.skip("pyzmq ships no libzmq here to stand in for a system one")
    system = tmp_path / "usr"
    (system / "include").mkdir(parents=True)
    (system / "lib").mkdir()
    (system / "include" / "zmq.h").write_text(FAKE_ZMQ_H)
    lib = Path(bundled.ldflags[0])
    (system / "lib" / "libzmq.so").symlink_to(lib)
    for other in lib.parent.iterdir():  # libsodium, which libzmq finds next to itself ($ORIGIN)
        (system / "lib" / other.name).symlink_to(other)
    return system


def test_a_libzmq_the_compiler_finds_is_preferred_to_pyzmqs_copy(tmp_path):
    """libzmq3-dev where pkg-config is not installed: zmq.h and libzmq.so where gcc looks."""
    system = fake_system_libzmq(tmp_path)
    done = run_build(tmp_path, env={"CPATH": str(system / "include"), "LIBRARY_PATH": str(system / "lib")})
    assert done.returncode == 0, done.stderr
    assert "compiler" in done.stdout.splitlines()[0] and "note:" not in done.stdout, done.stdout
    assert " -lzmq" in done.stdout and runpath(tmp_path / "out" / "example") == ""


def test_pkg_config_libzmq_is_preferred_to_pyzmqs_copy(tmp_path):
    """libzmq3-dev's libzmq.pc (Debian 12's 4.3.4-6 has /usr/lib/<arch>/pkgconfig/libzmq.pc)."""
    if build.shutil.which("pkg-config") is None:
        pytest.skip("no pkg-config on PATH")
    system = fake_system_libzmq(tmp_path)
    pc = tmp_path / "pkgconfig"
    pc.mkdir()
    (pc / "libzmq.pc").write_text(
        f"Name: libzmq\nDescription: libzmq\nVersion: 4.3.5\n"
        f"Cflags: -I{system / 'include'}\nLibs: -L{system / 'lib'} -lzmq\n"
    )
    done = run_build(tmp_path, env={"PKG_CONFIG_PATH": str(pc)})
    assert done.returncode == 0, done.stderr
    assert "pkg-config" in done.stdout.splitlines()[0] and "note:" not in done.stdout, done.stdout
    assert f"-I{system / 'include'}" in done.stdout and runpath(tmp_path / "out" / "example") == ""
