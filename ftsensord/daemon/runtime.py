"""The files the daemon made in its runtime folders (ipc sockets, lock files), watched.

logind deletes /run/user/<uid> at logout, and a /tmp cleaner deletes old files: a
daemon whose folder is gone runs on unreachable, and a second daemon can start in a
new folder of the same name. Each file is known by its inode as made; `lost` says
which is gone or replaced (the daemon then exits non-zero, so that systemd restarts it
with a new folder), and `remove_own` deletes only files that are still the ones this
daemon made, never a second daemon's under the same name.
"""

from __future__ import annotations

import os
from pathlib import Path


class RuntimeFiles:
    """Files made by this process, by path and identity (st_dev, st_ino)."""

    def __init__(self) -> None:
        self.files: dict[Path, tuple[int, int]] = {}
        self.removable: list[Path] = []

    def made(self, path: Path, fd: int | None = None, *, remove: bool = True) -> None:
        """``path`` was just made (or opened) by this process (``fd``: its open descriptor,
        whose identity cannot have been swapped since); ``remove``: deleted at exit (a lock
        file is not: a second daemon may have it open, waiting)."""
        st = os.fstat(fd) if fd is not None else os.lstat(path)
        self.files[path] = (st.st_dev, st.st_ino)
        if remove:
            self.removable.append(path)

    def _ours(self, path: Path) -> bool:
        try:
            st = os.lstat(path)
        except FileNotFoundError:
            return False
        return (st.st_dev, st.st_ino) == self.files[path]

    def lost(self) -> str | None:
        """What is gone or replaced (a message naming the file), or None: all in place."""
        for path in self.files:
            if not self._ours(path):
                what = "replaced by another" if os.path.lexists(path) else "deleted"
                return (
                    f"{path} was {what} (its folder removed? logind does so at logout, "
                    "a /tmp cleaner after days): clients can no longer reach this daemon"
                )
        return None

    def remove_own(self) -> None:
        """Delete each removable file that is still the one made here; leave any other alone
        (a second daemon's socket made between the check and the unlink, microseconds
        apart, is the one case left: that daemon then sees it lost and exits for a restart)."""
        for path in self.removable:
            if self._ours(path):
                path.unlink()
