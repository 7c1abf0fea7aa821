"""Floor 13, the command line: `ftsensord` by command group.

- `parser`: the parser and `main`; `options`: what several commands share.
- `service`: `run` and the commands that ask the running daemon (status, tare, untare, set,
  reload); `streams`: echo, record, plot; `hardware`: scan, doctor; `calibrate`: dataset,
  calibrate. Each command's work is done in its floor; a command imports it when it runs, so
  `ftsensord status` does not load the calibration's fits.

May import every floor.
"""

from ftsensord.cli.parser import build_parser, main

__all__ = ["build_parser", "main"]
