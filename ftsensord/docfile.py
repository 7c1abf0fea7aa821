"""Reading TOML and JSON documents with errors that name the file, the key and
what was expected: scene files, configuration, datasets, calibration files."""

from __future__ import annotations

import json
import math
import os
import re
import tomllib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from ftsensord.errors import ConfigError

_MISSING = object()


#: Largest file read, bytes: a dataset of 100,000 samples of 16 chips is about 40 MB.
MAX_FILE_BYTES = 256 * 1024 * 1024
#: Deepest nesting of arrays and tables accepted: the project's deepest documents
#: (a calibration's matrices inside its model table) nest 4 deep; Python's own parsers
#: recurse per level and fail near 1000 with an exception a caller would not expect.
MAX_DEPTH = 32
#: Longest integer literal accepted, characters (no integer the project reads has 20):
#: Python refuses to turn more than 4300 digits into an int (a plain ValueError), and
#: int() of a long literal costs quadratic time below that.
MAX_NUMBER_CHARS = 100


class _TooLong(str):
    """An integer literal longer than MAX_NUMBER_CHARS, kept to be reported with its key."""


def _bounded_number(convert: Any) -> Any:
    def parse(text: str) -> Any:
        return _TooLong(text) if len(text) > MAX_NUMBER_CHARS else convert(text)

    return parse


def _check_tree(doc: Any, max_depth: int) -> str | None:
    """None when ``doc`` nests at most ``max_depth`` deep and holds no over-long number;
    else what is wrong, with the key path (``a.b[3]``)."""
    stack: list[tuple[Any, str, int]] = [(doc, "", 0)]
    while stack:
        value, where, depth = stack.pop()
        if isinstance(value, _TooLong):
            return (
                f"{where or 'the document'}: an integer of {len(value)} characters "
                f"(at most {MAX_NUMBER_CHARS})"
            )
        if isinstance(value, dict):
            items: Iterable[tuple[str, Any]] = (
                (f"{where}.{k}" if where else str(k)[:80], v) for k, v in value.items()
            )
        elif isinstance(value, list):
            items = (
                (f"{where}[{i}]", v) for i, v in enumerate(value) if isinstance(v, (dict, list, _TooLong))
            )
        else:
            continue
        if depth >= max_depth:
            return f"{where or 'the document'}: nested deeper than {max_depth} levels"
        stack.extend((v, k, depth + 1) for k, v in items)
    return None


def parse_json(raw: bytes | str, *, max_bytes: int = MAX_FILE_BYTES, max_depth: int = MAX_DEPTH) -> Any:
    """JSON within limits: at most ``max_bytes``, ``max_depth`` levels of nesting, integer
    literals of at most MAX_NUMBER_CHARS characters. Raises ConfigError (a ValueError) saying what
    was wrong and where (the key path); never another exception, whatever ``raw`` holds."""
    if len(raw) > max_bytes:
        raise ConfigError(f"{len(raw)} bytes, more than the {max_bytes} accepted")
    try:
        # Only integers need the hook: float() of a long literal is linear and bounded by
        # the size limit; a hook on every float would double the time of a dataset.
        doc = json.loads(raw, parse_int=_bounded_number(int))
    except RecursionError as exc:
        raise ConfigError(f"nested deeper than {max_depth} levels") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"not UTF-8 text: {exc.reason} at byte {exc.start}") from exc
    except json.JSONDecodeError as exc:
        raise ConfigError(f"not valid JSON: {exc}") from exc
    except ValueError as exc:  # whatever else Python's parser refuses: never out of here
        raise ConfigError(f"not valid JSON: {exc}") from exc
    problem = _check_tree(doc, max_depth)
    if problem is not None:
        raise ConfigError(problem)
    return doc


def _read(path: Path, max_bytes: int = MAX_FILE_BYTES, what: str = "file") -> bytes:
    """The file's bytes; a file over ``max_bytes`` is refused by its size before a byte is
    read (a reload must not spend seconds on a file it will refuse)."""
    try:
        with path.open("rb") as f:
            size = os.fstat(f.fileno()).st_size
            if size > max_bytes:
                raise ConfigError(
                    f"{path}: {size} bytes, larger than the {max_bytes} bytes a {what} may hold"
                )
            raw = f.read(max_bytes + 1)  # a file growing while read (or a pipe) is bounded too
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    if len(raw) > max_bytes:
        raise ConfigError(f"{path}: larger than the {max_bytes} bytes a {what} may hold")
    return raw


_TOML_KEY = re.compile(r"^\s*([A-Za-z0-9_.\-\"' ]+?)\s*=")
_TOML_TABLE = re.compile(r"^\s*\[+\s*([^\]]+?)\s*\]")
_LONG_DIGITS = re.compile(r"[0-9_]{" + str(MAX_NUMBER_CHARS + 1) + ",}")


