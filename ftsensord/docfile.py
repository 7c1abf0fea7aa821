"""Reading TOML and JSON documents with errors that name the file, the key and
what was expected: scene files, configuration, datasets, calibration files."""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from .errors import ConfigError

_MISSING = object()


def load_toml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc


def load_json(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        with path.open("rb") as f:
            doc = json.load(f)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not valid JSON: {exc}") from exc
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: expected a JSON object at the top, got {type(doc).__name__}")
    return doc


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _abbreviate(value: Any, limit: int = 80) -> Any:
    text = repr(value)
    return value if len(text) <= limit else _Abbrev(text[:limit] + "...")


class _Abbrev(str):
    def __repr__(self) -> str:
        return str(self)


class Table:
    """One TOML table, with its file and its key path for error messages."""

    def __init__(self, doc: dict[str, Any], path: str | Path, prefix: str = ""):
        self.doc = doc
        self.path = Path(path)
        self.prefix = prefix

    def key(self, name: str) -> str:
        return f"{self.prefix}{name}"

    def fail(self, name: str, expected: str, got: Any) -> ConfigError:
        return ConfigError(f"{self.path}: {self.key(name)}: expected {expected}, got {_abbreviate(got)!r}")

    def only(self, allowed: Iterable[str]) -> None:
        """Refuse unknown keys, so a misspelt key never goes unnoticed."""
        allowed = sorted(allowed)
        for name in self.doc:
            if name not in allowed:
                raise self.fail(name, f"one of {', '.join(allowed)}", name)

    def get(self, name: str, default: Any = _MISSING) -> Any:
        if name not in self.doc:
            if default is _MISSING:
                raise ConfigError(f"{self.path}: {self.key(name)}: missing")
            return default
        return self.doc[name]

    def number(self, name: str, default: Any = _MISSING, *, low: float = -math.inf,
               high: float = math.inf, unit: str = "") -> float:
        value = self.get(name, default)
        if not _is_number(value) or not low <= value <= high:
            bounds = "" if (low, high) == (-math.inf, math.inf) else f" in [{low}, {high}]"
            raise self.fail(name, f"a finite number{bounds}{' (' + unit + ')' if unit else ''}", value)
        return float(value)

    def integer(self, name: str, default: Any = _MISSING, *, low: int | None = None,
                high: int | None = None, what: str = "an integer") -> int:
        value = self.get(name, default)
        if not isinstance(value, int) or isinstance(value, bool) \
                or (low is not None and value < low) or (high is not None and value > high):
            raise self.fail(name, what, value)
        return value

    def string(self, name: str, default: Any = _MISSING, *, choices: Iterable[str] | None = None) -> str:
        value = self.get(name, default)
        options = None if choices is None else list(choices)
        if not isinstance(value, str) or (options is not None and value not in options):
            raise self.fail(name, "a string" if options is None else "one of " + ", ".join(
                f'"{c}"' for c in options), value)
        return value

    def numbers(self, name: str, length: int | None = None, default: Any = _MISSING, *,
                unit: str = "") -> list[float]:
        value = self.get(name, default)
        if not isinstance(value, list) or (length is not None and len(value) != length) \
                or not all(_is_number(v) for v in value):
            count = f"{length} " if length is not None else ""
            raise self.fail(name, f"{count}finite numbers{' (' + unit + ')' if unit else ''}", value)
        return [float(v) for v in value]

    def matrix(self, name: str, rows: int, cols: int, *, unit: str = "") -> list[list[float]]:
        """A rows x cols matrix of finite numbers, as a list of rows."""
        value = self.get(name)
        ok = isinstance(value, list) and len(value) == rows and all(
            isinstance(r, list) and len(r) == cols and all(_is_number(v) for v in r) for r in value)
        if not ok:
            raise self.fail(name, f"a {rows} x {cols} matrix of finite numbers"
                            + (f" ({unit})" if unit else ""), value)
        return [[float(v) for v in r] for r in value]

    def table(self, name: str, default: Any = _MISSING) -> Table:
        value = self.get(name, default)
        if not isinstance(value, dict):
            raise self.fail(name, "a table", value)
        return Table(value, self.path, f"{self.key(name)}.")

    def tables(self, name: str) -> list[Table]:
        value = self.get(name)
        if not isinstance(value, list) or not value or not all(isinstance(v, dict) for v in value):
            raise self.fail(name, f"a non-empty array of [[{name}]] tables", value)
        return [Table(v, self.path, f"{self.key(name)}[{i}].") for i, v in enumerate(value)]
