"""Several fingers on the serial link: a lost finger line leaves only that (sample,
finger) unknown (``/quality/missing_finger``); its sibling lines keep their values, and
the estimator's data weights are zero exactly at the unknown pairs."""

import casadi as ca
import numpy as np
import pytest

from tacest.estimation.data import data_matrix, parameter_vector, touching
from tacest.estimation.estimator import ImplicitEstimator
from tacest.estimation.initial import initial_guess
from tacest.estimation.problem2d import Problem2D
from tacest.io.run import read_run
from tacest.sensors.emulator import Faults, builtin_run, emulate_bytes
from tacest.sensors.serial_protocol import Precision, format_sample
from tacest.sensors.serial_rig import Assembler, write_snapshot

P = Precision()
# Round-trip tolerances: values are printed with fixed decimals, so they come back to
# within half a unit in the last place (float64 parsing adds < 1e-15).
TOL_POS = 0.5 * 10.0 ** -P.position   # m
TOL_FORCE = 0.5 * 10.0 ** -P.force    # N
# normals: each component rounded by <= 0.5e-5, then renormalised (moves a component by
# at most sqrt(3) * 0.5e-5); 2e-5 covers both
TOL_NORMAL = 2e-5

HDR2F = b"#TACEST,1,dim=2,fingers=2,radius=0.010;0.012,dt=0.01\n"


def assemble(data):
    a = Assembler()
    a.feed(data)
    a.finish()
    return a


def data_columns(F):
    """Column slices of data_matrix, in the layout Problem2D.n_data documents."""
    names = ("c_f", "v_f", "contact", "n_meas", "F_meas", "w_force", "w_tact", "radius", "c_f_start",
             "ends", "q_obs", "w_pose")
    sizes = (2 * F, 2 * F, F, 2 * F, 2 * F, F, F, F, 2 * F, F, 3, 1)
    assert sum(sizes) == Problem2D.n_data(None, F)
    edges = np.cumsum((0,) + sizes)
    return {n: slice(int(a), int(b)) for n, a, b in zip(names, edges[:-1], edges[1:])}


def test_corrupted_line_of_finger_1_keeps_finger_0_and_zeroes_only_its_weights(tmp_path):
    src = builtin_run(2, 2, 300, dt=0.01)
    # a sample where finger 0 touches, so that its contact, force and normal are real data
    k = int(np.flatnonzero(src.contact[100:, 0] == 1)[0]) + 100
    data, log = emulate_bytes(src, Faults(corrupt_lines=frozenset({(k, 1)})))
    assert log.corrupted == 1 and (k, 1) not in log.intact and (k, 0) in log.intact
    a = assemble(data)
    s = a.summary()
    assert s.dropped == {**s.dropped, "checksum": 1} and s.dropped_lines == 1
    assert (s.kept_samples, s.kept_lines, s.missing_samples, s.partial_samples) == (299, 599, 1, 1)
    out = tmp_path / "rec.h5"
    write_snapshot(*a.to_run(), out)
    run = read_run(out)

    expect = np.zeros((300, 2), np.uint8)
    expect[k, 1] = 1
    np.testing.assert_array_equal(run.missing_finger, expect)
    np.testing.assert_array_equal(run.missing, expect.any(axis=1))
    np.testing.assert_array_equal(run.finger_missing_mask, expect.astype(bool))
    # finger 0 keeps its contact, force and normal on that sample
    assert run.contact[k, 0] == 1
    np.testing.assert_allclose(run.force[k, 0], src.force[k, 0], atol=TOL_FORCE, rtol=0)
    np.testing.assert_allclose(run.normal[k, 0], src.normal[k, 0], atol=TOL_NORMAL, rtol=0)
    np.testing.assert_allclose(run.finger_position[k, 0], src.finger_position[k, 0], atol=TOL_POS, rtol=0)
    # finger 1 there: placeholders, its position interpolated between its neighbours
    assert run.contact[k, 1] == 0 and np.all(run.force[k, 1] == 0) and np.all(np.isnan(run.normal[k, 1]))
    mid = 0.5 * (src.finger_position[k - 1, 1] + src.finger_position[k + 1, 1])
    np.testing.assert_allclose(run.finger_position[k, 1], mid, atol=2 * TOL_POS, rtol=0)
    # every other line is as sent
    ok = ~expect.astype(bool)
    np.testing.assert_allclose(run.finger_position[ok], src.finger_position[ok], atol=TOL_POS, rtol=0)
    np.testing.assert_array_equal(run.contact[ok], src.contact[ok])

    # the estimator: weights zero exactly at (k, finger 1), the measured data elsewhere
    F = 2
    D = data_matrix(run, F)
    col = data_columns(F)
    w_zero = np.zeros((300, F), bool)
    w_zero[k, 1] = True
    for w in ("w_tact", "w_force"):
        np.testing.assert_array_equal(D[:, col[w]] == 0.0, w_zero)
    np.testing.assert_array_equal(D[:, col["contact"]], run.contact * ~w_zero)
    assert D[k, col["contact"]][0] == 1.0
    np.testing.assert_allclose(D[k, col["F_meas"]].reshape(F, 2)[0], run.force[k, 0])
    np.testing.assert_allclose(D[k, col["n_meas"]].reshape(F, 2)[0], run.normal[k, 0])
    on = touching(run)
    assert on[k, 0] and not on[k, 1]
    np.testing.assert_array_equal(on, run.contact.astype(bool) & ~w_zero)

    # a reader that knows only the per-sample mask gives the whole sample no weight
    old = run.replace(missing_finger=None)
    D_old = data_matrix(old, F)
    assert np.all(D_old[k, col["w_tact"]] == 0.0) and np.count_nonzero(D_old[:, col["w_tact"]] == 0.0) == F


