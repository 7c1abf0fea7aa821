"""`python -m ftsensord` and the `ftsensord` script (pyproject.toml): the command line,
with `ftsensord run`'s stop and reload signals held while it imports.

The imports take most of a second on a small board, and systemctl stop may come then:
a SIGTERM would kill the daemon by the signal, half started. Held here (this module
imports nothing heavy) and handed to `daemon.run`, it is a clean exit 0 instead.
"""

import signal
import sys

EARLY_SIGNALS: list[int] = []


def main() -> int:
    if sys.argv[1:2] == ["run"]:  # the daemon only: every other command keeps the defaults
        for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            signal.signal(signum, lambda signum, frame: EARLY_SIGNALS.append(signum))
    from ftsensord.cli import main as cli_main

    return cli_main(early_signals=EARLY_SIGNALS)


if __name__ == "__main__":
    raise SystemExit(main())
