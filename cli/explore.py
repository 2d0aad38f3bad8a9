"""``tacest explore``: the closed loop in simulation: poke, estimate, plan, repeat."""

from __future__ import annotations

import click

#: the files of a loop in its output folder (tacest/planning/explore.py)
EXPLORE_FILES = ("run.h5", "summary.json", "learning_curve.png", "view_3d.png", "view_3d.html", "estimate_*.h5",
                 "plan_*.h5")


@click.command()
@click.option("-o", "--output", "out_dir", type=click.Path(file_okay=False), required=True,
              help="Folder for run.h5, estimate_<n>.h5, plan_<n>.h5, summary.json, learning_curve.png "
                   "(3-D: also view_3d.png, view_3d.html).")
@click.option("--dim", type=click.Choice(["2", "3"]), default="2", show_default=True,
              help="World: 2 (pymunk) or 3 (MuJoCo).")
@click.option("--object", "object_spec", default="box", show_default=True,
              help="box, box:W,H (m), polygon, polygon:K, or a file of x y vertex rows (docs/simulation.md); "
                   "with --dim 3: box, box:W,H,D, polytope, polytope:K, or a file of x y z rows.")
@click.option("--fingers", type=click.IntRange(1, 3), default=1, show_default=True, help="Fingertips.")
@click.option("--force/--no-force", "force_stream", default=None,
              help="Record a force stream (default: yes in 2-D; no in 3-D, contact and normal only).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Seed of the simulated object, its first poke and the sensor noise.")
@click.option("--policy", type=click.Choice(["eig", "random", "identity"]), default="eig", show_default=True,
              help="How every poke after the first is chosen (tacest plan --method).")
@click.option("--pokes", type=click.IntRange(1, 100), default=8, show_default=True, help="Number of pokes.")
@click.option("--shape", default=None, help="Estimator shape (default: box for box objects, else polygon:8; "
                                            "3-D: polytope:12).")
@click.option("--information", type=click.Choice(["schur", "identity", "diffsim", "marginal"]), default=None,
              help="How eig builds the information (tacest plan --information; default schur in 2-D, marginal "
                   "in 3-D).")
@click.option("--score", type=click.Choice(["logdet", "A", "D", "E"]), default="logdet", show_default=True,
              help="Scalarization of the information (docs/planning.md).")
@click.option("--vary", multiple=True, type=click.Choice(["depth", "speed", "height"]),
              help="Also choose the depth, speed and/or aim height of each poke (repeatable).")
@click.option("--poke-style", type=click.Choice(["gentle", "dynamic"]), default="gentle", show_default=True,
              help="gentle: slow pokes at the centroid; dynamic: the first poke from tacest record's dynamic "
                   "mix, and every planned poke fast (0.1-0.6 m/s) with its aim height chosen, so the object "
                   "tips and topples (docs/planning.md).")
@click.option("--iterations", type=click.IntRange(1, 50), default=4, show_default=True,
              help="Cross-entropy iterations (eig, identity; per finger in 2-D, one search in 3-D).")
@click.option("--population", type=click.IntRange(2, 500), default=12, show_default=True,
              help="Candidates per cross-entropy iteration.")
@click.option("--fingers-per-action", type=click.IntRange(1, 3), default=1, show_default=True,
              help="[3-D] fingers that move together in each planned action (each from its own direction; "
                   "docs/planning.md).")
@click.option("--config", "config_path", type=click.Path(dir_okay=False), default=None,
              help="Estimator TOML settings (`tacest config --defaults` prints every key).")
@click.option("--quiet", is_flag=True, help="No progress output.")
def explore(out_dir, dim, object_spec, fingers, force_stream, seed, policy, pokes, shape, information, score, vary,
            poke_style, iterations, population, fingers_per_action, config_path, quiet):
    """Explore a simulated object (2-D, or 3-D with --dim 3): record a poke, estimate,
    plan the next poke with POLICY, repeat until POKES pokes; write per-step files,
    summary.json and a learning-curve plot (3-D: and views) to OUTPUT."""
    import sys
    from pathlib import Path

    from tacest.cli.logs import setup_logging, step_progress
    from tacest.estimation.config import load_config
    from tacest.geometry.shapes import make_shape
    from tacest.geometry.shapes3d import make_shape_3d
    from tacest.io.outputs import check_output, replacing_files
    from tacest.linear_solver import check_linear_solver
    from tacest.dims import dimension
    from tacest.planning.explore import ExploreOptions

    object_file = object_spec if Path(object_spec).is_file() else None
    check_output(out_dir, inputs=[object_file, config_path], folder=True)
    if shape is not None:
        (make_shape_3d if dim == "3" else make_shape)(shape)  # a bad --shape is an error before anything is simulated
    check_linear_solver(load_config(config_path).solver.linear_solver)
    opts = ExploreOptions(object_spec=object_spec, seed=seed, policy=policy, pokes=pokes, shape=shape, score=score,
                          config_path=config_path, vary=tuple(vary), dim=int(dim), fingers=fingers,
                          force_stream=force_stream, information=information, iterations=iterations,
                          population=population, poke_style=poke_style,
                          fingers_per_action=fingers_per_action).validate()
    setup_logging(quiet)

    progress = step_progress(quiet, "pokes")

    # an earlier loop's files are removed, never mistaken for this one's (put back on Ctrl-C)
    with replacing_files(out_dir, EXPLORE_FILES) as out:
        summary = dimension(opts.dim).implementation("explore")(opts, out, progress=progress)
    last = summary["steps"][-1]
    ch = last.get("chamfer")
    if not quiet:
        click.echo(f"wrote {out_dir}: {len(summary['steps'])} steps, final chamfer "
                   f"{'n/a' if ch is None else f'{1e3 * ch:.2f} mm'}, {summary['wall_time']:.0f} s", err=True)
    sys.stdout.flush()