def test_partial_samples_at_both_ends_of_the_run_are_kept():
    # the recorder starts after finger 0 of seq 0 went by; the link ends before finger 1 of seq 4
    body = b""
    for seq in range(5):
        for f in range(2):
            if (seq, f) in ((0, 0), (4, 1)):
                continue
            body += (format_sample(seq, seq * 0.01, f, (seq * 1e-3, 0.05 + f), 0, (0.0, 0.0), None) + "\n").encode()
    a = assemble(HDR2F + body)
    s = a.summary()
    assert (s.kept_samples, s.kept_lines, s.missing_samples, s.gaps, s.partial_samples) == (3, 8, 2, 2, 2)
    run, clock = a.to_run()
    run.validate()
    assert run.n_samples == 5
    np.testing.assert_array_equal(run.missing_finger, [[1, 0], [0, 0], [0, 0], [0, 0], [0, 1]])
    # unknown positions before the first and after the last known one are held
    np.testing.assert_allclose(run.finger_position[0, 0], [1e-3, 0.05], atol=TOL_POS)
    np.testing.assert_allclose(run.finger_position[4, 1], [3e-3, 1.05], atol=TOL_POS)
    assert np.all(np.isfinite(clock))


def test_no_run_before_a_complete_sample():
    # two samples, finger 1 only: positions of finger 0 would be unknown everywhere
    body = b"".join((format_sample(q, q * 0.01, 1, (0.0, 1.0), 0, (0.0, 0.0), None) + "\n").encode()
                    for q in range(2))
    a = assemble(HDR2F + body)
    assert a.to_run() is None and a.summary().kept_samples == 0