def _toml_locate(text: str) -> str:
    """Where in a TOML text the first over-long number is: 'line N, key T.K' (tomllib
    does not say which key an int() that failed belonged to)."""
    table = ""
    for n, line in enumerate(text.splitlines(), 1):
        header = _TOML_TABLE.match(line)
        if header and "=" not in line.split("]")[0]:
            table = header.group(1) + "."
        if _LONG_DIGITS.search(line):
            key = _TOML_KEY.match(line)
            return f"line {n}, key {table}{key.group(1) if key else '?'}"
    return "somewhere"


def load_toml(path: str | Path) -> dict[str, Any]:
    """A TOML file within the limits (size, depth, number length); ConfigError naming the
    file and the key otherwise."""
    path = Path(path)
    raw = _read(path)
    try:
        text = raw.decode("utf-8")
        doc = tomllib.loads(text)
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text: {exc.reason} at byte {exc.start}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    except RecursionError as exc:
        raise ConfigError(f"{path}: nested deeper than {MAX_DEPTH} levels") from exc
    except ValueError as exc:  # int() of more than 4300 digits: tomllib lets it through
        raise ConfigError(
            f"{path}: {_toml_locate(text)}: an integer longer than {MAX_NUMBER_CHARS} "
            f"characters ({str(exc)[:80]})"
        ) from exc
    problem = _check_tree(doc, MAX_DEPTH)
    if problem is None:
        problem = next(
            (f"{k}: an integer of more than {MAX_NUMBER_CHARS} digits" for k in _long_ints(doc)), None
        )
    if problem is not None:
        raise ConfigError(f"{path}: {problem}")
    return doc


def _long_ints(doc: Any, where: str = "") -> Iterable[str]:
    """Key paths of integers over MAX_NUMBER_CHARS digits (tomllib has no parse_int hook)."""
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _long_ints(v, f"{where}.{k}" if where else str(k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _long_ints(v, f"{where}[{i}]")
    elif isinstance(doc, int) and not isinstance(doc, bool) and doc.bit_length() > 3.33 * MAX_NUMBER_CHARS:
        yield where


def load_json(path: str | Path, max_bytes: int = MAX_FILE_BYTES, what: str = "file") -> dict[str, Any]:
    """A JSON file within the limits (`parse_json`; at most ``max_bytes``, for a ``what``);
    ConfigError naming the file and the key otherwise."""
    path = Path(path)
    try:
        doc = parse_json(_read(path, max_bytes, what), max_bytes=max_bytes)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
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

    def number(
        self,
        name: str,
        default: Any = _MISSING,
        *,
        low: float = -math.inf,
        high: float = math.inf,
        unit: str = "",
    ) -> float:
        value = self.get(name, default)
        if not _is_number(value) or not low <= value <= high:
            bounds = "" if (low, high) == (-math.inf, math.inf) else f" in [{low}, {high}]"
            raise self.fail(name, f"a finite number{bounds}{' (' + unit + ')' if unit else ''}", value)
        return float(value)

    def integer(
        self,
        name: str,
        default: Any = _MISSING,
        *,
        low: int | None = None,
        high: int | None = None,
        what: str = "an integer",
    ) -> int:
        value = self.get(name, default)
        if (
            not isinstance(value, int)
            or isinstance(value, bool)
            or (low is not None and value < low)
            or (high is not None and value > high)
        ):
            raise self.fail(name, what, value)
        return value

    def string(self, name: str, default: Any = _MISSING, *, choices: Iterable[str] | None = None) -> str:
        value = self.get(name, default)
        options = None if choices is None else list(choices)
        if not isinstance(value, str) or (options is not None and value not in options):
            raise self.fail(
                name,
                "a string" if options is None else "one of " + ", ".join(f'"{c}"' for c in options),
                value,
            )
        return value

    def numbers(
        self, name: str, length: int | None = None, default: Any = _MISSING, *, unit: str = ""
    ) -> list[float]:
        value = self.get(name, default)
        if (
            not isinstance(value, list)
            or (length is not None and len(value) != length)
            or not all(_is_number(v) for v in value)
        ):
            count = f"{length} " if length is not None else ""
            raise self.fail(name, f"{count}finite numbers{' (' + unit + ')' if unit else ''}", value)
        return [float(v) for v in value]

    def matrix(self, name: str, rows: int, cols: int, *, unit: str = "") -> list[list[float]]:
        """A rows x cols matrix of finite numbers, as a list of rows."""
        value = self.get(name)
        ok = (
            isinstance(value, list)
            and len(value) == rows
            and all(isinstance(r, list) and len(r) == cols and all(_is_number(v) for v in r) for r in value)
        )
        if not ok:
            raise self.fail(
                name, f"a {rows} x {cols} matrix of finite numbers" + (f" ({unit})" if unit else ""), value
            )
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
