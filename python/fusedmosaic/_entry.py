"""The ``fusedmosaic`` command's entry point: loads the command line (NumPy, OpenCV, the core:
about a second, in the import of fusedmosaic.cli and in building its parser) inside a guard, so
that a Ctrl-C that early ends as it does later ("fusedmosaic: interrupted", exit 130) rather
than with a traceback. Nothing is written before the command runs, and cli.main handles an
interrupt of the command itself (removing what it staged)."""

from __future__ import annotations

import sys


def main() -> int:
    try:
        from fusedmosaic.cli import main as cli_main

        return cli_main()
    except KeyboardInterrupt:
        print("fusedmosaic: interrupted", file=sys.stderr)
        return 130
