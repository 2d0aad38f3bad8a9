"""Where the library's messages go on the command line: ``logging`` records of the
``tacest`` loggers to stderr, progress at level INFO, warnings as ``warning: ...``.

The library itself only logs (``logging.getLogger(__name__)``); a command calls
:func:`setup_logging` once with its ``--quiet`` flag (quiet: warnings and errors only).

The executor's progress records (tacest.parallel, attribute PROGRESS_ATTR: tasks done,
total, time left) are drawn as one bar, redrawn in place, when stderr is a terminal,
and printed as lines otherwise (a log file, a pipe).
"""

from __future__ import annotations

import logging
import sys


class _Format(logging.Formatter):
    """Progress lines as they are; warnings prefixed ``warning: ``."""

    def format(self, record):
        msg = record.getMessage()
        return f"warning: {msg}" if record.levelno >= logging.WARNING else msg


#: characters of the progress bar
BAR_WIDTH = 24


def progress_bar(p: dict) -> str:
    """``diagnosis [#########---------------] 12/43  28 %  1:20 elapsed, ~3:25 left``."""
    from tacest.parallel import format_seconds

    done, total = int(p["done"]), max(int(p["total"]), 1)
    filled = int(round(BAR_WIDTH * done / total))
    return (f"{p.get('what', 'tasks')} [{'#' * filled}{'-' * (BAR_WIDTH - filled)}] {done}/{total} "
            f"{done / total:4.0%}  {format_seconds(p['elapsed'])} elapsed, ~{format_seconds(p['eta'])} left")


def step_progress(quiet: bool, what: str):
    """``progress(done, total)`` for a loop of slow steps (an exploration): one
    :func:`progress_bar` line per step on stderr, the time left extrapolated from the
    steps so far (later steps, with more data, take longer); a no-op when quiet."""
    import time

    t_start = time.perf_counter()

    def progress(done, total):
        if quiet or done <= 0:
            return
        elapsed = time.perf_counter() - t_start
        sys.stderr.write("  " + progress_bar({"done": done, "total": total, "what": what, "elapsed": elapsed,
                                              "eta": elapsed / done * (total - done)}) + "\n")
        sys.stderr.flush()

    return progress


class _Handler(logging.StreamHandler):
    """The CLI's handler: progress records as a bar redrawn in place on a terminal."""

    _tacest_cli = True

    def __init__(self, stream=None):
        self._fixed = stream  # None: whatever sys.stderr is when a record comes
        super().__init__(stream)
        self._bar = False  # a bar is on the screen, without its newline

    @property
    def stream(self):
        return self._fixed if self._fixed is not None else sys.stderr

    @stream.setter
    def stream(self, value):  # StreamHandler.__init__ and setStream; sys.stderr: follow it
        self._fixed = None if value is sys.stderr else value

    def emit(self, record):
        from tacest.parallel import PROGRESS_ATTR

        progress = getattr(record, PROGRESS_ATTR, None)
        tty = bool(getattr(self.stream, "isatty", lambda: False)())
        if progress is None or not tty:
            if self._bar:
                self.stream.write("\n")
                self._bar = False
            super().emit(record)
            return
        try:
            self.acquire()
            line = progress_bar(progress)
            last = progress["done"] >= progress["total"]
            self.stream.write("\r" + line + ("\n" if last else "\x1b[K"))
            self.stream.flush()
            self._bar = not last
        finally:
            self.release()


def setup_logging(quiet: bool = False, stream=None) -> logging.Logger:
    """Send the ``tacest`` loggers' records to ``stream`` (stderr), at INFO (WARNING
    when ``quiet``); called again, it replaces its own handler."""
    logger = logging.getLogger("tacest")
    for h in list(logger.handlers):
        if getattr(h, "_tacest_cli", False):
            logger.removeHandler(h)
    handler = _Handler(stream)  # no stream: sys.stderr as it is at each record (a test may swap it)
    handler.setFormatter(_Format())
    logger.addHandler(handler)
    logger.setLevel(logging.WARNING if quiet else logging.INFO)
    logger.propagate = False
    return logger


def warn_fit_quality(est) -> None:
    """One warning line when the estimate ``est`` handed to the user is IPOPT's last
    iterate of a final stage that used up its iteration budget (kept because no start's
    converged fit reached a lower objective: solver.solve_from_starts), and one when it
    failed its goodness-of-fit test; one information line for a local misfit (consistent:
    tacest.estimation.fitquality).  The fits inside a diagnosis, which misfit on purpose,
    are not said here."""
    from tacest.estimation.result import not_converged_note

    note = not_converged_note(est)
    if note:
        logging.getLogger("tacest.estimate").warning(note)
    if est.consistent is False or est.local_misfit:
        from tacest.estimation.fitquality import quality_summary

        say = logging.getLogger("tacest.estimate")
        (say.warning if est.consistent is False else say.info)(quality_summary(est.fit_quality))
