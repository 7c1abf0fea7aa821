"""Where the daemon's files are: files named in a configuration (relative to it, or
shipped in the package as ``builtin:NAME``) and the private folder for its sockets.

May import: `docfile`, `errors` (floor 1).
"""

from __future__ import annotations

import os
import stat
from importlib import resources
from pathlib import Path

from ftsensord.docfile import Table
from ftsensord.errors import ConfigError

BUILTIN = "builtin:"


def builtin_path(name: str) -> Path:
    """A file shipped in the package's data folder."""
    return Path(str(resources.files("ftsensord") / "data" / name))


def resolve_file(table: Table, key: str, value: str) -> Path:
    """``table[key]``'s file: ``builtin:NAME``, or a path relative to the table's file's folder;
    refused (naming the file and key) unless it exists."""
    if value.startswith(BUILTIN):
        path = builtin_path(value[len(BUILTIN) :])
    else:
        path = Path(value).expanduser()
        if not path.is_absolute():
            path = table.path.parent / path
    if not path.is_file():
        raise table.fail(
            key, "an existing file (relative to the configuration's folder, or builtin:NAME)", value
        )
    return path


def runtime_dir() -> Path:
    """Where the daemon's sockets go: systemd's RuntimeDirectory, else the user's
    ($XDG_RUNTIME_DIR/ftsensord), else /tmp/ftsensord-<uid> (sudo, cron, containers).
    Only a name: `ensure_private_dir` creates and checks it before use."""
    if os.environ.get("RUNTIME_DIRECTORY"):
        return Path(os.environ["RUNTIME_DIRECTORY"].split(":")[0])
    if os.environ.get("XDG_RUNTIME_DIR"):
        return Path(os.environ["XDG_RUNTIME_DIR"]) / "ftsensord"
    return Path(f"/tmp/ftsensord-{os.getuid()}")


def check_private_dir(path: Path, owner: int | None = None) -> None:
    """Refuse a folder for sockets that someone else could swap them in: a symlink, not a
    folder, not owned by ``owner`` (default: this process's user), or writable by its group
    or others. ``owner=-1``: any owner, but then its parent must be root's and not writable
    by others (only root, or systemd for the service, can have made it)."""
    try:
        st = os.lstat(path)
    except FileNotFoundError as exc:
        raise ConfigError(f"{path}: the runtime folder does not exist") from exc
    uid = os.geteuid() if owner is None else owner
    why = None
    if stat.S_ISLNK(st.st_mode):
        why = "is a symbolic link"
    elif not stat.S_ISDIR(st.st_mode):
        why = "is not a folder"
    elif uid != -1 and st.st_uid != uid:
        why = f"belongs to uid {st.st_uid}, not to uid {uid}"
    elif st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        who = "others" if st.st_mode & stat.S_IWOTH else "its group"
        why = f"is writable by {who} (mode {st.st_mode & 0o7777:04o})"
    elif uid == -1:
        parent = os.lstat(path.parent)
        if parent.st_uid != 0 or parent.st_mode & stat.S_IWOTH:
            why = f"is in {path.parent}, which root alone does not control"
    if why is not None:
        raise ConfigError(
            f"{path}: refusing this runtime folder: it {why}; another user could put their "
            "sockets in place of the daemon's. Remove it (or fix its owner and mode 0700), "
            "or set RUNTIME_DIRECTORY or XDG_RUNTIME_DIR"
        )


def ensure_private_dir(path: Path) -> Path:
    """Create ``path`` mode 0700 if missing (its missing parents too), then check it with
    `check_private_dir` (lstat: a symlink put there meanwhile is refused, never followed)."""
    if not os.path.lexists(path):
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        try:
            os.mkdir(path, 0o700)  # one syscall: exists already (someone else's?) or ours
        except FileExistsError:
            pass  # made meanwhile: the check below decides
    check_private_dir(path)
    return path
