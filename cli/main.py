"""Entry point: the ``tacest`` click group, and the one place where errors become
one line on stderr with exit status 2.

Subcommands live in their own modules and are imported only when invoked, so
``tacest --help`` stays fast.
"""

from __future__ import annotations

import importlib
import os
import sys

import click

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


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="tacest")
def cli():
    """tacest: learn an unknown rigid object by touch.

    Stages chain over HDF5 files (see docs/formats.md):
    record -> estimate -> plan -> eval / diagnose.
    """


def main(argv=None):
    """Run the CLI; every failure is one line on stderr and exit status 2.

    Set TACEST_DEBUG=1 to see the Python traceback of an unexpected error.
    """
    from tacest.errors import TacestError

    try:
        rv = cli.main(args=argv, prog_name="tacest", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("tacest: interrupted", err=True)
        sys.exit(130)
    except click.ClickException as exc:
        # usage errors: unknown option, bad value, missing argument
        ctx_hint = ""
        if isinstance(exc, click.UsageError) and exc.ctx is not None:
            ctx_hint = f" (see '{exc.ctx.command_path} --help')"
        click.echo(f"tacest: error: {exc.format_message()}{ctx_hint}", err=True)
        sys.exit(2)
    except TacestError as exc:
        click.echo(f"tacest: error: {exc}", err=True)
        sys.exit(2)
    except KeyboardInterrupt:
        click.echo("tacest: interrupted", err=True)
        sys.exit(130)
    except Exception as exc:  # an input we failed to validate, or a bug: still one line
        if os.environ.get("TACEST_DEBUG"):
            raise
        msg = str(exc).splitlines()[0] if str(exc) else ""
        click.echo(f"tacest: error: {exc.__class__.__name__}: {msg} "
                   "(unexpected; set TACEST_DEBUG=1 for a traceback)", err=True)
        sys.exit(2)
    sys.exit(rv if isinstance(rv, int) else 0)


if __name__ == "__main__":
    main()
