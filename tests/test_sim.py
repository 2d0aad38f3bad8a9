"""The 2-D pymunk recorder: contact force and normal conventions on hand-built cases,
known-answer physics, recorded files for every object kind, plans and continuation."""

import json
import math

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.io.plan import Plan, write_plan
from tacest.io.run import read_run, write_run
from tacest.sim.effects import effects_from_json
from tacest.geometry.polygon import box_vertices, polygon_area, polygon_centroid, polygon_inertia, signed_area
from tacest.geometry.transforms import rot2
from tacest.sim.objects import (SimObject, convex_ccw, face_normals, inradius, random_polygon, rest_angle,
                                resting_pose)
from tacest.sim.pokes import POKE_NAMES
from tacest.sim.record import (TOSS_DROP, TOSS_LIFT, TOSS_SPEED, TOSS_SPIN, SimOptions, WorldState, initial_state,
                               record_sim, simulate_pokes, state_from_run, toss_state)
from tacest.sim.world import MAX_FINGER_FORCE

G = 9.81
#: noise-free recordings, so the tests see the physics exactly
CLEAN = dict(noise_force=0.0, noise_position=0.0, noise_normal=0.0)
#: pymunk's contact slop (1e-4 m) plus solver drift: how far a resting body may sink
SLOP_TOL = 3e-4
#: normals from pymunk's circle-polygon contact are exact face normals up to the tilt
#: the iterative solver leaves on a resting box (~1e-5 rad); 1e-3 is far above that
NORMAL_TOL = 1e-3


def _box(mass=0.5, w=0.1, h=0.06, mu_g=0.3, mu_f=0.4):
    v = box_vertices(w, h)
    return SimObject(v, mass, polygon_inertia(v, mass), mu_g, mu_f, "box")


def _state(obj, finger_at, y0=None):
    h = np.max(obj.vertices[:, 1])
    pose = np.array([0.0, h if y0 is None else y0, 0.0])
    return WorldState(obj, pose, np.zeros(3), np.array([finger_at], float), np.array([0.01]))


def test_press_down_on_top_force_points_down_normal_up():
    obj = _box()
    run = simulate_pokes(_state(obj, (0.0, 0.2)), [[0, math.pi / 2, 0.0, 0.03, 0.01, 0.03]], SimOptions(**CLEAN))
    on = run.contact[:, 0] == 1
    assert on.sum() > 20
    f, n = run.force[on, 0], run.normal[on, 0]
    # (a touching sample may carry no impulse, e.g. as the finger leaves)
    assert np.all(f[:, 1] <= 0) and np.mean(f[:, 1] < 0) > 0.9, "the finger pushes the object down (-y)"
    assert np.allclose(n, [0.0, 1.0], atol=NORMAL_TOL), "normal out of the top face, into the finger (+y)"
    # pressing a resting box into the table, the drive saturates at its force limit;
    # 1e-3 relative: pymunk clamps the joint impulse exactly at max_force·h
    assert np.max(-f[:, 1]) == pytest.approx(MAX_FINGER_FORCE, rel=1e-3)
    assert np.all(run.force[~on] == 0) and np.all(np.isnan(run.normal[~on]))
    # the box stays where it is (it only sinks into the contact slop)
    assert np.max(np.abs(run.truth.pose[:, :2] - run.truth.pose[0, :2])) < SLOP_TOL


