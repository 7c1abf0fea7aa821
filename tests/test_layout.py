"""The package's floors (ftsensord/__init__.py): no module imports from a floor above its
own, and no import circle, counting the imports only type checkers read. How big a class
or module is follows from its design; ruff and mypy (tests/test_lint.py) keep the lines and
types honest."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "ftsensord"
#: Floor of each top-level part, lowest first (the package docstring lists them).
FLOORS = {
    "errors": 1,
    "docfile": 1,
    "model": 2,
    "chip": 3,
    "sim": 4,
    "acquire": 5,
    "calibration": 6,
    "protocol": 7,
    "config": 8,
    "processing": 9,
    "daemon": 10,
    "client": 11,
    "recording": 12,
    "plot": 12,
    "foxglove": 12,
    "ros2": 12,
    "echo": 12,
    "cli": 13,
    "__main__": 13,
    "testing": 14,
}


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


def _face_exports() -> dict[str, str]:
    """The package face's lazy names and the module each comes from (its ``_EXPORTS``):
    ``from ftsensord import Subscriber`` imports ftsensord.client when it runs."""
    for node in ast.parse((PACKAGE / "__init__.py").read_text()).body:
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "_EXPORTS" for t in node.targets
        ):
            return ast.literal_eval(node.value)
    return {}


FACE_EXPORTS = _face_exports()


def _literal_import(node: ast.Call) -> str | None:
    """The module an ``importlib.import_module("...")`` or ``__import__("...")`` call names."""
    func = node.func
    name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else None
    if (
        name in ("import_module", "__import__")
        and node.args
        and isinstance(node.args[0], ast.Constant)
        and isinstance(node.args[0].value, str)
    ):
        return node.args[0].value
    return None


def _imports(name: str, path: Path, annotations: bool = False) -> set[str]:
    """The package modules ``name`` imports anywhere in its code (lazy ones too, by
    importlib with a literal name, and through the package face's lazy names); what only
    type checkers read (the body of ``if TYPE_CHECKING:``, not its else) only with
    ``annotations``."""
    tree = ast.parse(path.read_text())
    skip = (
        set()
        if annotations
        else {
            id(n)
            for node in ast.walk(tree)
            if isinstance(node, ast.If) and _is_type_checking(node)
            for statement in node.body
            for n in ast.walk(statement)
        }
    )
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    faces = set()  # the names the package face is bound to (import ftsensord [as f])
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("ftsensord")}
            faces |= {a.asname or a.name for a in node.names if a.name == "ftsensord"}
        elif isinstance(node, ast.ImportFrom) and node.module != "__future__":
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("ftsensord"):
                continue
            for alias in node.names:  # `from pkg import module` imports the module
                module = f"{target}.{alias.name}"
                found.add(
                    module
                    if module in MODULES
                    else FACE_EXPORTS.get(alias.name, target)
                    if target == "ftsensord"
                    else target
                )
        elif isinstance(node, ast.Call) and (literal := _literal_import(node)) is not None:
            found.add(literal)
    for node in ast.walk(tree):  # ftsensord.Subscriber after `import ftsensord`
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name)
            and node.value.id in faces
            and node.attr in FACE_EXPORTS
            and id(node) not in skip
        ):
            found.add(FACE_EXPORTS[node.attr])
    return {m for m in found if m in MODULES and m != name}


#: What each module imports when it runs.
GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}
#: What each module imports for a type checker too: an annotation from a floor above, or a
#: circle only annotations close, is as much a knot in the design as one that runs. The
#: package face is left out: its annotations name the lazy names it hands out.
TYPED_GRAPH = {name: _imports(name, path, annotations=name != "ftsensord") for name, path in MODULES.items()}


def floor(module: str) -> int:
    parts = module.split(".")
    return 1 if len(parts) == 1 else FLOORS[parts[1]]  # the package face holds only __version__ eagerly


def test_every_part_of_the_package_has_a_floor():
    assert {m.split(".")[1] for m in MODULES if "." in m} <= set(FLOORS)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_no_module_imports_from_a_floor_above_its_own(module):
    above = sorted(m for m in TYPED_GRAPH[module] if floor(m) > floor(module))
    assert not above, f"{module} (floor {floor(module)}) imports {above}"


def test_no_import_circle():
    seen: dict[str, int] = {}  # 1: on the path, 2: done

    def visit(m: str, path: list[str]) -> None:
        seen[m] = 1
        for n in sorted(TYPED_GRAPH[m]):
            if seen.get(n) == 1:
                pytest.fail("import circle: " + " -> ".join(path[path.index(n) :] + [n]))
            if n not in seen:
                visit(n, path + [n])
        seen[m] = 2

    for m in sorted(TYPED_GRAPH):
        if m not in seen:
            visit(m, [m])


def test_the_package_face_imports_nothing_of_the_package_eagerly():
    assert GRAPH["ftsensord"] == set()


def test_each_floor_says_what_it_owns_and_may_import():
    for part in sorted(p for p in FLOORS if (PACKAGE / p / "__init__.py").exists()):
        doc = ast.get_docstring(ast.parse((PACKAGE / part / "__init__.py").read_text())) or ""
        assert "May import" in doc, (
            f"ftsensord/{part}/__init__.py: its docstring says nothing of what it may import"
        )


def test_the_public_face():
    code = (
        "import sys, ftsensord as f; assert 'zmq' not in sys.modules; "
        "f.open_bus, f.MLX90393, f.load_config, f.Subscriber, f.ControlClient, f.FtsensordError; "
        "assert issubclass(f.FtsensordError, Exception) and callable(f.open_bus)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize(
    "source,imported",
    [
        # the face's lazy names are its floors' modules: ControlClient is the client's (9)
        ("from .. import ControlClient\n", "ftsensord.client"),
        ("from ftsensord import Subscriber as S\n", "ftsensord.client"),
        ("import ftsensord\n\ndef f():\n    return ftsensord.load_config\n", "ftsensord.config.file"),
        # run at run time: an else beside TYPE_CHECKING, importlib with a literal name
        (
            "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    pass\nelse:\n    from ..protocol import wire\n",
            "ftsensord.protocol.wire",
        ),
        (
            "import importlib\n\ndef f():\n    return importlib.import_module('ftsensord.protocol.wire')\n",
            "ftsensord.protocol.wire",
        ),
        ("def f():\n    return __import__('ftsensord.client')\n", "ftsensord.client"),
    ],
)
def test_the_floor_check_sees_imports_that_run_whatever_their_form(tmp_path, source, imported):
    """Until 2026-11-27 each of these passed the floors as an import of the package face
    (floor 1) or of nothing, while it imports a floor-8 or floor-9 module when it runs."""
    path = tmp_path / "fake.py"
    path.write_text(source)
    found = _imports("ftsensord.chip.fake", path)
    assert imported in found and floor(imported) > floor("ftsensord.chip.fake"), found


@pytest.mark.parametrize("module", sorted(m for m, p in MODULES.items() if p.name == "__init__.py"))
def test_each_package_init_only_hands_names_on(module):
    """`__init__` holds no code of its own (a reader looks for a part's code in its modules);
    the package face's one function is its lazy `__getattr__`. Until 2026-11-27 the
    recording's held its writers and loop (302 lines), the simulator's `simulated_bus`."""
    tree = ast.parse(MODULES[module].read_text())
    defined = [n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))]
    assert defined == (["__getattr__"] if module == "ftsensord" else []), f"{module} defines {defined}"


def test_the_circle_check_sees_imports_only_type_checkers_read(tmp_path):
    """An import under ``if TYPE_CHECKING:`` closes no circle when the code runs, but it
    ties the two modules' designs together as much as one that runs: the checks count it."""
    path = tmp_path / "fake.py"
    path.write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ftsensord.daemon.daemon import Daemon\n"
    )
    assert "ftsensord.daemon.daemon" not in _imports("ftsensord.daemon.fake", path)
    assert "ftsensord.daemon.daemon" in _imports("ftsensord.daemon.fake", path, annotations=True)
