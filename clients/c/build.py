"""Build C/C++ programs against clients/c/ftsensord.h, finding libzmq without root.

The system's libzmq is preferred, in this order (first found wins):

1. ``pkg-config --cflags --libs libzmq`` (Debian and Raspberry Pi OS: libzmq3-dev);
2. zmq.h and libzmq.so where the compiler looks by itself (libzmq3-dev where
   pkg-config is not installed): a test compile says;
3. a runtime libzmq the dynamic loader knows (``libzmq.so.5`` without the development
   package), linked by that name; ftsensord.h then declares the calls it makes.

Only when there is none, the copy the pyzmq wheel ships inside the venv
(``site-packages/pyzmq.libs/libzmq-<hash>.so.5``, or ``zmq/.libs``/``zmq/.dylibs``):
linked by its path with an rpath to that folder, FTSENSORD_NO_ZMQ_H defined (the wheel has
no zmq.h). Such a program works only while that venv stays where and as it is, which
the output says. With neither, it fails naming both fixes.

Run it to build the example (prints where libzmq came from and the command it ran):

    python clients/c/build.py [--out DIR]       # a system libzmq
    .venv/bin/python clients/c/build.py         # or the venv's pyzmq
"""

from __future__ import annotations

import argparse
import ctypes.util
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
WARNINGS = ["-Wall", "-Wextra", "-Werror"]
STANDARDS = {"c": ("gcc", "-std=c11"), "c++": ("g++", "-std=c++17")}


# The two ways out when no libzmq is found, as the error says them.
FIXES = ("either install the system's (Debian, Raspberry Pi OS):  sudo apt install libzmq3-dev\n"
         "or build with the venv's python, whose pyzmq ships one:  .venv/bin/python clients/c/build.py")


@dataclass(frozen=True)
class Libzmq:
    """How to compile and link against one libzmq; ``origin`` says which was found and
    ``venv``, for pyzmq's copy, the environment the program then depends on (None: the
    system's, which outlives any venv)."""

    cflags: list[str]
    ldflags: list[str]
    origin: str
    venv: Path | None = None


def _pkg_config() -> Libzmq | None:
    if shutil.which("pkg-config") is None:
        return None
    flags = [subprocess.run(["pkg-config", which, "libzmq"], capture_output=True, text=True, check=False)
             for which in ("--cflags", "--libs")]
    if any(done.returncode != 0 for done in flags):
        return None
    return Libzmq(flags[0].stdout.split(), flags[1].stdout.split(), "system libzmq (pkg-config)")


# A program making one libzmq call: whether it compiles and links says a libzmq is usable.
_PROBE = "int main(void) { return zmq_ctx_new() == 0; }\n"


def _links(header: str, ldflags: list[str]) -> bool:
    cc = compiler("c")
    if cc is None:
        return False
    with tempfile.TemporaryDirectory() as tmp:
        done = subprocess.run([cc, "-x", "c", "-", "-o", str(Path(tmp) / "probe"), *ldflags], input=header + _PROBE,
                              capture_output=True, text=True, check=False)
    return done.returncode == 0


def _compiler_default() -> Libzmq | None:
    """zmq.h and -lzmq where gcc looks without being told (CPATH, LIBRARY_PATH honoured)."""
    if not _links("#include <zmq.h>\n", ["-lzmq"]):
        return None
    return Libzmq([], ["-lzmq"], "system libzmq (zmq.h and -lzmq found by the compiler)")


def _loader() -> Libzmq | None:
    name = ctypes.util.find_library("zmq")
    # ctypes may name a library the linker cannot find by that name: the link says.
    if name is None or not _links("void *zmq_ctx_new(void);\n", [f"-l:{name}"]):
        return None
    return Libzmq(["-DFTSENSORD_NO_ZMQ_H"], [f"-l:{name}"], f"system {name} (known to the dynamic loader, no zmq.h)")


def _environment_of(lib: Path) -> Path:
    """The venv (or other prefix) holding ``lib``: what a rebuild replaces."""
    prefix = Path(sys.prefix).resolve()
    return prefix if lib.is_relative_to(prefix) else lib.parent


