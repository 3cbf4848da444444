"""The ``fusedmosaic`` command's entry point: loads the command line (NumPy, OpenCV, the core:
about a second, in the import of fusedmosaic.cli and in building its parser) inside a guard, so
that a Ctrl-C, SIGTERM or SIGHUP that early ends as it does later ("fusedmosaic: interrupted",
exit 130) rather than with a traceback or a bare signal death. Nothing is written before the
command runs, and cli.main handles an interrupt of the command itself (removing what it
staged). Light on purpose: the package's __init__ imports nothing heavy either."""

from __future__ import annotations

import contextlib
import signal
import sys
import threading


class OutputsWrittenInterrupt(KeyboardInterrupt):
    """An interrupt (Ctrl-C, SIGTERM, SIGHUP) that arrived while io.output.OutputWriter moved
    its outputs into ``out_dir``, held until they all were and delivered then: the outputs are
    complete, and the command says so rather than 'interrupted' alone, which tells that nothing
    was left. (Here, not in io.output, so that cli.main tells it without loading OpenCV.)"""

    def __init__(self, out_dir) -> None:
        super().__init__(str(out_dir))
        self.out_dir = out_dir


@contextlib.contextmanager
def signals_as_interrupt():
    """SIGTERM / SIGHUP (a closed terminal, `timeout`, a scheduler's stop) end any command as
    Ctrl-C does, so its staged outputs are removed; a signal ignored by whoever started us stays
    ignored (nohup: SIGHUP). Only the main thread can set handlers (elsewhere: unchanged).
    Nested uses restore the enclosing one's handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        raise KeyboardInterrupt

    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGTERM, signal.SIGHUP)
                if signal.getsignal(sig) is not signal.SIG_IGN}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def main() -> int:
    try:
        with signals_as_interrupt():
            from fusedmosaic.cli import main as cli_main

            return cli_main()
    except KeyboardInterrupt:
        print("fusedmosaic: interrupted", file=sys.stderr)
        return 130
