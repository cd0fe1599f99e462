"""The `nhjax` command's entry point, outside the `nhjax` package: importing the package
imports JAX, XLA and every method, which takes seconds (more on a loaded machine), and a
Ctrl-C in that time would end the command with a traceback. This module installs the
command's interrupt handler first, then imports the package (`nhjax._cli.main`)."""

import os
import signal
import sys
import threading


def _leave_on_interrupt(*_) -> None:
    print("\nnhjax: interrupted", file=sys.stderr, flush=True)
    os._exit(130)


def main(argv=None) -> int:
    """`nhjax._cli.main`, with Ctrl-C handled from the first instruction on: exit status
    130 and one line, whether it comes while the package imports or later. An ignored
    SIGINT (nohup) stays ignored."""
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) not in (
        signal.SIG_IGN,
        None,
    ):
        signal.signal(signal.SIGINT, _leave_on_interrupt)
    from nhjax._cli import main as command

    return command(argv)


if __name__ == "__main__":
    sys.exit(main())
