"""Build C/C++ programs against clients/c/ftsensord.h, finding libzmq without root.

Where libzmq is looked for, first found wins:

1. the system's, through ``pkg-config libzmq`` (header and library; e.g. Debian's
   libzmq3-dev);
2. the one the pyzmq wheel ships (``site-packages/pyzmq.libs/libzmq-<hash>.so.5``, or
   ``zmq/.libs``/``zmq/.dylibs`` on other wheels): linked by its path with an rpath to its
   folder. The wheel ships no zmq.h, so the build defines FTSENSORD_NO_ZMQ_H and
   ftsensord.h declares the nine libzmq functions it calls itself;
3. a libzmq the dynamic loader knows (``libzmq.so.5`` without its development link).

Run it to build the example (prints the commands it ran):

    python clients/c/build.py [--out DIR]
"""

from __future__ import annotations

import argparse
import ctypes.util
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
WARNINGS = ["-Wall", "-Wextra", "-Werror"]
STANDARDS = {"c": ("gcc", "-std=c11"), "c++": ("g++", "-std=c++17")}


@dataclass(frozen=True)
class Libzmq:
    """How to compile and link against one libzmq; ``origin`` says which was found."""

    cflags: list[str]
    ldflags: list[str]
    origin: str


def _pkg_config() -> Libzmq | None:
    if shutil.which("pkg-config") is None:
        return None
    if subprocess.run(["pkg-config", "--exists", "libzmq"], check=False).returncode != 0:
        return None
    cflags = subprocess.run(["pkg-config", "--cflags", "libzmq"], capture_output=True, text=True, check=False).stdout.split()
    libs = subprocess.run(["pkg-config", "--libs", "libzmq"], capture_output=True, text=True, check=False).stdout.split()
    return Libzmq(cflags, libs, "system libzmq (pkg-config)")


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
                          f"({lib.parent.name}/{lib.name})")
    return None


def _loader() -> Libzmq | None:
    name = ctypes.util.find_library("zmq")
    if name is None:
        return None
    return Libzmq(["-DFTSENSORD_NO_ZMQ_H"], [f"-l:{name}"], f"{name} (known to the dynamic loader)")


def find_libzmq() -> Libzmq:
    """The first libzmq found (module docstring's order); LookupError saying where it looked."""
    for finder in (_pkg_config, _pyzmq_bundled, _loader):
        found = finder()
        if found is not None:
            return found
    raise LookupError("no libzmq: `pkg-config libzmq` finds none, pyzmq ships none in its wheel "
                      "(pyzmq.libs/, zmq/.libs/), and the dynamic loader knows no libzmq")


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
    return 0


if __name__ == "__main__":
    sys.exit(main())
