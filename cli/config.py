"""``tacest config``: the estimator's settings file as shipped with tacest."""

from __future__ import annotations

from importlib import resources

import click

#: the settings file shipped inside the package (setup.cfg [options.package_data])
DEFAULTS_RESOURCE = ("tacest", "configs/estimate.toml")


def defaults_toml() -> str:
    """The text of the shipped defaults file, tacest/configs/estimate.toml."""
    package, name = DEFAULTS_RESOURCE
    return resources.files(package).joinpath(name).read_text(encoding="utf-8")


@click.command()
@click.option("--defaults", is_flag=True, help="Print every estimator setting at its default, with its meaning (TOML).")
def config(defaults):
    """Print the estimator's default settings: a TOML file listing every key of
    `tacest estimate --config FILE` with its default, unit and meaning.  Save it, change
    what you need, and pass it with --config."""
    if not defaults:
        raise click.UsageError("give --defaults (print the default settings as TOML)")
    click.echo(defaults_toml(), nl=False)
