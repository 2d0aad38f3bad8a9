"""Entry point: the ``tacest`` click group, and the one place where errors and
interrupts become one line on stderr and an exit status (docs/index.md, "Exit status"):

- 0 (EXIT_OK): success; also ``tacest`` with no arguments, which prints the help on stdout;
- 2 (EXIT_BAD_INPUT): bad input or environment — a usage error, a bad file, an output
  tacest must not write, a failed solve: ``tacest: error: ...``;
- 3 (EXIT_BUG): an unexpected exception, a bug in tacest: ``tacest: internal error: ...``
  (TACEST_DEBUG=1 shows the traceback);
- 130 (EXIT_INTERRUPTED): Ctrl-C (SIGINT): ``tacest: interrupted``; no output is written
  and an existing output is left as it was.

Subcommands live in their own modules and are imported only when invoked, so
``tacest --help`` stays fast.
"""

from __future__ import annotations

import importlib
import os
import sys

import click

EXIT_OK = 0
EXIT_BAD_INPUT = 2
EXIT_BUG = 3
#: 128 + SIGINT, as a shell reports a program ended by Ctrl-C
EXIT_INTERRUPTED = 130

#: command name -> (module, attribute, one-line help)
COMMANDS = {
    "record": ("tacest.cli.record", "record", "Record a run: simulation, serial tactile rig or tactile video."),
    "estimate": ("tacest.cli.estimate", "estimate", "Estimate pose trajectory, shape, mass, inertia, friction."),
    "plan": ("tacest.cli.plan", "plan", "Choose the next poke by expected information gain."),
    "explore": ("tacest.cli.explore", "explore", "Closed loop in simulation: poke, estimate, plan, repeat."),
    "eval": ("tacest.cli.evaluate", "eval_cmd", "Score an estimate against a run's truth (Chamfer, pose, params)."),
    "diagnose": ("tacest.cli.diagnose", "diagnose", "Where and why the model disagrees with recordings."),
    "export": ("tacest.cli.export", "export", "Export the estimated object: MJCF, URDF, SDF, OBJ, STL, GLB."),
    "view": ("tacest.cli.view", "view", "Animate a run or an estimate: GIF/MP4 (2-D), interactive HTML (3-D)."),
    "demo": ("tacest.cli.demo", "demo", "Run the whole pipeline on a built-in simulated example."),
    "config": ("tacest.cli.config", "config", "Print the estimator's default settings (TOML)."),
}


class LazyGroup(click.Group):
    """A click group whose subcommands are imported on first use."""

    def list_commands(self, ctx):
        return list(COMMANDS)

    def get_command(self, ctx, name):
        if name not in COMMANDS:
            return None
        module, attr, _ = COMMANDS[name]
        try:
            return getattr(importlib.import_module(module), attr)
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith("tacest"):
                return _unavailable(name, COMMANDS[name][2])
            raise

    def format_commands(self, ctx, formatter):
        rows = [(name, COMMANDS[name][2]) for name in COMMANDS]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


def _unavailable(name, help_text):
    @click.command(name=name, help=help_text + " (not available in this version)",
                   context_settings={"ignore_unknown_options": True})
    @click.argument("args", nargs=-1, type=click.UNPROCESSED)
    def cmd(args):
        raise click.UsageError(f"'tacest {name}' is not implemented in this version yet")

    return cmd


@click.group(cls=LazyGroup, invoke_without_command=True, no_args_is_help=False,
             context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="tacest")
@click.pass_context
def cli(ctx):
    """tacest: learn an unknown rigid object by touch.

    Stages chain over HDF5 files (see docs/formats.md):
    record -> estimate -> plan -> eval / diagnose.
    """
    if ctx.invoked_subcommand is None:  # bare `tacest`: the help, as `tacest --help`
        click.echo(ctx.get_help())


def _first_line(exc) -> str:
    text = str(exc)
    return text.splitlines()[0] if text else ""


def _caused_by_interrupt(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is in the cause or context chain of ``exc``: a SIGINT
    that arrives while a C extension function runs surfaces as ``SystemError: ...
    returned a result with an exception set`` whose cause is the KeyboardInterrupt."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def main(argv=None):
    """Run the CLI; every failure is one line on stderr and an exit status (module doc).

    Set TACEST_DEBUG=1 to see the Python traceback of an unexpected error.
    """
    from tacest.errors import TacestError
    from tacest.interrupt import interrupt_latch, raise_if_noted
    from tacest.provenance import set_command_line

    args = list(sys.argv[1:] if argv is None else argv)
    set_command_line(args)
    try:
        with interrupt_latch():  # a Ctrl-C that a C library swallowed still ends the command
            rv = cli.main(args=args, prog_name="tacest", standalone_mode=False)
            raise_if_noted()
    except (click.exceptions.Abort, KeyboardInterrupt):
        click.echo("tacest: interrupted", err=True)
        sys.exit(EXIT_INTERRUPTED)
    except click.ClickException as exc:
        # usage errors: unknown option, bad value, missing argument
        ctx_hint = ""
        if isinstance(exc, click.UsageError) and exc.ctx is not None:
            ctx_hint = f" (see '{exc.ctx.command_path} --help')"
        click.echo(f"tacest: error: {_first_line(exc.format_message())}{ctx_hint}", err=True)
        sys.exit(EXIT_BAD_INPUT)
    except TacestError as exc:
        click.echo(f"tacest: error: {_first_line(exc)}", err=True)
        sys.exit(EXIT_BAD_INPUT)
    except OSError as exc:  # the environment: disk full, permissions, a vanished file
        where = f"{exc.filename}: " if exc.filename else ""
        click.echo(f"tacest: error: {where}{exc.strerror or _first_line(exc) or exc.__class__.__name__}", err=True)
        sys.exit(EXIT_BAD_INPUT)
    except Exception as exc:  # a bug: still one line, and its own status
        if _caused_by_interrupt(exc):  # Ctrl-C inside a C extension's call (e.g. CasADi's DM.__array__)
            click.echo("tacest: interrupted", err=True)
            sys.exit(EXIT_INTERRUPTED)
        if os.environ.get("TACEST_DEBUG"):
            raise
        click.echo(f"tacest: internal error: {exc.__class__.__name__}: {_first_line(exc)} "
                   "(a bug in tacest; set TACEST_DEBUG=1 for a traceback)", err=True)
        sys.exit(EXIT_BUG)
    finally:
        set_command_line(None)
    sys.exit(rv if isinstance(rv, int) else EXIT_OK)


if __name__ == "__main__":
    main()
