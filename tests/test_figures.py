"""Figures a new user found hard to read, checked on the drawn matplotlib objects: the
learning curve (whole-number poke ticks, plain numbers on the log axis, no panel stretched
over a 0.002 % wobble), the diagnosis' held-out figure (none when nothing was compared)
and the 3-D residual figure (a y label, time in seconds)."""

import re
from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")
import matplotlib.figure  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402


@pytest.fixture
def saved_figures(monkeypatch):
    """Every Figure saved during the test (savefig still writes the file)."""
    figs = []
    orig = matplotlib.figure.Figure.savefig

    def savefig(self, *args, **kwargs):
        figs.append(self)
        return orig(self, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)
    return figs


def _labels(axis, minor=False):
    return [t.get_text() for t in axis.get_ticklabels(minor=minor) if t.get_text()]


def test_learning_curve_ticks_labels_and_flat_panel(tmp_path, saved_figures):
    from tacest.planning.explore import plot_learning_curve

    steps = [{"pokes": k, "chamfer": c, "mass_rel": m, "friction_ground_rel": 0.1 / k,
              "friction_finger_rel": 0.23401 + 5e-8 * k}  # a 0.002 % wobble
             for k, c, m in [(1, 0.0062, 0.3), (2, 0.0052, 0.2), (3, 0.0049, 0.1)]]
    plot_learning_curve(tmp_path / "lc.png", [{"policy": "eig", "steps": steps}])
    fig = saved_figures[-1]
    chamfer, mass, _, finger = fig.axes
    for ax in fig.axes:
        xt = _labels(ax.xaxis)
        assert xt and all(re.fullmatch(r"\d+", s) for s in xt), xt  # whole pokes only
    labels = _labels(chamfer.yaxis) + _labels(chamfer.yaxis, minor=True)
    assert labels and not any(("times" in s) or ("×" in s) or ("$" in s) for s in labels), labels
    assert all(re.fullmatch(r"[0-9.]+", s) for s in labels), labels
    lo, hi = finger.get_ylim()
    assert hi - lo >= 2.0 and lo <= 23.401 <= hi  # percent: a range around the value, not 0.002 %
    assert finger.yaxis.get_offset_text().get_text() == ""
    lo, hi = mass.get_ylim()
    assert hi - lo < 40  # a panel that does change keeps matplotlib's range


def test_no_heldout_figure_when_no_candidate_was_compared(tmp_path, monkeypatch):
    from tacest.diagnosis import report

    failed = [SimpleNamespace(name="latency", status="failed", gap_after=float("nan")),
              SimpleNamespace(name="restitution", status="failed", gap_after=float("nan"))]
    diag = SimpleNamespace(runs=[], effects=failed, verdict="none", heldout={}, to_json=lambda: {})
    drawn = []
    monkeypatch.setattr(report, "plot_heldout", lambda d, p: drawn.append(p))
    seen = {}

    def fake_markdown(d, figures):
        seen["figures"] = list(figures)
        return "report"

    monkeypatch.setattr(report, "markdown", fake_markdown)
    names = report.write_report(diag, tmp_path / "out")
    assert not drawn and "heldout_gap.png" not in names and "heldout_gap.png" not in seen["figures"]
    assert not report.heldout_compared(diag)
    failed[0].status, failed[0].gap_after = "ok", 0.3
    assert report.heldout_compared(diag)


def test_residual_figure_3d_has_a_y_label_and_seconds(tmp_path, saved_figures):
    from tacest.diagnosis.diagnose3d import TERMS, Diagnosis3D, write_report_3d

    T, dt = 120, 0.01
    rng = np.random.default_rng(0)
    res = [{t: rng.uniform(0.1, 2.0, T) for t in TERMS}]
    flags = [np.zeros(T, bool)]
    flags[0][40:50] = True
    fit = SimpleNamespace(params={"friction_ground": 0.3}, status="ok", seconds=1.0, train_loss_per_sample=1.0,
                          heldout_loss_per_sample=1.2, heldout_status="ok")
    diag = Diagnosis3D(runs=["a/toss1.h5", "a/toss2.h5"], train=["a/toss1.h5"], heldout=["a/toss2.h5"],
                       residuals=res, flags=flags, where=[], fits={"none": fit}, effects=[], verdict="none",
                       reason="test", floor=1.0, dts=[dt])
    write_report_3d(diag, tmp_path / "d3")
    fig = saved_figures[-1]
    ax = fig.axes[0]
    assert ax.get_ylabel() == "loss per sample"
    assert ax.get_xlabel() == "time (s)" and ax.get_title(loc="left") == "toss1.h5"
    assert ax.get_xlim()[1] == pytest.approx((T - 1) * dt, rel=0.1)
    labels = _labels(ax.yaxis) + _labels(ax.yaxis, minor=True)
    assert labels and not any(("$" in s) or ("×" in s) for s in labels), labels
