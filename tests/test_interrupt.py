"""Ctrl-C stops every command at once (issue 27, item 2): exit status 130, one line
"tacest: interrupted", no new output, an existing output untouched.

The commands run as a user runs them (the installed ``tacest``) and get SIGINT in the
middle of their work: during an IPOPT solve (estimate, diagnose, explore), the planner's
search (plan) and the simulation (record).
"""

import os
import signal

import pytest

from tacest.interrupt import check_interrupt, deferred_interrupts, raise_if_interrupted, watch_interrupts
from tests.reliability_files import interrupt_when, make_run, truth_estimate

INTERRUPTED = "tacest: interrupted"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("interrupt")
    a = make_run(d / "a.h5", seed=1, pokes=3)
    b = make_run(d / "b.h5", seed=1, pokes=2)
    return {"dir": d, "a": a, "b": b, "est": truth_estimate([a], d / "est.h5")}


def _snapshot(folder):
    """{relative path: bytes} of every file under ``folder`` (hidden ones included)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _assert_interrupted(code, lines):
    assert code == 130, lines
    assert lines and lines[-1] == INTERRUPTED, lines
    for ln in lines:
        assert "Traceback" not in ln and "CasADi" not in ln and not ln.startswith("wrote"), lines
        assert not ln.startswith("restart") and "tacest: error" not in ln, lines


def test_estimate_interrupted_mid_solve_keeps_the_previous_estimate(files, tmp_path):
    out = tmp_path / "est.h5"
    out.write_bytes(files["est"].read_bytes())  # the previous output
    before = _snapshot(tmp_path)
    code, lines = interrupt_when(["estimate", files["a"], "-o", out], marker="homotopy 1/2 iter", delay=0.2)
    _assert_interrupted(code, lines)
    assert _snapshot(tmp_path) == before  # byte-identical, no temporary file left


def test_ctrl_c_in_a_terminal_while_starts_solve_in_processes_is_one_line(files, tmp_path):
    """Ctrl-C reaches the whole process group, the forked workers solving the compared
    starts too (tacest.parallel.fork_map): one line, 130, no traceback from any worker,
    and nothing written after it."""
    out = tmp_path / "est.h5"
    code, lines = interrupt_when(["estimate", files["a"], "-o", out], marker="compared starts in", delay=1.0,
                                 group=True)
    _assert_interrupted(code, lines)
    assert not any("Process" in ln or "KeyboardInterrupt" in ln for ln in lines), lines
    assert not out.exists()


def test_diagnose_interrupted_mid_fit_writes_no_report(files, tmp_path):
    report = tmp_path / "report"
    report.mkdir()
    (report / "report.md").write_text("an earlier report")
    before = _snapshot(tmp_path)
    code, lines = interrupt_when(["diagnose", files["a"], files["b"], "--effects", "latency", "-o", report],
                                 marker="plain model", delay=1.0)
    _assert_interrupted(code, lines)
    assert _snapshot(tmp_path) == before


def test_plan_interrupted_mid_search_writes_no_plan(files, tmp_path):
    out = tmp_path / "plan.h5"
    out.write_text("an earlier plan")
    before = _snapshot(tmp_path)
    # a long search, interrupted once the planner has started
    code, lines = interrupt_when(["plan", files["est"], files["a"], "--iterations", "50", "--population", "500",
                                  "-o", out], delay=4.0)
    _assert_interrupted(code, lines)
    assert _snapshot(tmp_path) == before


def test_explore_interrupted_mid_loop_leaves_the_folder_as_it_was(tmp_path):
    out = tmp_path / "loop"
    out.mkdir()
    for name in ("run.h5", "summary.json", "estimate_1.h5", "notes.txt"):
        (out / name).write_text(f"earlier {name}")
    before = _snapshot(tmp_path)
    code, lines = interrupt_when(["explore", "--pokes", "2", "-o", out], delay=3.0)  # while it estimates
    _assert_interrupted(code, lines)
    assert _snapshot(tmp_path) == before


def test_record_interrupted_mid_simulation_writes_no_run(tmp_path):
    out = tmp_path / "run.h5"
    code, lines = interrupt_when(["record", "--pokes", "400", "-o", out], marker="poke 2/", delay=0.2)
    _assert_interrupted(code, lines)
    assert list(tmp_path.iterdir()) == []


def test_raise_if_interrupted():
    raise_if_interrupted("Solve_Succeeded")
    raise_if_interrupted("Maximum_Iterations_Exceeded")
    with pytest.raises(KeyboardInterrupt):
        raise_if_interrupted("User_Requested_Stop")


def test_watch_interrupts_notes_a_sigint_that_a_solver_swallowed():
    with pytest.raises(KeyboardInterrupt):
        with watch_interrupts() as watch:
            try:
                os.kill(os.getpid(), signal.SIGINT)  # the handler runs right after
            except KeyboardInterrupt:
                pass  # what IPOPT does: it turns the exception into a return status
        raise_if_interrupted("NonIpopt_Exception_Thrown", watch)
    assert watch.interrupted
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored


@pytest.mark.parametrize("outside", [None, signal.SIG_IGN], ids=["installed-outside-python", "ignored"])
def test_watch_interrupts_leaves_a_handler_it_could_not_put_back(monkeypatch, outside):
    """``getsignal`` gives None for a handler installed outside Python (an embedding
    program's): Python could not set it again, so the watch must not replace it (once it
    did, and its end raised TypeError from ``signal.signal(SIGINT, None)``).  Under an
    ignoring handler SIGINT stays ignored."""
    set_to = []
    monkeypatch.setattr(signal, "getsignal", lambda signum: outside)
    monkeypatch.setattr(signal, "signal", lambda signum, handler: set_to.append(handler))
    with watch_interrupts() as watch:
        pass
    assert set_to == [] and not watch.interrupted
    raise_if_interrupted("Solve_Succeeded", watch)


def _resting_ball():
    """A pymunk space with a ball resting on a static ground, and the ball, whose body
    has an arbiter (the space is returned too: the body keeps only a weak reference)."""
    import pymunk

    space = pymunk.Space()
    space.gravity = (0.0, -9.81)
    space.add(pymunk.Segment(space.static_body, (-1.0, 0.0), (1.0, 0.0), 0.0))
    ball = pymunk.Body(1.0, pymunk.moment_for_circle(1.0, 0.0, 0.05))
    ball.position = (0.0, 0.049)
    space.add(ball, pymunk.Circle(ball, 0.05))
    space.step(1e-3)
    return space, ball


def test_a_sigint_in_a_cffi_callback_is_delivered_after_it(capfd):
    """pymunk runs the arbiter callbacks from C through cffi, which swallows a
    KeyboardInterrupt raised inside them; in deferred_interrupts the SIGINT is noted and
    check_interrupt raises it outside, with nothing printed."""
    space, ball = _resting_ball()
    seen = []

    def callback(arbiter):
        os.kill(os.getpid(), signal.SIGINT)  # the handler runs inside the callback
        seen.append(sum(range(100)))  # ... and the callback goes on

    with pytest.raises(KeyboardInterrupt):
        with deferred_interrupts():
            ball.each_arbiter(callback)
            assert seen  # the callback ran to its end
            check_interrupt()
    assert "Exception ignored" not in capfd.readouterr().err
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored


def test_deferred_interrupts_deliver_at_the_end_of_the_block_at_the_latest():
    with pytest.raises(KeyboardInterrupt):
        with deferred_interrupts():
            with deferred_interrupts():  # nested: the outer block holds the handler
                os.kill(os.getpid(), signal.SIGINT)
                sum(range(1000))
            sum(range(1000))  # nothing raised inside the block
    check_interrupt()  # nothing pending any more
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_an_interrupt_inside_a_c_extension_call_is_an_interrupt():
    """A SIGINT that arrives while a C extension function runs (seen: CasADi's
    DM.__array__ during an explore loop's estimate) surfaces as SystemError("...
    returned a result with an exception set") caused by the KeyboardInterrupt: the CLI
    reads it as Ctrl-C (exit 130), not as a bug (exit 3)."""
    from tacest.cli.main import _caused_by_interrupt

    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as inner:
            raise SystemError("<function DM.__array__> returned a result with an exception set") from inner
    except SystemError as exc:
        assert _caused_by_interrupt(exc)
    assert not _caused_by_interrupt(ValueError("a bug"))


def test_a_swallowed_interrupt_still_ends_the_command_before_its_output(tmp_path):
    """Under the command line's latch, a SIGINT whose KeyboardInterrupt something caught
    (a C library running Python code) still ends the command: the next solve's result
    and the output's commit raise it, and the earlier output stays as it was."""
    from tacest.interrupt import interrupt_latch, raise_if_noted
    from tacest.io.outputs import atomic_dir, atomic_file

    out = tmp_path / "est.h5"
    out.write_text("the previous estimate")
    with interrupt_latch():
        raise_if_interrupted("Solve_Succeeded")  # nothing noted yet
        try:
            os.kill(os.getpid(), signal.SIGINT)
        except KeyboardInterrupt:
            pass  # swallowed, as CasADi or cffi would
        with pytest.raises(KeyboardInterrupt):
            raise_if_interrupted("Solve_Succeeded")
        with pytest.raises(KeyboardInterrupt):
            with atomic_file(out) as tmp:
                tmp.write_text("a new estimate")
        with pytest.raises(KeyboardInterrupt):
            with atomic_dir(tmp_path / "report") as folder:
                (folder / "report.md").write_text("a report")
    assert out.read_text() == "the previous estimate"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["est.h5"]  # no temporary left
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored ...
    raise_if_noted()  # ... and the latch cleared


def test_the_latch_chains_under_the_other_handlers():
    """A SIGINT noted by a solve's watch or a deferred block reaches the latch too."""
    from tacest.interrupt import _LATCH, interrupt_latch

    with interrupt_latch():
        with pytest.raises(KeyboardInterrupt):
            with deferred_interrupts():
                os.kill(os.getpid(), signal.SIGINT)
                sum(range(1000))
        assert _LATCH.noted
    assert not _LATCH.noted
    with interrupt_latch():
        with watch_interrupts():
            try:
                os.kill(os.getpid(), signal.SIGINT)
            except KeyboardInterrupt:
                pass
        assert _LATCH.noted


def test_the_latch_is_the_main_threads_to_act_on(tmp_path):
    """A file written by another thread (a live recording's snapshot) is not stopped by a
    noted SIGINT: the main thread decides what a Ctrl-C means."""
    import threading

    from tacest.interrupt import interrupt_latch
    from tacest.io.outputs import atomic_file

    out = tmp_path / "snapshot.h5"
    errors = []

    def write():
        try:
            with atomic_file(out) as tmp:
                tmp.write_text("a snapshot")
        except BaseException as exc:  # what the thread saw
            errors.append(exc)

    with interrupt_latch():
        try:
            os.kill(os.getpid(), signal.SIGINT)
        except KeyboardInterrupt:
            pass
        t = threading.Thread(target=write)
        t.start()
        t.join()
    assert not errors and out.read_text() == "a snapshot"


def test_an_interrupt_in_a_finalizer_is_neither_printed_nor_lost(capfd):
    """A SIGINT whose KeyboardInterrupt lands in a __del__ (or a weakref callback) run by
    the garbage collector: Python can only print it ("Exception ignored in ...", with a
    traceback: seen mid-estimate in an explore loop).  Under the latch nothing is
    printed, and the interrupt is raised at the next check."""
    from tacest.interrupt import interrupt_latch, raise_if_noted

    class Finalized:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)  # the handler runs inside __del__
            sum(range(1000))

    with interrupt_latch():
        obj = Finalized()
        del obj  # __del__ raises KeyboardInterrupt, which Python cannot raise here
        with pytest.raises(KeyboardInterrupt):
            raise_if_noted()
    err = capfd.readouterr().err
    assert "Exception ignored" not in err and "Traceback" not in err, err
