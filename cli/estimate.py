"""``tacest estimate``: physics-constrained estimate of pose, shape, mass, inertia, friction."""

from __future__ import annotations

import click


@click.command()
@click.argument("runs", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True, help="Estimate file to write (HDF5).")
@click.option("--shape", default="box", show_default=True, help="Shape parameterization: box or polygon:K (2-D runs); box or polytope:K (3-D runs).")
@click.option("--method", type=click.Choice(["implicit", "shooting"]), default="implicit", show_default=True,
              help="implicit: one NLP over states, impulses and parameters; shooting: baseline.")
@click.option("--config", "config_path", type=click.Path(dir_okay=False), default=None,
              help="TOML settings (`tacest config --defaults` prints every key with its default); unknown keys are an error.")
@click.option("--quiet", is_flag=True, help="No progress output.")
def estimate(runs, output, shape, method, config_path, quiet):
    """Estimate one object from RUNS (run files of the same object; shared parameters,
    one trajectory each) and write the estimate file OUTPUT."""
    from tacest.dims import estimate_runs
    from tacest.estimation.config import load_config
    from tacest.io.estimate import write_estimate
    from tacest.io.outputs import check_output
    from tacest.io.run import read_runs
    from tacest.linear_solver import check_linear_solver

    from tacest.cli.logs import setup_logging

    setup_logging(quiet)
    output = check_output(output, inputs=[*runs, config_path])  # before minutes of solving
    config = load_config(config_path)
    check_linear_solver(config.solver.linear_solver)
    loaded = read_runs(runs)
    est = estimate_runs(loaded, shape, config=config, method=method)
    write_estimate(est, output)
    if not quiet:
        p = est.params

        def fit_mark(e):  # the goodness-of-fit test and the shape's identifiability (warnings above)
            return ("" if e.consistent in (True, None) else "; fit NOT consistent with the data (see warning)") \
                + ("; shape not identifiable" if e.identifiable.get("shape") is False else "")

        def note(name):  # without a force stream, at a bound, or set by the Occam term (warnings above)
            return "" if est.identifiable.get(name, True) else " (not identifiable)"

        click.echo(f"wrote {output}: {est.solver_status} ({est.iterations} iterations, {est.wall_time:.1f} s); "
                   f"mass {p['mass']:.4g} kg{note('mass')}, friction ground {p['friction_ground']:.3g}"
                   f"{note('friction_ground')}, finger {p['friction_finger']:.3g}{note('friction_finger')}"
                   f"{fit_mark(est)}", err=True)
