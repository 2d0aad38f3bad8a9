"""``tacest record``: make a run file from simulation, a serial tactile rig or video."""

from __future__ import annotations

from pathlib import Path

import click

from tacest.sim.effects import EFFECT_NAMES  # light: no pymunk


@click.command()
@click.argument("bag", required=False, type=click.Path())
@click.option("--source", type=click.Choice(["sim", "serial", "video", "rosbag"]), default="sim", show_default=True,
              help="Where the data comes from.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True, help="Run file to write (HDF5).")
# --- sim -------------------------------------------------------------------------
@click.option("--dim", type=click.Choice(["2", "3"]), default="2", show_default=True,
              help="[sim] 2-D (pymunk) or 3-D (MuJoCo) world.")
@click.option("--object", "object_spec", default="box", show_default=True,
              help="[sim] box, box:W,H (m), polygon, polygon:K, or a file of x y vertex rows "
                   "(m); with --dim 3: box, box:W,H,D, polytope (or polygon), polytope:K, or a file of "
                   "x y z rows (docs/simulation.md).")
@click.option("--seed", type=int, default=0, show_default=True, help="[sim] random seed.")
@click.option("--pokes", type=click.IntRange(0, 1000), default=6, show_default=True, help="[sim] number of pokes.")
@click.option("--poke-style", type=click.Choice(["gentle", "fast", "high", "flick", "dynamic", "mixed"]),
              default="gentle", show_default=True,
              help="[sim] random pokes: gentle (slow, at the centroid: the object slides), fast (0.1-0.6 m/s at any "
                   "height), high (near the top: it tips and topples), flick (low and fast: it slides and spins "
                   "free), dynamic (each poke fast, high or flick), mixed (any of the four). docs/simulation.md.")
@click.option("--fingers", type=click.IntRange(1, 3), default=1, show_default=True, help="[sim] fingertips.")
@click.option("--fingers-per-action", type=click.IntRange(1, 3), default=1, show_default=True,
              help="[sim, --dim 3] fingers that move together in each random action, each with its own random "
                   "poke (docs/simulation.md).")
@click.option("--effect", "effects", multiple=True, metavar="NAME[:key=value,...]",
              help="[sim] inject an unmodelled effect (repeatable): " + ", ".join(EFFECT_NAMES)
                   + "; parameters not given are random, e.g. latency:samples=2; see docs/effects.md.")
@click.option("--noise-force", type=click.FloatRange(min=0), default=0.02, show_default=True,
              help="[sim] force noise, N (one sigma).")
@click.option("--noise-position", type=click.FloatRange(min=0), default=1e-4, show_default=True,
              help="[sim] fingertip position noise, m.")
@click.option("--noise-normal", type=click.FloatRange(min=0), default=0.02, show_default=True,
              help="[sim] contact normal noise, rad.")
@click.option("--no-force", is_flag=True, help="[sim] no force stream (contact and normal only).")
@click.option("--observe-pose", type=click.FloatRange(min=0), default=None,
              help="[sim] also write pose observations with this position sigma (m).")
@click.option("--toss", is_flag=True,
              help="[sim] start with the object tossed: released in the air at a random height, speed and "
                   "spin; it lands, and the pokes start once it is at rest (docs/simulation.md).")
@click.option("--dt", type=click.FloatRange(min=1e-4, max=0.1), default=0.01, show_default=True,
              help="[sim] sample period, s.")
@click.option("--no-truth", is_flag=True, help="[sim] leave out the /truth group.")
@click.option("--plan", "plan_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="[sim] execute the chosen action of this plan file (appends to OUTPUT if it exists).")
# --- serial ----------------------------------------------------------------------
@click.option("--port", default=None, help="[serial] device or pyserial URL (loop://, /dev/pts/N, ...).")
@click.option("--baud", type=click.IntRange(min=1), default=115200, show_default=True, help="[serial] baud rate.")
@click.option("--duration", type=click.FloatRange(min=0), default=None,
              help="[serial] stop after this many seconds (default: until the link closes or Ctrl-C).")
# --- video -----------------------------------------------------------------------
@click.option("--frames", type=click.Path(exists=True), default=None,
              help="[video] folder of images or a video file of the tactile camera.")
@click.option("--calib", type=click.Path(exists=True, dir_okay=False), default=None,
              help="[video] dome calibration JSON (docs/tactile_video.md).")
@click.option("--finger-log", type=click.Path(exists=True, dir_okay=False), default=None,
              help="[video] CSV of time stamps and fingertip positions.")
@click.option("--fps", type=click.FloatRange(min=0, min_open=True), default=None,
              help="[video] frame rate, Hz: for a folder without timestamps.csv, or to override a video's.")
@click.option("--t0", "frames_t0", type=float, default=0.0, show_default=True,
              help="[video] time of the first frame, s, when times come from the frame rate.")
@click.option("--reference", type=click.Path(exists=True, dir_okay=False), default=None,
              help="[video] no-contact reference image (default: the first frame).")
@click.option("--flow-scale", type=click.FloatRange(0.05, 1.0), default=0.5, show_default=True,
              help="[video] resize frames by this factor before the optical flow.")
@click.option("--flow-preset", type=click.Choice(["tactile", "ultrafast", "fast", "medium"]), default="tactile",
              show_default=True, help="[video] DIS optical flow settings (docs/tactile_video.md).")
@click.option("--noise-frames", type=click.IntRange(min=1), default=10, show_default=True,
              help="[video] contact-free frames after the reference used to measure the noise level.")
@click.option("--contact-k", type=click.FloatRange(min=0, min_open=True), default=3.0, show_default=True,
              help="[video] contact starts above this many times the noise level (ends below 2/3 of it).")
# --- rosbag ----------------------------------------------------------------------
@click.option("--mapping", type=click.Path(dir_okay=False), default=None,
              help="[rosbag] TOML mapping of topics and frames to the run file's fields (docs/rosbag.md).")
@click.option("--quiet", is_flag=True, help="No progress output.")
def record(bag, source, output, **kw):
    """Record a run file (SPEC run format) from SOURCE.

    With --source rosbag, BAG is a ROS 1 bag (.bag), a ROS 2 bag folder, or an .mcap or
    .db3 file, read with the mapping given by --mapping.
    """
    from tacest.cli.logs import setup_logging
    from tacest.io.outputs import check_output

    output = Path(output)
    quiet = kw.pop("quiet")
    setup_logging(quiet)
    mapping = kw.pop("mapping")
    if source != "rosbag" and bag is not None:
        raise click.UsageError(f"unexpected argument {bag!r}: a BAG is read with --source rosbag")
    if source == "rosbag" and (bag is None or mapping is None):
        raise click.UsageError("--source rosbag needs BAG and --mapping MAP.toml")
    inputs = [bag, mapping] + [kw[n] for n in ("plan_path", "frames", "calib", "finger_log", "reference")]
    if source == "sim" and kw["object_spec"] and Path(kw["object_spec"]).is_file():
        inputs.append(kw["object_spec"])
    # before any work (a planned poke continues an existing OUTPUT in place: _record_sim
    # checks that it is the run the plan was made from)
    check_output(output, inputs=inputs)
    if source == "rosbag":
        from tacest.io.run import write_run
        from tacest.sensors.rosbag import record_rosbag

        run = record_rosbag(bag, mapping)
        write_run(run, output)
        if not quiet:
            _echo_err(f"wrote {output}: {run.n_samples} samples, {run.n_fingers} finger(s)")
    elif source == "sim":
        _record_sim(output, quiet=quiet, **kw)
    elif source == "serial":
        if not kw["port"]:
            raise click.UsageError("--source serial needs --port")
        from tacest.sensors.serial_rig import record_serial

        record_serial(kw["port"], baud=kw["baud"], duration=kw["duration"], output=output)
    else:
        missing = [n for n in ("frames", "calib", "finger_log") if not kw[n]]
        if missing:
            raise click.UsageError("--source video needs " + ", ".join("--" + m.replace("_", "-") for m in missing))
        from tacest.sensors.tactile_flow import DetectSettings, FlowSettings
        from tacest.sensors.video import VideoOptions, record_video

        options = VideoOptions(
            fps=kw["fps"], t0=kw["frames_t0"], reference=kw["reference"],
            flow=FlowSettings(work_scale=kw["flow_scale"], dis_preset=kw["flow_preset"]),
            detect=DetectSettings(noise_frames=kw["noise_frames"], k_on=kw["contact_k"], k_off=kw["contact_k"] * 2 / 3),
        )
        record_video(kw["frames"], kw["calib"], kw["finger_log"], output=output, options=options)


def _echo_err(*args, **kwargs):
    click.echo(*args, err=True, **kwargs)


def _record_sim(output, quiet, **kw):
    from tacest.dims import record_sim
    from tacest.errors import TacestError
    from tacest.io.plan import check_plan_continues, read_plan
    from tacest.io.run import write_run
    from tacest.sim.record import SimOptions

    opts = SimOptions(
        dim=int(kw["dim"]), object_spec=kw["object_spec"], seed=kw["seed"], pokes=kw["pokes"],
        fingers=kw["fingers"], effects=list(kw["effects"]), noise_force=kw["noise_force"],
        noise_position=kw["noise_position"], noise_normal=kw["noise_normal"], force_stream=not kw["no_force"],
        observe_pose=kw["observe_pose"], dt=kw["dt"], toss=kw["toss"], poke_style=kw["poke_style"],
        fingers_per_action=kw["fingers_per_action"],
    )
    append_to = output if kw["plan_path"] and output.exists() else None
    if append_to is not None:
        check_plan_continues(read_plan(kw["plan_path"]), append_to)
    try:
        run = record_sim(opts, plan_path=kw["plan_path"], append_to=append_to)
    except TacestError as exc:
        if kw["plan_path"] and str(exc).startswith("poke:"):  # the plan's action: name the file
            raise TacestError(f"{kw['plan_path']}: /chosen/params: {exc}") from None
        raise
    write_run(run, output, include_truth=not kw["no_truth"])
    if not quiet:
        rows = 0 if run.actions is None else len(run.actions.segments)
        actions = 0 if run.actions is None else len({tuple(s) for s in run.actions.segments.tolist()})
        _echo_err(f"wrote {output}: {run.n_samples} samples, {run.n_fingers} finger(s), {actions} action(s)"
                  + (f" ({rows} finger pokes)" if rows != actions else ""))
