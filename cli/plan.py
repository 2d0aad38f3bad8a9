"""``tacest plan``: choose the next poke by expected information gain."""

from __future__ import annotations

import logging

import click


@click.command()
@click.argument("estimate", type=click.Path(dir_okay=False))
@click.argument("runs", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True, help="Plan file to write (HDF5).")
@click.option("--method", type=click.Choice(["eig", "random", "identity"]), default="eig", show_default=True,
              help="eig: cross-entropy search of the expected information gain; random: random approach "
                   "direction; identity: the quasi-static identity-Jacobian approximation.")
@click.option("--score", type=click.Choice(["logdet", "A", "D", "E"]), default="logdet", show_default=True,
              help="Scalarization of the information (docs/planning.md).")
@click.option("--information", type=click.Choice(["schur", "identity", "diffsim", "marginal"]), default=None,
              help="How the information of a poke and of the past is built (docs/planning.md): schur (the "
                   "estimator's own, 2-D default), identity, diffsim (differentiating the simulation) or "
                   "marginal (past states marginalized by sampling, 3-D default).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Random seed of the search.")
@click.option("--vary", multiple=True, type=click.Choice(["depth", "speed", "height"]),
              help="Also choose the poke's depth, speed and/or aim height above the centroid (repeatable); "
                   "default: 2 cm, a 1 s approach, at the centroid.")
@click.option("--poke-style", type=click.Choice(["gentle", "dynamic"]), default="gentle", show_default=True,
              help="dynamic: fast pokes (0.1-0.6 m/s) whose speed and aim height are chosen, so the object "
                   "tips and topples (docs/planning.md).")
@click.option("--iterations", type=click.IntRange(1, 50), default=4, show_default=True,
              help="Cross-entropy iterations (per finger in 2-D; one search in 3-D).")
@click.option("--population", type=click.IntRange(2, 500), default=12, show_default=True,
              help="Candidates per cross-entropy iteration.")
@click.option("--fingers-per-action", type=click.IntRange(1, 3), default=1, show_default=True,
              help="[3-D] fingers that move together in the planned action (each from its own direction; "
                   "docs/planning.md).")
@click.option("--quiet", is_flag=True, help="No progress output.")
def plan(estimate, runs, output, method, score, information, seed, vary, poke_style, iterations, population,
         fingers_per_action, quiet):
    """Plan the next poke of the object in ESTIMATE (an estimate file) from the RUNS it
    was estimated from, and write the plan file OUTPUT.  The poke aims at the estimated
    centroid; `tacest record --source sim --plan OUTPUT -o RUN.h5` executes it."""
    import json

    from tacest.io.estimate import check_runs_match, read_estimate
    from tacest.io.h5util import sha256_file
    from tacest.io.outputs import check_output
    from tacest.io.plan import RUNS_SHA256, write_plan
    from tacest.io.run import read_runs
    from tacest.dims import dimension
    from tacest.planning.actions import describe_action
    from tacest.planning.planner import PlanSettings

    from tacest.cli.logs import setup_logging

    setup_logging(quiet)
    output = check_output(output, inputs=[estimate, *runs])
    settings = PlanSettings(method=method, score=score, seed=seed, vary=tuple(vary), iterations=iterations,
                            population=population, information=information, poke_style=poke_style,
                            fingers_per_action=fingers_per_action).validate()
    est = read_estimate(estimate)
    loaded = read_runs(runs)
    check_runs_match(est, runs)
    if est.consistent is False:
        logging.getLogger("tacest.plan").warning(
            f"{estimate}: its fit is NOT consistent with its data (fit_quality): the plan rests on an estimate "
            "whose error bars are not to be trusted")
    result = dimension(est.dim).implementation("plan")(est, loaded, settings)
    # the runs the poke was planned from: `tacest record --plan` continues only the last
    result.extra_attrs[RUNS_SHA256] = json.dumps([sha256_file(p) for p in runs])
    write_plan(result, output)
    if not quiet:
        click.echo(f"wrote {output}: {method} ({score} {result.scores.max() if method != 'random' else result.scores[0]:.4g}, "
                   f"{len(result.scores)} candidates, {float(result.extra_attrs['wall_time']):.1f} s): "
                   + describe_action(result.chosen_dict(), detailed=True), err=True)
