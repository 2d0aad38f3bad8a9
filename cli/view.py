"""``tacest view``: an animation of a run or an estimate that opens without tacest."""

from __future__ import annotations

import click


@click.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True,
              help="Animation to write: .gif or .mp4 (2-D), .html (3-D, interactive).")
@click.option("--run", "run_path", type=click.Path(dir_okay=False), default=None,
              help="For an estimate: the run file it came from, for the finger path, contacts, normals and the "
                   "true shape (default: the estimate's source_file when it exists).")
@click.option("--run-index", type=click.IntRange(min=0), default=0, show_default=True,
              help="Which run of an estimate to show.")
@click.option("--fps", type=click.FloatRange(1, 60), default=20.0, show_default=True,
              help="Frames per second (real time: one frame every 1/fps s of the recording).")
@click.option("--max-frames", type=click.IntRange(min=2), default=None,
              help="At most this many frames, evenly thinned (default 300 for GIF/MP4, 600 for HTML).")
def view(file, output, run_path, run_index, fps, max_frames):
    """Animate FILE (a run or an estimate file): true and estimated shapes along the
    trajectory, fingertips with their path, contact points and normals."""
    from tacest.io.outputs import check_output
    from tacest.view.scene import load_scene

    output = check_output(output, inputs=[file, run_path])  # before any work
    sc = load_scene(file, run_path=run_path, run_index=run_index)
    suffix = output.suffix.lower()
    if sc.dim == 2:
        if suffix not in (".gif", ".mp4"):
            raise click.UsageError(f"a 2-D view is written as .gif or .mp4, not {suffix or 'no suffix'!r}")
        from tacest.view.anim2d import write_animation_2d

        n = write_animation_2d(sc, output, fps=fps, max_frames=max_frames or 300)
    else:
        if suffix not in (".html", ".htm"):
            raise click.UsageError(f"a 3-D view is written as .html, not {suffix or 'no suffix'!r}")
        from tacest.view.html3d import write_html_3d

        n = write_html_3d(sc, output, fps=fps, max_frames=max_frames or 600)
    click.echo(f"wrote {output}: {n} frames", err=True)
