"""The package's floors (ftsensord/__init__.py): no module imports from a floor
above its own, no import circle, classes and modules small enough to read."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "ftsensord"
#: Floor of each top-level part, lowest first (the package docstring lists them).
FLOORS = {"errors": 1, "docfile": 1, "model": 2, "chip": 3, "sim": 4, "acquire": 5, "calibration": 6,
          "stages": 7, "service": 8, "client": 9, "recording": 10, "plot": 10, "bridge": 10, "ros2": 10, "echo": 10, "cli": 11,
          "__main__": 11}
#: "About 200" and "about 400" lines (issue 13): past these a class or module does too much.
MAX_CLASS_LINES = 200
MAX_MODULE_LINES = 400


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = ["ftsensord", *path.relative_to(PACKAGE).with_suffix("").parts]
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _is_type_checking(node: ast.If) -> bool:
    return isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"


def _imports(name: str, path: Path) -> set[str]:
    """The package modules ``name`` imports anywhere in its code (lazy ones too),
    leaving out what only type checkers read."""
    tree = ast.parse(path.read_text())
    skip = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If) and _is_type_checking(node)
            for n in ast.walk(node)}
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("ftsensord")}
        elif isinstance(node, ast.ImportFrom) and node.module != "__future__":
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("ftsensord"):
                continue
            for alias in node.names:  # `from pkg import module` imports the module
                found.add(f"{target}.{alias.name}" if f"{target}.{alias.name}" in MODULES else target)
    return {m for m in found if m in MODULES and m != name}


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def floor(module: str) -> int:
    parts = module.split(".")
    return 1 if len(parts) == 1 else FLOORS[parts[1]]  # the package face holds only __version__ eagerly


def test_every_part_of_the_package_has_a_floor():
    assert {m.split(".")[1] for m in MODULES if "." in m} <= set(FLOORS)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_no_module_imports_from_a_floor_above_its_own(module):
    above = sorted(m for m in GRAPH[module] if floor(m) > floor(module))
    assert not above, f"{module} (floor {floor(module)}) imports {above}"


def test_no_import_circle():
    seen: dict[str, int] = {}  # 1: on the path, 2: done

    def visit(m: str, path: list[str]) -> None:
        seen[m] = 1
        for n in sorted(GRAPH[m]):
            if seen.get(n) == 1:
                pytest.fail("import circle: " + " -> ".join(path[path.index(n):] + [n]))
            if n not in seen:
                visit(n, path + [n])
        seen[m] = 2

    for m in sorted(GRAPH):
        if m not in seen:
            visit(m, [m])


def test_the_package_face_imports_nothing_of_the_package_eagerly():
    assert GRAPH["ftsensord"] == set()


def test_each_floor_says_what_it_owns_and_may_import():
    for part in ("model", "chip", "sim", "acquire", "calibration", "service"):
        doc = ast.get_docstring(ast.parse((PACKAGE / part / "__init__.py").read_text())) or ""
        assert "May import" in doc, f"ftsensord/{part}/__init__.py: its docstring says nothing of what it may import"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_classes_and_modules_stay_small(module):
    source = MODULES[module].read_text()
    assert source.count("\n") <= MAX_MODULE_LINES, f"{module}: {source.count(chr(10))} lines"
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ClassDef):
            assert node.end_lineno - node.lineno + 1 <= MAX_CLASS_LINES, \
                f"{module}.{node.name}: {node.end_lineno - node.lineno + 1} lines"


def test_the_public_face():
    code = ("import sys, ftsensord as f; assert 'zmq' not in sys.modules; "
            "f.open_bus, f.MLX90393, f.load_config, f.Subscriber, f.ControlClient, f.FtsensordError; "
            "assert issubclass(f.FtsensordError, Exception) and callable(f.open_bus)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
