"""``tacest export``: the estimated object as a model for simulators and planners."""

from __future__ import annotations

from pathlib import Path

import click

FORMAT_CHOICES = ("mjcf", "urdf", "sdf", "obj", "stl", "glb")


@click.command()
@click.argument("estimate", type=click.Path(dir_okay=False))
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True,
              help="Model file to write (URDF/SDF also write NAME.stl beside it; OBJ/STL/GLB NAME.physics.json).")
@click.option("--format", "fmt", type=click.Choice(FORMAT_CHOICES), default=None,
              help="Output format (default: from the suffix of --output: .xml/.mjcf, .urdf, .sdf, .obj, .stl, .glb).")
@click.option("--depth", type=click.FloatRange(min=0, min_open=True), default=None,
              help="[2-D estimates] depth (m) the polygon is extruded to; an assumption, said so in the file "
                   "(default 0.1).")
@click.option("--run-index", type=click.IntRange(min=0), default=0, show_default=True,
              help="Which estimated run's trajectory to export (keyframes, --trajectory).")
@click.option("--run", "run_path", type=click.Path(dir_okay=False), default=None,
              help="The run file of that trajectory, for its sample times (default: the estimate's "
                   "source_file when it exists).")
@click.option("--trajectory", "trajectory_path", type=click.Path(dir_okay=False), default=None,
              help="Also write the estimated pose trajectory to this CSV (sample, time, x, y, z, qw, qx, qy, qz).")
@click.option("--keyframes", default="1000", show_default=True, metavar="N|all",
              help="[mjcf] at most N keyframes of the trajectory (evenly subsampled; 0: none), or all samples.")
@click.option("--name", default="tacest_object", show_default=True, help="Model name in the file.")
def export(estimate, output, fmt, depth, run_index, run_path, trajectory_path, keyframes, name):
    """Export the object estimated in ESTIMATE (an estimate file) as a model file.

    The model holds the mesh (convex hull of the estimated vertices, body frame at the
    centre of mass), mass, inertia, ground and finger friction and the effects the format
    can express, with a comment block saying where each number came from and which are
    priors the data could not determine (docs/export.md).
    """
    from tacest.errors import TacestError
    from tacest.export.formats import (SUFFIX_FORMAT, check_finite_body, export_paths, write_export,
                                       write_trajectory_csv)
    from tacest.export.model import body_from_estimate
    from tacest.io.estimate import read_estimate
    from tacest.io.outputs import check_output

    output = Path(output)
    if fmt is None:
        fmt = SUFFIX_FORMAT.get(output.suffix.lower())
        if fmt is None:
            raise click.UsageError(f"cannot tell the format from {output.name!r}; give --format "
                                   + "|".join(FORMAT_CHOICES))
    outputs = export_paths(output, fmt) + ([Path(trajectory_path)] if trajectory_path else [])
    if len({p.resolve() for p in outputs}) < len(outputs):
        raise TacestError(f"{trajectory_path}: is also the model file or its companion; give another --trajectory")
    for path in outputs:  # before any work
        check_output(path, inputs=[estimate, run_path])
    if keyframes == "all":
        max_keys = None
    else:
        try:
            max_keys = int(keyframes)
        except ValueError:
            raise click.BadParameter(f"{keyframes!r}: expected a number or 'all'", param_hint="--keyframes") from None
        if max_keys < 0:
            raise click.BadParameter("must be >= 0", param_hint="--keyframes")
    est = read_estimate(estimate)
    time = _run_time(est, estimate, run_index, run_path)
    body = body_from_estimate(est, depth=depth, run_index=run_index, time=time, source=str(estimate))
    body.name = name
    check_finite_body(body, str(estimate))
    if trajectory_path and not est.runs:
        raise TacestError(f"{estimate}: /runs: the estimate has no trajectory to write to {trajectory_path}")
    written = write_export(body, output, fmt, max_keys=max_keys)
    if trajectory_path:
        write_trajectory_csv(body, trajectory_path)
        written.append(Path(trajectory_path))
    click.echo("wrote " + ", ".join(str(p) for p in written), err=True)


def _run_time(est, estimate, run_index, run_path):
    """(T,) s of the exported run's samples: from --run, else the estimate's source_file
    (as given, or next to the estimate) when it exists and matches; else None."""
    from tacest.errors import TacestError
    from tacest.io.run import read_run

    if run_path:
        return read_run(run_path).time
    if not est.runs or run_index >= len(est.runs):
        return None
    src = est.runs[run_index].source_file
    if not src:
        return None
    for cand in (Path(src), Path(estimate).parent / Path(src).name):
        if cand.is_file():
            try:
                t = read_run(cand).time
            except TacestError:  # a stale or replaced file: times are optional
                continue
            if len(t) == len(est.runs[run_index].pose):
                return t
    return None