def test_push_from_left_force_plus_x_normal_minus_x_and_coulomb_sliding():
    obj = _box(mass=0.5, mu_g=0.3)
    run = simulate_pokes(_state(obj, (-0.2, 0.2)), [[0, math.pi, 0.0, 0.03, 0.03, 0.03]], SimOptions(**CLEAN))
    on = run.contact[:, 0] == 1
    f, n = run.force[on, 0], run.normal[on, 0]
    assert np.all(f[:, 0] >= 0) and np.mean(f[:, 0] > 0) > 0.9, "the finger pushes the object to the right (+x)"
    assert np.allclose(n, [-1.0, 0.0], atol=NORMAL_TOL), "normal out of the left face (-x)"
    assert run.truth.pose[-1, 0] > 0.02, "the box slid to the right"
    # steady sliding (the middle of the contact, velocity constant): the push balances
    # Coulomb friction on the ground, fx = mu_g·(m·g - fy); 1e-3 relative is the
    # convergence of pymunk's 30 solver iterations
    mid = f[len(f) // 4: 3 * len(f) // 4]
    assert np.allclose(mid[:, 0], 0.3 * (0.5 * G - mid[:, 1]), rtol=1e-3)


def test_fingers_are_compliant_when_pushed_into_the_ground():
    # a poke aimed into the table far from the object: the finger stops on the ground
    obj = _box()
    state = _state(obj, (0.3, 0.2))
    state.pose[0] = -0.5
    run = simulate_pokes(state, [[0, math.pi / 2, 0.3, 0.0, 0.05, 0.05]], SimOptions(**CLEAN))
    assert run.contact.sum() == 0
    # the fingertip never sinks into the ground by more than the contact slop
    assert np.min(run.finger_position[:, 0, 1]) > 0.01 - SLOP_TOL


def test_segments_tile_the_run_and_params_are_pokes():
    run = record_sim(SimOptions(seed=3, pokes=3, **CLEAN))
    seg = run.actions.segments
    assert seg[0, 0] == 0 and seg[-1, 1] == run.n_samples
    assert np.all(seg[1:, 0] == seg[:-1, 1])
    assert run.actions.names == list(POKE_NAMES) and run.actions.kind == "poke"
    ang = run.actions.params[:, 1]
    assert np.all((ang > 0) & (ang < math.pi))
    # random pokes aim at the true centroid at poke start (no com_offset: the COM)
    for (s, _), p in zip(seg, run.actions.params):
        assert np.allclose(p[2:4], run.truth.pose[s, :2], atol=1e-9)
    # every poke touched the object
    for s, e in seg:
        assert run.contact[s:e].any()


def test_same_seed_same_run_other_seed_other_run():
    a = record_sim(SimOptions(seed=5, pokes=2))
    b = record_sim(SimOptions(seed=5, pokes=2))
    c = record_sim(SimOptions(seed=6, pokes=2))
    assert np.array_equal(a.force, b.force) and np.array_equal(a.finger_position, b.finger_position)
    assert a.truth.mass != c.truth.mass


@pytest.mark.parametrize("spec,kind,k", [("box", "box", 4), ("box:0.08,0.05", "box", 4),
                                         ("polygon", "polygon", None), ("polygon:6", "polygon", 6)])
def test_recorded_objects_validate_and_round_trip(tmp_path, spec, kind, k):
    run = record_sim(SimOptions(object_spec=spec, seed=2, pokes=2, observe_pose=1e-3))
    path = tmp_path / "run.h5"
    write_run(run, path)
    back = read_run(path)
    for name in ("time", "finger_position", "contact", "force", "pose_obs"):
        assert np.array_equal(getattr(back, name), getattr(run, name)), name
    assert np.array_equal(back.normal, run.normal, equal_nan=True)
    assert np.array_equal(back.truth.pose, run.truth.pose)
    assert back.prior["shape"] == kind and back.prior["size_bound"] == pytest.approx(0.3)
    assert json.loads(json.dumps(back.truth.effects)) == [{"name": "none"}]
    v = back.truth.vertices
    if k is not None:
        assert len(v) == k
    if spec == "box:0.08,0.05":
        assert np.ptp(v[:, 0]) == pytest.approx(0.08) and np.ptp(v[:, 1]) == pytest.approx(0.05)
    assert signed_area(v) > 0, "counter-clockwise"
    assert np.allclose(polygon_centroid(v), 0.0, atol=1e-12), "body frame at the COM (uniform density)"
    assert back.truth.inertia == pytest.approx(polygon_inertia(v, back.truth.mass), rel=1e-12)
    assert 0.1 <= back.truth.mass <= 1.0
    assert 0.2 <= back.truth.friction_ground <= 0.8 and 0.1 <= back.truth.friction_finger <= 0.6
    # at rest on the ground at the start: lowest vertex on y = 0
    c, s = math.cos(run.truth.pose[0, 2]), math.sin(run.truth.pose[0, 2])
    y = v @ np.array([s, c]) + run.truth.pose[0, 1]
    assert abs(y.min()) < SLOP_TOL


def test_object_geometry_hand_computed():
    v = box_vertices(0.1, 0.06)
    assert np.allclose(face_normals(v), [[0, -1], [1, 0], [0, 1], [-1, 0]])
    assert inradius(v) == pytest.approx(0.03)
    assert inradius(v, point=[0.01, 0.0]) == pytest.approx(0.03)
    assert inradius(v, point=[0.045, 0.0]) == pytest.approx(0.005)
    rng = np.random.default_rng(0)
    assert rest_angle(v, rng, preferred=0.0) == pytest.approx(0.0)
    assert rest_angle(v, rng, preferred=1.4) == pytest.approx(math.pi / 2)
    assert np.allclose(resting_pose(v, math.pi / 2, x=0.2), [0.2, 0.05, math.pi / 2])
    # a right triangle whose COM is over the corner of its hypotenuse face only: the
    # long legs are stable faces, the short one is too, the hypotenuse is not (t ~ 1/3)
    tri = np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.02]])
    tri = tri - polygon_centroid(tri)
    for seed in range(20):
        a = rest_angle(tri, np.random.default_rng(seed))
        n_down = face_normals(tri) @ rot2(a).T
        assert np.min(n_down[:, 1]) == pytest.approx(-1.0)


