"""Ctrl-C during an IPOPT solve ends the command, never just the solve.

IPOPT, through CasADi, turns a KeyboardInterrupt raised inside a solve (in a callback or
a function evaluation) into a return status (``User_Requested_Stop``, or
``NonIpopt_Exception_Thrown`` when it arrived during an evaluation) and carries on; the
estimator would then take it for a failed stage, try another start and write an
estimate.  Every solve is therefore wrapped::

    with watch_interrupts() as watch:
        sol = solver(**args)
    raise_if_interrupted(solver.stats()["return_status"], watch)

:func:`watch_interrupts` notes a SIGINT that arrives during the block (and still raises
KeyboardInterrupt at once, so IPOPT stops at its next check); :func:`raise_if_interrupted`
raises KeyboardInterrupt after the solve if one arrived, or if IPOPT says the user
stopped it.  The command line turns KeyboardInterrupt into "tacest: interrupted" and
exit status 130 (cli/main.py).
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading

#: IPOPT return statuses that mean "stopped by the user" (tacest's iteration callbacks
#: never ask IPOPT to stop, so this status comes from an interrupt only)
INTERRUPT_STATUSES = ("User_Requested_Stop",)
#: CasADi's warning when an interrupt arrives during a function evaluation: not shown
#: (the command line says "tacest: interrupted" instead)
_CASADI_INTERRUPT_WARNING = "KeyboardInterruptException"


class InterruptWatch:
    """What :func:`watch_interrupts` saw: ``interrupted`` is True once a SIGINT arrived."""

    def __init__(self):
        self.interrupted = False


class _DropCasadiInterruptWarning:
    """sys.stderr during a watched solve: passes every line on except CasADi's warning
    about the KeyboardInterrupt it caught (CasADi writes that line in pieces, so text is
    passed on line by line; :meth:`close` passes on an unfinished last line)."""

    def __init__(self, stream):
        self._stream = stream
        self._line = ""

    def write(self, text):
        *lines, self._line = (self._line + text).split("\n")
        for line in lines:
            if _CASADI_INTERRUPT_WARNING not in line:
                self._stream.write(line + "\n")
        return len(text)

    def close(self):
        if self._line and _CASADI_INTERRUPT_WARNING not in self._line:
            self._stream.write(self._line)
        self._line = ""

    def __getattr__(self, name):
        return getattr(self._stream, name)


@contextlib.contextmanager
def watch_interrupts():
    """Note a SIGINT that arrives inside the block (yields an :class:`InterruptWatch`).

    The previous SIGINT handler still runs (Python's default raises KeyboardInterrupt);
    a handler that ignores SIGINT keeps it ignored.  Outside the main thread, where no
    signal handler can be set, the watch sees only what IPOPT's status tells.
    """
    watch = InterruptWatch()
    if threading.current_thread() is not threading.main_thread():
        yield watch
        return
    previous = signal.getsignal(signal.SIGINT)
    if previous is signal.SIG_IGN:
        yield watch
        return

    def note(signum, frame):
        watch.interrupted = True
        if callable(previous):
            previous(signum, frame)
        else:  # SIG_DFL or a handler installed outside Python: end as Python's default would
            raise KeyboardInterrupt

    signal.signal(signal.SIGINT, note)
    stderr = sys.stderr
    sys.stderr = filtered = _DropCasadiInterruptWarning(stderr)
    try:
        yield watch
    finally:
        sys.stderr = stderr
        filtered.close()
        signal.signal(signal.SIGINT, previous)


def raise_if_interrupted(status: str, watch: InterruptWatch | None = None) -> None:
    """Raise KeyboardInterrupt if IPOPT's return ``status`` says the user stopped the
    solve or ``watch`` saw a SIGINT during it."""
    if status in INTERRUPT_STATUSES or (watch is not None and watch.interrupted):
        raise KeyboardInterrupt
