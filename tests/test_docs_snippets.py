"""The first hour, as a new user copies it: every ```python block of README.md and
docs/guide/clients.md runs as written against `ftsensord run` (the packaged simulated daemon),
with only the values the text leaves to the user defined first (`USERS_OWN`). The CSV
readers' block (indented in a list) is run by tests/test_record.py on a real recording."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import start_daemon

ROOT = Path(__file__).resolve().parent.parent
PAGES = (ROOT / "README.md", ROOT / "docs" / "guide" / "clients.md")
#: What a snippet's text says is the user's own (a device's kinematics, a scipy rotation):
#: stand-ins of the same kind. Anything else a snippet uses must be in the snippet.
USERS_OWN = """
import numpy as np
R_world_tip = np.eye(3)                      # 'R_world,tip from the device's kinematics'
class _Rotation:                             # scipy.spatial.transform.Rotation, as far as used
    def as_quat(self): return np.array([0.0, 0.0, 0.0, 1.0])
    def as_matrix(self): return np.eye(3)
rot = _Rotation()
"""


def blocks() -> list[tuple[str, int, str]]:
    """(page, line, code) of each ```python block that starts a line."""
    out = []
    for page in PAGES:
        text = page.read_text()
        for m in re.finditer(r"^```python\n(.*?)^```", text, re.DOTALL | re.MULTILINE):
            out.append((page.name, text[: m.start()].count("\n") + 1, m.group(1)))
    return out


BLOCKS = blocks()


def test_the_pages_have_python_blocks_to_run():
    assert len(BLOCKS) >= 2  # the Subscriber/ControlClient block and the orientation one


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    folder = tmp_path_factory.mktemp("docs")
    config = ROOT / "ftsensord" / "data" / "sim.toml"  # what `ftsensord run` uses without --config
    proc, notify = start_daemon(config, folder, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        yield folder
    finally:
        proc.terminate()
        proc.wait(timeout=20)
        notify.close()


@pytest.mark.parametrize(("page", "line", "code"), BLOCKS, ids=[f"{p}:{n}" for p, n, _ in BLOCKS])
def test_a_python_block_runs_as_written(daemon, page, line, code):
    env = {**os.environ, "XDG_RUNTIME_DIR": str(daemon)}
    env.pop("RUNTIME_DIRECTORY", None)
    out = subprocess.run(
        [sys.executable, "-c", USERS_OWN + "\n" + code],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
        cwd=ROOT,
    )  # this checkout's package, as the other tests
    assert out.returncode == 0 and "Traceback" not in out.stderr, f"{page}:{line}\n{out.stderr[-2000:]}"
