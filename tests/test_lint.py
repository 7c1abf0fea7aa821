"""The package's lines and types, checked as the project configures them (pyproject.toml):
ruff (line length, import order, pyupgrade, bugbear, a complexity limit) and mypy. They take
the place of a cap on a file's size: a file is as big as its one job, and these keep it honest."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True, text=True)


def test_ruff_passes_on_the_package_the_tests_and_the_benchmarks():
    done = _run("ruff", "check", "ftsensord", "tests", "benchmarks")
    assert done.returncode == 0, done.stdout + done.stderr


def test_the_code_is_as_ruff_formats_it():
    done = _run("ruff", "format", "--check", "ftsensord", "tests", "benchmarks")
    assert done.returncode == 0, done.stdout + done.stderr


def test_mypy_passes_on_the_package():
    done = _run("mypy")  # the files and settings: [tool.mypy]
    assert done.returncode == 0, done.stdout + done.stderr
