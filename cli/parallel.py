"""``--workers`` and ``--scheduler``: where a command's independent fits run
(tacest.parallel, docs/parallel.md)."""

from __future__ import annotations

import click

WORKERS_HELP = ("Run the fits on a local Dask cluster of N worker processes (auto: one per core); "
                "1: in this process, one after another (the default, or $TACEST_WORKERS).")
SCHEDULER_HELP = ("Send the fits to the Dask scheduler at ADDRESS (e.g. tcp://10.0.0.5:8786; default "
                  "$TACEST_SCHEDULER). See docs/parallel.md.")


def parallel_options(command):
    """Add ``--workers`` and ``--scheduler`` to a click command (parameters ``workers``
    and ``scheduler``, None when not given)."""
    command = click.option("--scheduler", default=None, metavar="ADDRESS", help=SCHEDULER_HELP)(command)
    return click.option("--workers", default=None, metavar="N|auto", help=WORKERS_HELP)(command)


def executor(workers, scheduler):
    """The executor of the options (a context manager; the environment fills in what the
    options leave open)."""
    from tacest.parallel import open_executor

    return open_executor(workers, scheduler)
