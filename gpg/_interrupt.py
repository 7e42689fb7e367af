"""Ctrl-C at safe points: a SIGINT becomes a flag that long loops check between steps.

Python delivers a KeyboardInterrupt only between bytecodes; while XLA compiles or runs, it
arrives when the C++ call returns, and an interpreter torn down around XLA's live threads
crashed (SIGSEGV, 3 of 3 tries during ``generate_data``'s compilation). Inside
:func:`deferred`, the first Ctrl-C only sets a flag; :func:`check`, called by the generator's
chunk loop and the comparison's model loop, then raises KeyboardInterrupt in ordinary Python
code, where ``finally`` blocks remove temporary files and the entry point exits with a message.
A second Ctrl-C aborts at once (``os._exit``), for when the next safe point is far away.

Outside :func:`deferred` nothing is installed and :func:`check` does nothing: importing gpg
changes no signal handling.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading

_flag = threading.Event()


def check() -> None:
    """Raise KeyboardInterrupt if a Ctrl-C arrived inside :func:`deferred`."""
    if _flag.is_set():
        _flag.clear()
        raise KeyboardInterrupt


@contextlib.contextmanager
def deferred():
    """Turn SIGINT into a flag for :func:`check` while the block runs (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        if _flag.is_set():
            sys.stderr.write("\nsecond interrupt: aborting now\n")
            os._exit(130)
        _flag.set()
        sys.stderr.write(
            "\ninterrupt received: stopping at the next safe point (Ctrl-C again aborts now)\n"
        )

    previous = signal.signal(signal.SIGINT, handler)
    _flag.clear()
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _flag.clear()
