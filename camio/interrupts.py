"""Ctrl-C held over the steps it must not cut short (issue 24).

A terminal's Ctrl-C reaches every process of the group. Cut short, two steps of a render went wrong: starting
worker processes (a worker still importing torch printed its own KeyboardInterrupt traceback; one whose parent
was interrupted while launching it printed `EOFError: Ran out of input`), and loading Mitsuba (a
KeyboardInterrupt inside its extension's import came back as an ImportError, read as "no Mitsuba here", and
the render went on with our tracer to exit 0). `held()` defers SIGINT over such a step and acts on it after.

    held()        context manager: SIGINT blocked in this thread (children started inside inherit the block and
                  never see the Ctrl-C) and, in the main thread, held and acted on once the step is done
    INTERRUPTS    SIGINTs recorded by a handler that appends to it (the `renderer` command's): a render
                  waiting on its workers stops at its next wake, even where the exception was dropped
"""
from __future__ import annotations

import contextlib
import signal
import sys
import threading

INTERRUPTS: list = []


@contextlib.contextmanager
def held():
    """SIGINT held over the block: blocked in this thread, and in the main thread, where Python runs signal
    handlers, caught and acted on after the block as it would have been (the handler called, or the default
    action). Outside the main thread only the block applies (other threads take the signal)."""
    if not hasattr(signal, "pthread_sigmask"):  # pragma: no cover - not on POSIX
        yield
        return
    main = threading.current_thread() is threading.main_thread()
    caught: list = []
    handler = signal.getsignal(signal.SIGINT) if main else None
    swap = handler not in (signal.SIG_IGN, None)  # None: a handler not set from Python, left alone
    if swap:
        signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # a SIGINT pending here is caught too (handlers run now)
        if swap:
            signal.signal(signal.SIGINT, handler)
        if caught:  # over any exception: the user asked to stop
            if callable(handler):
                handler(signal.SIGINT, sys._getframe())
            else:  # SIG_DFL: end as the signal ends a process
                signal.raise_signal(signal.SIGINT)


def interrupt_on_sigterm():
    """SIGTERM ends the command like Ctrl-C (temporary files removed, exit 130); returns the old handler."""

    def handler(signum, frame):
        raise KeyboardInterrupt

    try:
        return signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        return None
