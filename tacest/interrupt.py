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

Python callbacks run from C through cffi (pymunk's arbiter iteration, every physics
substep of the 2-D simulator) lose a KeyboardInterrupt raised inside them: cffi prints
it as "Exception ignored" and the simulation goes on.  The simulators therefore run
inside :func:`deferred_interrupts`, where a SIGINT is only noted, and call
:func:`check_interrupt` after each substep, outside any callback, which raises it::

    with deferred_interrupts():
        for ...:
            world.step(...)        # World.step ends with check_interrupt()

Behind both, the command line runs every command inside :func:`interrupt_latch`: its
SIGINT handler notes the signal process-wide before raising, and every other handler
here chains to it.  Whatever catches a KeyboardInterrupt on the way (a Ctrl-C seen in a
diagnosis ran on to its end once, exit 0), the next solve
(:func:`raise_if_interrupted`), the commit of any output (tacest.io.outputs) and the
end of the command raise it again (:func:`raise_if_noted`).
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

    The previous SIGINT handler still runs (Python's default raises KeyboardInterrupt).
    Where no handler may be replaced (:func:`_handler_to_replace`: outside the main
    thread, under a handler that ignores SIGINT or one installed outside Python, which
    Python could not put back) the watch sees only what IPOPT's status tells.
    """
    watch = InterruptWatch()
    previous = _handler_to_replace()
    if previous is None:
        yield watch
        return

    def note(signum, frame):
        watch.interrupted = True
        if callable(previous):
            previous(signum, frame)
        else:  # SIG_DFL: end as Python's default would
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


def _handler_to_replace():
    """The SIGINT handler a block of this module may replace, or None where it must not:
    outside the main thread (no handler can be set there), under a handler that ignores
    SIGINT (it stays ignored), or one installed outside Python."""
    if threading.current_thread() is not threading.main_thread():
        return None
    previous = signal.getsignal(signal.SIGINT)
    return None if previous is signal.SIG_IGN else previous


class _Latch:
    """The state of :func:`interrupt_latch`: whether a SIGINT reached this process
    while it was on."""

    def __init__(self):
        self.noted = False


_LATCH = _Latch()


@contextlib.contextmanager
def interrupt_latch():
    """For the command line, around a command: every SIGINT is also noted in a
    process-wide latch, which :func:`raise_if_noted` reads.

    The handler raises KeyboardInterrupt as Python's default does, and every handler of
    this module chains to it, so a SIGINT is noted wherever it lands.  A KeyboardInterrupt
    can still be lost after that: a C library that runs Python code (CasADi's
    evaluations, cffi's callbacks) may catch it and go on, and one raised in a weakref
    callback or a ``__del__`` that the garbage collector runs is only printed ("Exception
    ignored in ...": seen in a loop's estimate, and the likely way a diagnosis once ran
    on to exit 0); inside the latch nothing is printed for it.  The latch keeps the command
    from ending as if nothing happened: every output is committed only after
    :func:`raise_if_noted` (tacest.io.outputs), and so is every solve's result
    (:func:`raise_if_interrupted`).  At the end of the block the previous handler is back
    and the latch cleared.  Only in the main thread (elsewhere it does nothing); a
    handler that ignores SIGINT keeps it ignored.
    """
    previous = _handler_to_replace()
    if previous is None:
        yield
        return

    def latch(signum, frame):
        _LATCH.noted = True
        raise KeyboardInterrupt

    unraisable = sys.unraisablehook

    def quiet_when_noted(info):
        # a KeyboardInterrupt raised where Python cannot raise it (a weakref callback or
        # a __del__ run by the garbage collector, a cffi callback) would be printed as
        # "Exception ignored in ..." with a traceback, and lost: the latch has it
        if issubclass(info.exc_type, KeyboardInterrupt) and _LATCH.noted:
            return
        unraisable(info)

    _LATCH.noted = False
    signal.signal(signal.SIGINT, latch)
    sys.unraisablehook = quiet_when_noted
    try:
        yield
    finally:
        sys.unraisablehook = unraisable
        signal.signal(signal.SIGINT, previous)
        _LATCH.noted = False


def raise_if_noted() -> None:
    """Raise KeyboardInterrupt if the latch (:func:`interrupt_latch`) noted a
    SIGINT: whatever caught its KeyboardInterrupt meanwhile, the command ends as
    interrupted.  Nothing without a latch, and nothing outside the main thread (Python
    delivers a SIGINT to the main thread, which decides: a live recording's snapshot
    writer, for one, must not end on a Ctrl-C that the recording takes as "stop and
    keep")."""
    if _LATCH.noted and threading.current_thread() is threading.main_thread():
        raise KeyboardInterrupt


def accept_interrupt() -> None:
    """For code whose Ctrl-C means "stop here and keep what you have" (a live
    recording, tacest.sensors.serial_rig), having caught its KeyboardInterrupt: the
    latch forgets that SIGINT, so the command goes on to write its output.  A later
    SIGINT is noted again."""
    _LATCH.noted = False


def raise_if_interrupted(status: str, watch: InterruptWatch | None = None) -> None:
    """Raise KeyboardInterrupt if IPOPT's return ``status`` says the user stopped the
    solve, ``watch`` saw a SIGINT during it, or the latch noted one
    (:func:`raise_if_noted`)."""
    if status in INTERRUPT_STATUSES or (watch is not None and watch.interrupted):
        raise KeyboardInterrupt
    raise_if_noted()


class _Deferral:
    """The state of :func:`deferred_interrupts`: how deep its blocks are nested, the
    SIGINT handler it replaced, and a SIGINT noted meanwhile ((signum, frame) or None)."""

    def __init__(self):
        self.depth = 0
        self.previous = None
        self.pending = None


_DEFERRAL = _Deferral()


@contextlib.contextmanager
def deferred_interrupts():
    """Inside the block a SIGINT is only noted, never raised where it lands (which may be
    a cffi callback that would swallow it); :func:`check_interrupt` delivers it at a safe
    point, and the end of the block at the latest.  Delivering means running the
    previous handler (Python's default raises KeyboardInterrupt).

    Blocks nest (the outermost one holds the handler).  A handler that ignores SIGINT
    keeps it ignored; outside the main thread, where no handler can be set, the block
    changes nothing.
    """
    d = _DEFERRAL
    if d.depth:
        d.depth += 1
        try:
            yield
        finally:
            d.depth -= 1
        return
    previous = _handler_to_replace()
    if previous is None:
        yield
        return

    def note(signum, frame):
        d.pending = (signum, frame)

    d.depth, d.previous, d.pending = 1, previous, None
    signal.signal(signal.SIGINT, note)
    try:
        yield
        check_interrupt()  # a SIGINT noted after the block's last check
    finally:
        signal.signal(signal.SIGINT, previous)
        d.depth, d.previous, d.pending = 0, None, None


def check_interrupt() -> None:
    """Deliver a SIGINT that :func:`deferred_interrupts` noted (KeyboardInterrupt with
    Python's default handler); nothing otherwise.  Cheap: called every physics substep."""
    d = _DEFERRAL
    if d.pending is None:
        raise_if_noted()
        return
    signum, frame = d.pending
    d.pending = None
    if callable(d.previous):
        d.previous(signum, frame)
    else:  # SIG_DFL or a handler installed outside Python: end as Python's default would
        raise KeyboardInterrupt
