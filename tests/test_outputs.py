"""Outputs never replace inputs or non-files (issue 27, item 1): every command checks
its output before any work (tacest/io/outputs.py), one line, exit 2, nothing touched."""

import os
import time

import pytest

from tacest.errors import TacestError
from tacest.io.outputs import atomic_dir, check_output, replacing_files
from tacest.io.run import read_run, write_run
from tests.reliability_files import make_run, one_error_line, poke_plan, tacest, truth_estimate


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("outputs")
    run = make_run(d / "run.h5", seed=1, pokes=2)
    est = truth_estimate([run], d / "est.h5")
    plan = poke_plan(d / "plan.h5", [run], est)
    return {"dir": d, "run": run, "est": est, "plan": plan}


def _unchanged(path, before: bytes):
    assert path.read_bytes() == before, f"{path} was changed"


@pytest.mark.parametrize("command", [
    lambda f: ["estimate", f["run"], "-o", f["run"]],
    lambda f: ["plan", f["est"], f["run"], "-o", f["est"]],
    lambda f: ["plan", f["est"], f["run"], "-o", f["run"]],
    lambda f: ["record", "--plan", f["plan"], "-o", f["plan"]],
    lambda f: ["eval", f["est"], "--truth", f["run"], "--plot", f["est"]],
    lambda f: ["export", f["est"], "--format", "mjcf", "-o", f["est"]],
    lambda f: ["export", f["est"], "-o", f["dir"] / "object.xml", "--trajectory", f["est"]],
    lambda f: ["view", f["run"], "-o", f["run"]],
], ids=["estimate-run", "plan-estimate", "plan-run", "record-plan", "eval-plot", "export-estimate",
        "export-trajectory", "view-run"])
def test_an_output_that_is_an_input_is_refused(files, command):
    args = command(files)
    target = args[-1]
    before = target.read_bytes()
    res = tacest(*args)
    assert res.returncode == 2
    assert "is also an input" in one_error_line(res)
    _unchanged(target, before)


def test_export_checks_the_companion_file_before_any_work(files, tmp_path):
    """A URDF's mesh is written beside it as NAME.stl: a link there is refused before
    anything is written."""
    (tmp_path / "object.stl").symlink_to(files["run"])
    before = files["run"].read_bytes()
    res = tacest("export", files["est"], "-o", tmp_path / "object.urdf")
    assert res.returncode == 2 and "symbolic link" in one_error_line(res)
    assert not (tmp_path / "object.urdf").exists()
    _unchanged(files["run"], before)


def test_a_hard_link_to_an_input_is_the_same_file(files, tmp_path):
    link = tmp_path / "other_name.h5"
    os.link(files["run"], link)
    res = tacest("estimate", files["run"], "-o", link)
    assert res.returncode == 2 and "is also an input" in one_error_line(res)
    _unchanged(files["run"], link.read_bytes())


def test_a_fifo_or_a_symlink_is_not_replaced(files, tmp_path):
    fifo = tmp_path / "fifo.h5"
    os.mkfifo(fifo)
    res = tacest("estimate", files["run"], "-o", fifo)
    assert res.returncode == 2 and "not a regular file" in one_error_line(res)
    assert fifo.is_fifo()
    link = tmp_path / "link.h5"
    link.symlink_to(files["est"])
    before = files["est"].read_bytes()
    res = tacest("estimate", files["run"], "-o", link)
    assert res.returncode == 2 and "symbolic link" in one_error_line(res)
    assert link.is_symlink() and os.readlink(link) == str(files["est"])
    _unchanged(files["est"], before)


def test_an_unwritable_folder_fails_before_any_work(files):
    # /proc takes no new files, even from root (whom a chmod would not stop)
    t0 = time.monotonic()
    res = tacest("estimate", files["run"], "-o", "/proc/tacest_estimate.h5")
    assert res.returncode == 2
    assert "cannot write in folder /proc" in one_error_line(res)
    assert time.monotonic() - t0 < 30  # no solve: the check comes first
    res = tacest("estimate", files["run"], "-o", files["dir"] / "missing" / "est.h5")
    assert res.returncode == 2 and "does not exist" in one_error_line(res)


def test_a_report_folder_that_holds_an_input_is_refused(files, tmp_path):
    folder = tmp_path / "report"
    folder.mkdir()
    (folder / "report.md").write_text("an earlier report")
    inside = folder / "run.h5"
    inside.write_bytes(files["run"].read_bytes())
    res = tacest("diagnose", inside, files["run"], "-o", folder)
    assert res.returncode == 2 and "holds the input" in one_error_line(res)
    assert inside.read_bytes() == files["run"].read_bytes()


def test_writers_refuse_links_and_folders_as_a_last_guard(files, tmp_path):
    run = read_run(files["run"])
    link = tmp_path / "link.h5"
    link.symlink_to(files["est"])
    with pytest.raises(TacestError, match="symbolic link"):
        write_run(run, link)
    (tmp_path / "folder.h5").mkdir()
    with pytest.raises(TacestError, match="is a folder"):
        write_run(run, tmp_path / "folder.h5")
    with pytest.raises(TacestError, match="not a folder"):
        with atomic_dir(files["run"]):
            pass
    assert not list(tmp_path.glob(".*.part*"))


def test_check_output_accepts_a_new_file_and_replaces_a_regular_one(files, tmp_path):
    assert check_output(tmp_path / "new.h5", inputs=[files["run"]]) == tmp_path / "new.h5"
    (tmp_path / "old.h5").write_text("an earlier output")
    check_output(tmp_path / "old.h5", inputs=[files["run"], None])
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tacest-probe")]


def test_replacing_files_puts_the_earlier_files_back_on_an_interrupt(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "run.h5").write_text("earlier run")
    (out / "notes.txt").write_text("the user's")
    with pytest.raises(KeyboardInterrupt):
        with replacing_files(out, ("run.h5", "estimate_*.h5")) as d:
            assert not (d / "run.h5").exists()  # moved aside while the command works
            (d / "run.h5").write_text("new run")
            (d / "estimate_1.h5").write_text("new estimate")
            raise KeyboardInterrupt
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "run.h5"]
    assert (out / "run.h5").read_text() == "earlier run"
    # an error: the earlier files are gone (never mistaken for this run's), the new stay
    with pytest.raises(TacestError):
        with replacing_files(out, ("run.h5",)) as d:
            raise TacestError("a failed solve")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no folder left aside