@pytest.mark.parametrize("k", [3, 4, 5, 6, 7, 8, 12])
def test_random_polygons_have_k_vertices_and_plausible_size(k):
    for seed in range(10):
        v = random_polygon(np.random.default_rng(seed), k)
        assert v.shape == (k, 2) and signed_area(v) > 0
        assert np.allclose(convex_ccw(v), np.roll(v, -int(np.argmin(v[:, 0])), axis=0))  # convex, same order
        diameter = np.max(np.linalg.norm(v[:, None] - v[None], axis=-1))
        assert 0.06 - 1e-12 <= diameter <= 0.14 + 1e-12
        assert np.allclose(polygon_centroid(v), 0.0, atol=1e-15)


@pytest.mark.parametrize("fmt", ["txt", "csv", "json", "jsondict"])
def test_object_from_file(tmp_path, fmt):
    pts = [[0.0, 0.0], [0.1, 0.0], [0.12, 0.05], [0.03, 0.07]]
    p = tmp_path / f"obj.{'json' if fmt.startswith('json') else fmt}"
    if fmt == "txt":
        p.write_text("# x y in metres\n" + "\n".join(f"{x} {y}" for x, y in pts) + "\n")
    elif fmt == "csv":
        p.write_text("\n".join(f"{x},{y}" for x, y in pts))
    elif fmt == "json":
        p.write_text(json.dumps(pts))
    else:
        p.write_text(json.dumps({"vertices": pts[::-1]}))  # clockwise is fine too
    run = record_sim(SimOptions(object_spec=str(p), seed=1, pokes=1))
    write_run(run, tmp_path / "r.h5")
    back = read_run(tmp_path / "r.h5")
    v = back.truth.vertices
    ref_c = polygon_centroid(np.array(pts))
    assert signed_area(v) == pytest.approx(polygon_area(pts)) and np.allclose(polygon_centroid(v), 0.0, atol=1e-12)
    # the same polygon up to the shift to its centroid (rows may start elsewhere)
    assert {tuple(np.round(r, 9)) for r in v + ref_c} == {tuple(np.round(r, 9)) for r in np.array(pts)}
    assert back.prior["shape"] == "polygon"


