"""Where the library's messages go on the command line: ``logging`` records of the
``tacest`` loggers to stderr, progress at level INFO, warnings as ``warning: ...``.

The library itself only logs (``logging.getLogger(__name__)``); a command calls
:func:`setup_logging` once with its ``--quiet`` flag (quiet: warnings and errors only).
"""

from __future__ import annotations

import logging
import sys


class _Format(logging.Formatter):
    """Progress lines as they are; warnings prefixed ``warning: ``."""

    def format(self, record):
        msg = record.getMessage()
        return f"warning: {msg}" if record.levelno >= logging.WARNING else msg


def setup_logging(quiet: bool = False, stream=None) -> logging.Logger:
    """Send the ``tacest`` loggers' records to ``stream`` (stderr), at INFO (WARNING
    when ``quiet``); called again, it replaces its own handler."""
    logger = logging.getLogger("tacest")
    for h in list(logger.handlers):
        if getattr(h, "_tacest_cli", False):
            logger.removeHandler(h)
    handler = logging.StreamHandler(stream or sys.stderr)
    handler._tacest_cli = True
    handler.setFormatter(_Format())
    logger.addHandler(handler)
    logger.setLevel(logging.WARNING if quiet else logging.INFO)
    logger.propagate = False
    return logger
