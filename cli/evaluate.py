"""``tacest eval``: score an estimate against the truth of a simulated run."""

from __future__ import annotations

import click


@click.command(name="eval")
@click.argument("estimate", type=click.Path(dir_okay=False))
@click.option("--truth", "truth", type=click.Path(dir_okay=False), required=True,
              help="Run file with a /truth group (a simulated recording).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout (NaN as null).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None,
              help="Also draw shapes, finger path and errors over time to this image (PNG, PDF, SVG).")
@click.option("--run-index", type=click.IntRange(min=0), default=None,
              help="Which run of ESTIMATE to compare (default: the one recorded from --truth, by "
                   "SHA-256 or file name; else run 0 if its length matches).")
def eval_cmd(estimate, truth, as_json, plot_path, run_index):
    """Score ESTIMATE (an estimate file) against the truth in the run file --truth.

    Prints the Chamfer distance of the placed shapes averaged over time, the Chamfer
    distance of the shapes alone after the best rigid alignment, pose errors, and the
    relative errors of mass, inertia and friction (see docs/evaluation.md).
    """
    import json

    from tacest.evaluation.metrics import evaluate_files, format_report, to_jsonable
    from tacest.io.outputs import atomic_file, check_output

    if plot_path:
        check_output(plot_path, inputs=[estimate, truth])
    report, series, est, run = evaluate_files(estimate, truth, run_index=run_index, return_series=True)
    if plot_path:
        from tacest.evaluation.plots import plot_evaluation

        with atomic_file(plot_path) as tmp:
            plot_evaluation(tmp, report, series, est, run, run_index=report["run_index"])
        report["plot"] = str(plot_path)
    if as_json:
        click.echo(json.dumps(to_jsonable(report), allow_nan=False))
    else:
        click.echo(format_report(report))
        if plot_path:
            click.echo(f"\nfigure written to {plot_path}")