@pytest.mark.parametrize("text,msg", [
    ("0 0\n0.1 0\n0.05 0.01\n0.1 0.1\n0 0.1\n", "not convex"),
    ("0 0\n0.1 zero\n", "line 2"),
    ("0 0\n1 0\n1 1\n", "outside"),  # 1 m: forgot to convert from mm/cm?
    ("0 0\n0.1 0\n", "at least 3"),
])
def test_bad_object_files(tmp_path, text, msg):
    p = tmp_path / "o.txt"
    p.write_text(text)
    with pytest.raises(TacestError, match=msg):
        record_sim(SimOptions(object_spec=str(p), pokes=1))


@pytest.mark.parametrize("spec", ["sphere", "box:1,2,3", "box:-0.1,0.1", "polygon:2", "polygon:x"])
def test_bad_object_specs(spec):
    with pytest.raises(TacestError):
        record_sim(SimOptions(object_spec=spec, pokes=1))


def test_dim_other_than_2_or_3_is_a_clear_error():
    # (3-D recording: tests/test_sim3d.py)
    with pytest.raises(TacestError, match="--dim must be 2 or 3"):
        record_sim(SimOptions(dim=4))


def test_streams_options_no_force_and_noise():
    run = record_sim(SimOptions(seed=1, pokes=1, force_stream=False))
    assert run.force is None and run.contact.any()
    clean = record_sim(SimOptions(seed=1, pokes=1, **CLEAN))
    noisy = record_sim(SimOptions(seed=1, pokes=1, noise_force=0.1, noise_position=1e-3, noise_normal=0.05))
    on = clean.contact == 1
    assert np.array_equal(on, noisy.contact == 1), "noise does not change the physics"
    # sample standard deviations of the added noise: with hundreds of samples the
    # estimate is within ~10 % of sigma, so 0.8-1.2 x sigma is a safe band
    dp = (noisy.finger_position - clean.finger_position).ravel()
    assert 0.8e-3 < dp.std() < 1.2e-3
    df = (noisy.force - clean.force)[on].ravel()
    assert 0.08 < df.std() < 0.12
    assert np.all(noisy.force[~on] == 0)
    assert np.allclose(np.linalg.norm(noisy.normal[on], axis=-1), 1.0, atol=1e-12)
    a, b = clean.normal[on], noisy.normal[on]
    ang = np.arctan2(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0], np.sum(a * b, -1))
    assert 0.04 < ang.std() < 0.06


def test_speed_of_a_default_recording():
    import time

    t = time.perf_counter()
    run = record_sim(SimOptions(seed=0))
    elapsed = time.perf_counter() - t
    duration = run.time[-1] - run.time[0]
    assert duration > 6.0
    # the issue: an 8 s recording takes a few seconds at most (here ~1 s)
    assert elapsed < 0.5 * duration


def test_several_fingers():
    run = record_sim(SimOptions(seed=4, pokes=4, fingers=2))
    assert run.finger_position.shape[1] == 2 and run.contact.shape[1] == 2
    assert set(run.actions.params[:, 0].astype(int)) <= {0, 1}


# ---------------------------------------------------------------------------------
# plans and continuation


def _plan(tmp_path, chosen, names=POKE_NAMES):
    p = tmp_path / "plan.h5"
    write_plan(Plan(chosen=np.asarray(chosen, float), candidates=np.asarray([chosen], float),
                    scores=np.array([1.0]), method="random", score="logdet", names=list(names)), p)
    return p