@pytest.mark.parametrize("fingers", [2, 3])
def test_every_intact_line_is_kept_with_its_values(fingers):
    """The issue's 'none valid lost' with several fingers: corrupted, truncated and
    dropped lines leave their own (sample, finger) unknown and nothing else."""
    src = builtin_run(2, fingers, 3000, dt=0.001)
    data, log = emulate_bytes(src, Faults(corrupt=0.01, truncate=0.005, drop_line=0.005, drop=0.002, seed=3))
    a = assemble(data)
    s = a.summary()
    assert s.kept_lines == log.intact_lines
    assert s.dropped_lines == log.corrupted + log.truncated
    run, _ = a.to_run()
    first = min(q for q, _ in log.intact)
    known = np.zeros((run.n_samples, fingers), bool)
    for q, f in log.intact:
        known[q - first, f] = True
    np.testing.assert_array_equal(run.missing_finger, ~known)
    sl = slice(first, first + run.n_samples)
    np.testing.assert_allclose(run.finger_position[known], src.finger_position[sl][known], atol=TOL_POS, rtol=0)
    np.testing.assert_array_equal(run.contact[known], src.contact[sl][known])
    np.testing.assert_allclose(run.force[known], src.force[sl][known], atol=TOL_FORCE, rtol=0)
    assert s.partial_samples > 10  # the faults above hit single lines of many samples


def test_emulator_plays_a_per_finger_mask_and_the_recorder_gets_it_back(tmp_path):
    src = builtin_run(2, 2, 200, dt=0.01)
    mf = np.zeros((200, 2), np.uint8)
    mf[[40, 41], 0] = 1
    mf[120, :] = 1
    src.missing_finger = mf
    src.missing = mf.any(axis=1).astype(np.uint8)
    src.contact[mf == 1] = 0
    src.normal[mf == 1] = np.nan
    src.force[mf == 1] = 0.0
    src.validate()
    data, log = emulate_bytes(src)
    assert log.intact_lines == 400 - 4
    a = assemble(data)
    run, _ = a.to_run()
    np.testing.assert_array_equal(run.missing_finger, mf)
    np.testing.assert_array_equal(run.missing, src.missing)
    s = a.summary()
    assert (s.missing_samples, s.gaps, s.partial_samples) == (3, 2, 2)


def test_an_unknown_finger_constrains_nothing_on_its_sample():
    """The estimator's objective and constraints do not depend on the placeholder
    position of an unknown (sample, finger): its weights are 0 and its impulse is held
    at 0 (variable bounds), so moving the placeholder anywhere changes nothing, while
    moving a known finger does."""
    src = builtin_run(2, 2, 40, dt=0.05)
    k = 25  # both fingers touch the disc here; the line of finger 1 is lost
    assert src.contact[k].all()
    data, _ = emulate_bytes(src, Faults(corrupt_lines=frozenset({(k, 1)})))
    run, _ = assemble(data).to_run()
    assert run.missing_finger[k, 1] == 1 and run.missing_finger.sum() == 1
    est = ImplicitEstimator([run], "box")
    pr = est.problem
    rng = np.random.default_rng(0)
    z = initial_guess(pr, [run], est.scales, est.s0) + rng.normal(size=pr.n_z) * 0.02
    lbx, ubx = est.variable_bounds(z)
    z = np.clip(z, lbx, ubx)  # impulses of fingers that do not touch (or are unknown) at 0
    p = parameter_vector(pr, [run], est.scales, est.config, 0.5, 2.0, est.s0, ridge=0.0)
    fg = ca.Function("fg", [pr.z_sym, pr.p_sym], [pr.f, pr.g])
    start, n_g, _ = pr.p_offsets[0]
    n_data = pr.n_data(2)
    c_f = data_columns(2)["c_f"]

    def moved(sample, finger, shift):
        q = p.copy()
        at = start + n_g + sample * n_data + c_f.start + 2 * finger
        q[at:at + 2] += shift
        f, g = fg(z, q)
        return float(f), np.asarray(g).ravel()

    f0, g0 = moved(k, 1, 0.0)
    for shift in ([0.05, 0.0], [-0.03, 0.04]):  # m: centimetres, into and around the object
        f1, g1 = moved(k, 1, np.array(shift))
        assert f1 == f0 and np.array_equal(g1, g0)
    # the known, touching finger on the same sample does count (the test can fail)
    f2, _ = moved(k, 0, np.array([0.05, 0.0]))
    assert f2 > f0 + 1.0