def _pyzmq_bundled() -> Libzmq | None:
    try:
        import zmq
    except ImportError:
        return None
    pkg = Path(zmq.__file__).resolve().parent
    for folder in (pkg.parent / "pyzmq.libs", pkg / ".libs", pkg / ".dylibs", pkg):
        libs = sorted(folder.glob("libzmq*.so*")) + sorted(folder.glob("libzmq*.dylib"))
        if libs:
            lib = libs[0]
            return Libzmq(["-DFTSENSORD_NO_ZMQ_H"], [str(lib), f"-Wl,-rpath,{lib.parent}"],
                          f"libzmq {zmq.zmq_version()} bundled with pyzmq {zmq.__version__} "
                          f"({lib.parent.name}/{lib.name})", venv=_environment_of(lib))
    return None


def choose(system: Libzmq | None, bundled: Libzmq | None) -> Libzmq:
    """The system's libzmq if there is one, else pyzmq's copy; LookupError naming both fixes."""
    if system is not None:
        return system
    if bundled is not None:
        return bundled
    raise LookupError(f"no libzmq found: `pkg-config libzmq` finds none, the compiler finds no zmq.h "
                      f"with -lzmq, the dynamic loader knows no libzmq, and {sys.executable} has no pyzmq;\n{FIXES}")


def find_system_libzmq() -> Libzmq | None:
    """The first system libzmq found (the module docstring's order), or None."""
    for finder in (_pkg_config, _compiler_default, _loader):
        found = finder()
        if found is not None:
            return found
    return None


def find_libzmq() -> Libzmq:
    """The libzmq to build with (``choose``): pyzmq is looked at only when the system has none."""
    system = find_system_libzmq()
    return choose(system, None if system is not None else _pyzmq_bundled())


def venv_note(libzmq: Libzmq) -> str | None:
    """What a program linked to pyzmq's copy depends on, and how to be rid of it; None for the system's."""
    if libzmq.venv is None:
        return None
    return (f"note: the program is linked to the libzmq inside {libzmq.venv}: it stops working when that "
            f"venv is removed or moved, or its pyzmq replaced (the copy's name carries a hash); "
            f"rebuild the program then, or `sudo apt install libzmq3-dev` (Debian, Raspberry Pi OS) for a "
            f"system libzmq, which this script then prefers")


def compiler(lang: str) -> str | None:
    """The compiler's path for "c" or "c++", or None."""
    return shutil.which(STANDARDS[lang][0])


def compile_command(sources: list[Path], output: Path, lang: str = "c", libzmq: Libzmq | None = None,
                    extra: list[str] | None = None, link: bool = True) -> list[str]:
    """The command compiling ``sources`` (as ``lang`` whatever their suffix) with the
    warnings as errors; ``link=False`` makes an object file and needs no libzmq."""
    cc, std = STANDARDS[lang]
    cmd = [compiler(lang) or cc, std, *WARNINGS, "-O2", "-I", str(HERE), "-x", lang, *map(str, sources), "-x", "none"]
    if libzmq is not None:
        cmd[1:1] = libzmq.cflags
    cmd += list(extra or [])
    cmd += ["-o", str(output)] if link else ["-c", "-o", str(output)]
    if link and libzmq is not None:
        cmd += libzmq.ldflags
    return cmd


def build(sources: list[Path], output: Path, lang: str = "c", libzmq: Libzmq | None = None,
          extra: list[str] | None = None, link: bool = True) -> list[str]:
    """Compile; raise RuntimeError with the compiler's messages on failure. Returns the command."""
    cmd = compile_command(sources, output, lang, libzmq, extra, link)
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}\n{done.stderr}")
    return cmd


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=HERE, help="folder for the program (default: clients/c)")
    args = parser.parse_args()
    if compiler("c") is None:
        print("no C compiler: gcc is not on PATH", file=sys.stderr)
        return 1
    try:
        libzmq = find_libzmq()
    except LookupError as exc:
        print(exc, file=sys.stderr)
        return 1
    print(f"libzmq: {libzmq.origin}")
    try:
        cmd = build([HERE / "example.c"], args.out / "example", "c", libzmq)
    except RuntimeError as exc:
        print(exc, file=sys.stderr)
        return 1
    print(" ".join(cmd))
    note = venv_note(libzmq)
    if note is not None:  # last, where it is read
        print(note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