def test_plan_executes_one_poke_with_the_plans_target(tmp_path):
    base = initial_state(SimOptions(seed=9))
    target = base.pose[:2] + np.array([0.005, 0.0])  # "an estimate": off the true COM
    chosen = [0, 2.5, target[0], target[1], 0.02, 0.04]
    run = record_sim(SimOptions(seed=9), plan_path=_plan(tmp_path, chosen))
    assert run.actions.params.shape == (1, 6)
    assert np.allclose(run.actions.params[0], chosen)
    assert run.contact.any()


def test_plan_parameters_are_matched_by_name(tmp_path):
    base = initial_state(SimOptions(seed=9))
    names = ["speed", "depth", "target_y", "target_x", "approach_angle", "finger"]
    chosen = [0.04, 0.02, base.pose[1], base.pose[0], 2.5, 0]
    run = record_sim(SimOptions(seed=9), plan_path=_plan(tmp_path, chosen, names))
    assert np.allclose(run.actions.params[0], chosen[::-1])


def test_bad_plan_poke_is_a_clear_error(tmp_path):
    with pytest.raises(TacestError, match="approach_angle"):
        record_sim(SimOptions(seed=9), plan_path=_plan(tmp_path, [0, -1.0, 0, 0.03, 0.02, 0.04]))
    with pytest.raises(TacestError, match="finger"):
        record_sim(SimOptions(seed=9), plan_path=_plan(tmp_path, [3, 1.0, 0, 0.03, 0.02, 0.04]))


def test_plan_appends_to_an_existing_run(tmp_path):
    opts = SimOptions(seed=11, pokes=2, effects=["force_bias"])
    first = record_sim(opts)
    path = tmp_path / "run.h5"
    write_run(first, path)
    last = first.truth.pose[-1]
    chosen = [0, 0.6, last[0], last[1], 0.02, 0.04]
    run = record_sim(opts, plan_path=_plan(tmp_path, chosen), append_to=path)
    write_run(run, path)
    back = read_run(path)
    T0 = first.n_samples
    assert back.n_samples > T0
    assert np.array_equal(back.truth.pose[:T0], first.truth.pose)
    assert np.array_equal(back.time[:T0], first.time)
    assert np.allclose(np.diff(back.time), back.dt)
    # the world continues: the object starts where it was (at rest: within the slop)
    assert np.allclose(back.truth.pose[T0], last, atol=SLOP_TOL)
    seg = back.actions.segments
    assert len(seg) == 3 and seg[2, 0] == T0 and seg[2, 1] == back.n_samples
    assert np.allclose(back.actions.params[2], chosen)
    # same effects, same parameters
    assert effects_from_json(back.truth.effects) == effects_from_json(first.truth.effects)
    assert back.contact[T0:].any()


def test_append_needs_truth(tmp_path):
    run = record_sim(SimOptions(seed=1, pokes=1))
    path = tmp_path / "hidden.h5"
    write_run(run, path, include_truth=False)
    with pytest.raises(TacestError, match="no /truth"):
        record_sim(SimOptions(seed=1), plan_path=_plan(tmp_path, [0, 1.0, 0, 0.03, 0.02, 0.04]), append_to=path)


def test_state_from_run_round_trip():
    run = record_sim(SimOptions(seed=2, pokes=1, effects=["face_friction", "latency:samples=2"]))
    state = state_from_run(run)
    assert np.allclose(state.pose, run.truth.pose[-1])
    assert [e.name for e in state.effects] == ["face_friction", "latency"]
    assert state.obj.mass == run.truth.mass


def test_simulate_pokes_from_an_estimate_like_state():
    # the planner's use: an object it believes in, pokes it chooses, no noise
    obj = _box(mass=0.3, w=0.08, h=0.08)
    state = _state(obj, (0.0, 0.15))
    acts = np.array([[0, 0.4, 0.0, 0.04, 0.02, 0.04], [0, 2.7, 0.0, 0.04, 0.02, 0.04]])
    run = simulate_pokes(state, acts, SimOptions(**CLEAN))
    assert run.actions.segments.shape == (2, 2)
    assert np.array_equal(run.actions.params, acts)
    run.validate()
    # or straight from the object: placed at rest at x = 0, fingers parked above it
    again = simulate_pokes(obj, acts, SimOptions(**CLEAN))
    assert np.allclose(again.truth.pose[0], [0.0, 0.04, 0.0], atol=SLOP_TOL)
    assert np.all(again.finger_position[0, :, 1] > 0.08)
    # the same pokes on the same object: the same outcome up to where the fingers started
    assert again.truth.pose[-1, 0] == pytest.approx(run.truth.pose[-1, 0], abs=1e-3)


