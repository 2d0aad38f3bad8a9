"""``tacest estimate``: physics-constrained estimate of pose, shape, mass, inertia, friction;
``--batch MANIFEST``: many objects at once (tacest.batch)."""

from __future__ import annotations

import click

from tacest.cli.logs import warn_fit_quality
from tacest.cli.parallel import executor, parallel_options


@click.command()
@click.argument("runs", nargs=-1, type=click.Path(dir_okay=False))
@click.option("-o", "--output", type=click.Path(), required=True,
              help="Estimate file to write (HDF5); with --batch, the output folder.")
@click.option("--batch", "manifest", type=click.Path(dir_okay=False), default=None, metavar="MANIFEST",
              help="Estimate every object of MANIFEST (CSV or TOML: which run files belong to which object) "
                   "into the folder -o: NAME.h5 per object, summary.csv, summary.json. See docs/parallel.md.")
@click.option("--shape", default="box", show_default=True, help="Shape parameterization: box or polygon:K (2-D runs); box or polytope:K (3-D runs).")
@click.option("--method", type=click.Choice(["implicit", "shooting"]), default="implicit", show_default=True,
              help="implicit: one NLP over states, impulses and parameters; shooting: baseline.")
@click.option("--config", "config_path", type=click.Path(dir_okay=False), default=None,
              help="TOML settings (`tacest config --defaults` prints every key with its default); unknown keys are an error.")
@click.option("--start-from", "previous_path", type=click.Path(dir_okay=False), default=None, metavar="ESTIMATE",
              help="An earlier estimate of the first samples of these runs (implicit method): its shape "
                   "(in 2-D also its parameters) and trajectories, continued over the newer samples, are one more "
                   "start, compared by objective with the estimator's own. See docs/estimation.md.")
@click.option("--quiet", is_flag=True, help="No progress output.")
@parallel_options
def estimate(runs, output, manifest, shape, method, config_path, previous_path, quiet, workers, scheduler):
    """Estimate one object from RUNS (run files of the same object; shared parameters,
    one trajectory each) and write the estimate file OUTPUT; or, with --batch, every
    object of a manifest (its estimates on a Dask cluster with --workers or --scheduler)."""
    from tacest.estimation.config import load_config
    from tacest.linear_solver import check_linear_solver

    from tacest.cli.logs import setup_logging

    setup_logging(quiet)
    if manifest is not None:
        if runs:
            raise click.UsageError("give either RUNS or --batch MANIFEST, not both")
        if previous_path is not None:
            raise click.UsageError("--start-from goes with the RUNS of one object, not --batch")
        _batch(manifest, output, shape, method, config_path, quiet, executor(workers, scheduler))
        return
    if not runs:
        raise click.UsageError("give the RUNS of one object, or --batch MANIFEST")
    if workers is not None or scheduler is not None:
        raise click.UsageError("--workers and --scheduler go with --batch (one object is one fit)")
    from tacest.dims import estimate_runs
    from tacest.io.estimate import read_estimate, write_estimate
    from tacest.io.outputs import check_output
    from tacest.io.run import read_runs

    output = check_output(output, inputs=[*runs, config_path, previous_path])  # before minutes of solving
    config = load_config(config_path)
    check_linear_solver(config.solver.linear_solver)
    loaded = read_runs(runs)
    previous = None if previous_path is None else read_estimate(previous_path)
    est = estimate_runs(loaded, shape, config=config, method=method, previous=previous)
    write_estimate(est, output)
    warn_fit_quality(est)
    if not quiet:
        p = est.params

        def fit_mark(e):  # the goodness-of-fit test and the shape's identifiability (warnings above)
            return ("; a local misfit (see above)" if e.local_misfit else "" if e.consistent in (True, None)
                    else "; fit NOT consistent with the data (see warning)") \
                + ("; shape not identifiable" if e.identifiable.get("shape") is False else "")

        def note(name):  # without a force stream, at a bound, or set by the Occam term (warnings above)
            return "" if est.identifiable.get(name, True) else " (not identifiable)"

        click.echo(f"wrote {output}: {est.solver_status} ({est.iterations} iterations, {est.wall_time:.1f} s); "
                   f"mass {p['mass']:.4g} kg{note('mass')}, friction ground {p['friction_ground']:.3g}"
                   f"{note('friction_ground')}, finger {p['friction_finger']:.3g}{note('friction_finger')}"
                   f"{fit_mark(est)}", err=True)


def _batch(manifest, output, shape, method, config_path, quiet, ex):
    """``--batch``: every object of the manifest, one summary (tacest.batch)."""
    from tacest.batch import estimate_batch, read_manifest, write_batch
    from tacest.errors import TacestError
    from tacest.estimation.config import load_config
    from tacest.io.outputs import check_output
    from tacest.linear_solver import check_linear_solver

    objects = read_manifest(manifest)
    out = check_output(output, inputs=[manifest, config_path, *(r for o in objects for r in o.runs)], folder=True)
    config = load_config(config_path)
    check_linear_solver(config.solver.linear_solver)
    with ex:
        results = estimate_batch(objects, ex, shape=shape, config=config, method=method)
    write_batch(results, out, extra={"method": method, "manifest": str(manifest)})
    failed = [r for r in results if r.status != "ok"]
    if failed:
        raise TacestError(f"{len(failed)} of {len(results)} object(s) failed, first {failed[0].name}: "
                          f"{failed[0].reason} (every object in {out}/summary.csv)")
    if not quiet:
        click.echo(f"wrote {out}/: {len(results)} estimate(s), summary.csv, summary.json", err=True)