#: m: pymunk integrates gravity with semi-implicit Euler substeps (h = 0.5 ms), whose
#: position error against the exact parabola is g·h·t/2, 0.5 mm after 0.2 s... measured
#: well below that at the sample instants; 1e-3 m bounds it with room
BALLISTIC_TOL = 1e-3


def test_a_toss_flies_a_parabola_then_lands_and_rests():
    """Known answer: between release and the first touch of the ground the COM follows
    y = y0 + vy·t − g·t²/2, x = x0 + vx·t, and the angle turns at the release spin;
    the recording ends at rest with the fingers never touching."""
    opts = SimOptions(seed=5, **CLEAN)
    tossed = toss_state(initial_state(opts), np.random.default_rng(1), x=0.0)
    P0, V0 = tossed.pose, tossed.velocity
    lowest = float(np.min((tossed.obj.vertices @ rot2(P0[2]).T)[:, 1])) + P0[1]
    assert TOSS_DROP[0] <= lowest <= TOSS_DROP[1]
    assert TOSS_SPEED[0] <= abs(V0[0]) <= TOSS_SPEED[1] and TOSS_LIFT[0] <= V0[1] <= TOSS_LIFT[1]
    assert TOSS_SPIN[0] <= abs(V0[2]) <= TOSS_SPIN[1]
    run = simulate_pokes(tossed, np.zeros((0, 6)), opts, settle_first=True)
    P = run.truth.pose
    t = run.time - run.time[0]
    heights = np.array([np.min((run.truth.vertices @ rot2(q[2]).T)[:, 1]) + q[1] for q in P])
    flying = np.cumprod(heights > 2e-3).astype(bool)  # up to the first touch of the ground
    assert flying.sum() > 15, "a flight of 0.2-0.35 s at 100 Hz"
    tf = t[flying]
    assert np.allclose(P[flying, 0], P0[0] + V0[0] * tf, atol=BALLISTIC_TOL)
    assert np.allclose(P[flying, 1], P0[1] + V0[1] * tf - 0.5 * G * tf ** 2, atol=BALLISTIC_TOL)
    assert np.allclose(P[flying, 2], P0[2] + V0[2] * tf, atol=1e-6 + 1e-3 * abs(V0[2]))
    assert not run.contact.any() and len(run.actions.segments) == 0
    assert np.all(np.abs(P[-5:] - P[-1]) < SLOP_TOL), "it ends at rest"
    assert np.min(heights) > -1e-3, "it lands on the ground, not through it"


def test_a_toss_then_pokes_waits_for_rest_and_keeps_the_seeds_streams():
    base = SimOptions(seed=2, pokes=1, observe_pose=5e-4)
    tossed = record_sim(SimOptions(**{**base.__dict__, "toss": True}))
    plain = record_sim(base)
    assert np.allclose(tossed.truth.vertices, plain.truth.vertices) and tossed.truth.mass == plain.truth.mass
    a = int(tossed.actions.segments[0, 0])
    assert a > 0 and not tossed.contact[:a].any()
    v = np.diff(tossed.truth.pose[a:a + 2], axis=0) / tossed.dt  # the finger is still in transit
    assert np.all(np.abs(v) < 0.05), "the poke starts with the object at rest"
    assert tossed.pose_obs is not None and np.all(np.isfinite(tossed.pose_obs[0]))
