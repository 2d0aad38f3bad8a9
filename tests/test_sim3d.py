"""The 3-D MuJoCo recorder: force and normal conventions on hand-built cases, resting,
mass properties, run files, effects, plans and the CLI."""

import json
import math

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.geometry.polytope import box_vertices_3d, polytope_centroid, polytope_inertia
from tacest.geometry.transforms import quat_to_matrix
from tacest.io.plan import Plan, write_plan
from tacest.io.run import read_run, write_run
from tacest.sim import effects as fx
from tacest.dims import record_sim
from tacest.sim.record import SimOptions
from tacest.sim3d.objects import (SimObject3, check_convex, hull_faces, inradius, random_polytope, stable_faces)
from tacest.sim3d.pokes import POKE3_NAMES
from tacest.sim3d.record import (WorldState3, effect_context, simulate_pokes, state_at_rest, state_from_run)
from tacest.sim3d.world import MAX_FINGER_FORCE

pytest.importorskip("mujoco")

G = 9.81
#: noise-free recordings, so the tests see the physics exactly
CLEAN = dict(noise_force=0.0, noise_position=0.0, noise_normal=0.0, dim=3)
#: m, how far a resting object may sink: MuJoCo's soft contact (solref 2 ms, solimp
#: 0.95-0.995) lets a resting 0.1-1 kg object sink (1-d)·g/(d·k) ~ 2-5 µm; 2e-5 m is
#: several times that and far below any real error (a tilt of 1e-3 rad moves a corner 50 µm)
REST_SINK_TOL = 2e-5
#: m, SPEC-level bound on contact penetration at any recorded sample (the task's < 1 mm)
PENETRATION_TOL = 1e-3
#: normals of a sphere on a flat face are the face normal up to the tilt the solver
#: leaves on a resting box (< 1e-4 rad measured); 1e-3 is far above that
NORMAL_TOL = 1e-3
#: unit quaternions / normals as stored: float64 normalised, so 1e-9 is generous
UNIT_TOL = 1e-9
#: relative accuracy of MuJoCo's soft (elliptic-cone) Coulomb friction in steady
#: sliding: sample-to-sample ripple ~0.5 %, the mean within ~0.2 %
FRICTION_RTOL = 0.03


def _box(mass=0.5, ext=(0.1, 0.08, 0.06), mu_g=0.3, mu_f=0.4):
    v = box_vertices_3d(ext)
    return SimObject3(v, mass, polytope_inertia(v, mass), mu_g, mu_f, "box")


def _state(obj, finger_at, effects=()):
    st = state_at_rest(obj, effects=fx.resolve_effects(list(effects), 0, effect_context(obj)))
    st.p_finger__world = np.array([finger_at], float)
    return st


def _lowest_z(run):
    """(T,) m, height of the object's lowest vertex (from /truth)."""
    V, q = run.truth.vertices, run.truth.pose
    return np.min(np.einsum("kj,tij->tki", V, quat_to_matrix(q[:, 3:]))[..., 2], axis=1) + q[:, 2]


def _poke(finger=0, az=0.0, el=math.pi / 2, target=(0.0, 0.0, 0.03), depth=0.01, speed=0.03):
    return [finger, az, el, *target, depth, speed]


@pytest.fixture(scope="module")
def random_run():
    """A default-style recording of a random polytope with three pokes (shared)."""
    return record_sim(SimOptions(dim=3, object_spec="polytope", seed=1, pokes=3, fingers=2, observe_pose=1e-3))


# ---------------------------------------------------------------------------------
# contact conventions on hand-built cases


def test_press_down_on_top_force_minus_z_normal_plus_z():
    run = simulate_pokes(_state(_box(), (0.0, 0.0, 0.12)), [_poke()], SimOptions(**CLEAN))
    on = run.contact[:, 0] == 1
    assert on.sum() > 20
    f, n = run.force[on, 0], run.normal[on, 0]
    assert np.all(f[:, 2] < 0), "the finger pushes the object down (-z)"
    assert np.allclose(n, [0.0, 0.0, 1.0], atol=NORMAL_TOL), "normal out of the top face, into the finger"
    # pressing a resting box into the table the drive saturates at its force limit;
    # 1e-3 relative: the limit is applied exactly, contact forces converge to 1e-10
    assert np.max(-f[:, 2]) == pytest.approx(MAX_FINGER_FORCE, rel=1e-3)
    assert np.max(np.abs(f[:, :2])) < 1e-6 * MAX_FINGER_FORCE, "no sideways force on a straight press"
    assert np.all(run.force[~on] == 0) and np.all(np.isnan(run.normal[~on]))
    assert np.max(np.abs(run.truth.pose[:, :3] - run.truth.pose[0, :3])) < REST_SINK_TOL * 5


def test_push_from_minus_x_force_plus_x_normal_minus_x_and_coulomb_sliding():
    obj = _box(mass=0.5, mu_g=0.3)
    run = simulate_pokes(_state(obj, (-0.2, 0.0, 0.1)), [_poke(az=math.pi, el=0.0, depth=0.03)],
                         SimOptions(**CLEAN))
    on = run.contact[:, 0] == 1
    f, n = run.force[on, 0], run.normal[on, 0]
    assert np.all(f[:, 0] > 0), "the finger pushes the object along +x"
    assert np.allclose(n, [-1.0, 0.0, 0.0], atol=NORMAL_TOL), "normal out of the -x face"
    assert run.truth.pose[-1, 0] > 0.02, "the box slid along +x"
    assert np.max(np.abs(run.truth.pose[:, 1])) < 1e-6, "and not sideways"
    # steady sliding (middle of the contact): the push balances Coulomb friction on the
    # ground, fx = mu_g·(m·g - fz)
    mid = f[len(f) // 4: 3 * len(f) // 4]
    ratio = mid[:, 0] / (0.3 * (0.5 * G - mid[:, 2]))
    assert np.allclose(ratio, 1.0, rtol=FRICTION_RTOL) and abs(np.mean(ratio) - 1) < 0.01


def test_oblique_press_that_sticks_pushes_along_the_finger_motion():
    # a heavy, high-friction box pressed at 30° from the vertical, coming from -x: the
    # finger sticks (tan 30° < mu_f), so its force is along its motion (+x, -z) and the
    # tangential part has the sign of the push (checks the friction force's sign)
    obj = _box(mass=1.0, mu_g=0.9, mu_f=0.9)
    el = math.radians(60.0)
    run = simulate_pokes(_state(obj, (-0.1, 0.0, 0.15)), [_poke(az=math.pi, el=el, depth=0.02)], SimOptions(**CLEAN))
    on = run.contact[:, 0] == 1
    # the approach goes on 0.02 m (depth) / 0.03 m/s = 0.67 s past the first touch, then
    # the finger retreats: the first 60 contact samples (0.6 s) are the press
    f = run.force[on, 0][:60]
    strong = f[np.linalg.norm(f, axis=1) > 0.5 * MAX_FINGER_FORCE]
    assert len(strong) > 20
    push = np.array([math.cos(el), 0.0, -math.sin(el)])  # -d: the finger's direction of motion
    cosang = strong @ push / np.linalg.norm(strong, axis=1)
    assert np.all(cosang > math.cos(math.radians(2.0))), "force within 2° of the finger's motion"
    assert np.allclose(run.normal[on, 0], [0.0, 0.0, 1.0], atol=NORMAL_TOL)
    assert np.max(np.abs(run.truth.pose[:, :3] - run.truth.pose[0, :3])) < 1e-4, "the box held still"


# ---------------------------------------------------------------------------------
# objects, resting, mass properties


def test_random_objects_rest_on_the_ground_and_stay_at_rest():
    for seed, spec in [(0, "box"), (2, "polytope"), (3, "polytope:8")]:
        run = record_sim(SimOptions(object_spec=spec, seed=seed, pokes=0, **CLEAN))
        low = _lowest_z(run)
        assert np.all(np.abs(low) < REST_SINK_TOL), (spec, low.min(), low.max())
        q = run.truth.pose
        assert np.max(np.abs(q[:, :3] - q[0, :3])) < REST_SINK_TOL, "no drift"
        assert np.allclose(np.linalg.norm(q[:, 3:], axis=1), 1.0, atol=UNIT_TOL)
        assert not run.contact.any()


def test_truth_inertia_is_the_uniform_density_inertia_of_the_hull():
    import mujoco
    import trimesh

    run = record_sim(SimOptions(object_spec="polytope:9", seed=5, pokes=0, **CLEAN))
    V, m, inertia = run.truth.vertices, run.truth.mass, np.asarray(run.truth.inertia)
    assert V.shape == (9, 3) and inertia.shape == (3, 3)
    mesh = trimesh.convex.convex_hull(V)
    mesh.density = m / mesh.volume
    # both are float64 sums over the same few triangles: 1e-9 relative is round-off
    assert np.allclose(inertia, mesh.moment_inertia, rtol=1e-9, atol=1e-12)
    assert np.allclose(polytope_centroid(V), 0.0, atol=1e-12), "body origin at the COM"
    # an independent computation: MuJoCo's own mesh inertia (principal moments)
    xml = (f'<mujoco><asset><mesh name="m" vertex="{" ".join(map(repr, V.ravel().tolist()))}"/></asset><worldbody>'
           f'<body><freejoint/><geom type="mesh" mesh="m" mass="{m!r}"/></body></worldbody></mujoco>')
    mj = mujoco.MjModel.from_xml_string(xml)
    assert np.allclose(np.sort(mj.body_inertia[1]), np.sort(np.linalg.eigvalsh(inertia)), rtol=1e-6)
    # and the box formula m(h²+d²)/12 ...
    box = _box(mass=0.6, ext=(0.1, 0.08, 0.06))
    assert np.allclose(np.diag(box.inertia), 0.05 * np.array([0.08 ** 2 + 0.06 ** 2, 0.1 ** 2 + 0.06 ** 2,
                                                               0.1 ** 2 + 0.08 ** 2]), rtol=1e-12)


def test_mujoco_collision_mesh_is_where_the_truth_vertices_are():
    st = state_at_rest(SimObject3(random_polytope(np.random.default_rng(4), 10), 0.3, np.eye(3) * 1e-4, 0.5, 0.5),
                       quat=np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2]))
    w = st.world()
    mesh = w.mesh_vertices__world()
    truth = w.vertices__world()
    d = np.linalg.norm(mesh[:, None, :] - truth[None, :, :], axis=-1)
    # 1e-7 m: MuJoCo stores mesh vertices in float32 (6e-8 relative of ~0.1 m)
    assert mesh.shape == truth.shape and np.all(d.min(axis=1) < 1e-7) and np.all(d.min(axis=0) < 1e-7)


@pytest.mark.parametrize("k", [4, 6, 12, 20])
def test_random_polytopes_have_k_hull_vertices_and_plausible_size(k):
    V = random_polytope(np.random.default_rng(k), k)
    assert V.shape == (k, 3)
    assert np.array_equal(check_convex(V), V), "every vertex is on the hull"
    size = np.max(np.linalg.norm(V[:, None] - V[None], axis=-1))
    assert 0.06 - 1e-12 <= size <= 0.14 + 1e-12
    assert np.allclose(polytope_centroid(V), 0.0, atol=1e-12) and inradius(V) > 0
    assert len(stable_faces(V)) >= 1


def test_box_faces_are_ordered_by_normal_and_all_stable():
    f = hull_faces(box_vertices_3d((0.1, 0.08, 0.06)))
    assert np.allclose(f.normals, [[-1, 0, 0], [0, -1, 0], [0, 0, -1], [0, 0, 1], [0, 1, 0], [1, 0, 0]])
    assert np.allclose(f.offsets, [0.05, 0.04, 0.03, 0.03, 0.04, 0.05])
    assert [len(v) for v in f.vertices] == [4] * 6
    assert list(stable_faces(box_vertices_3d((0.1, 0.08, 0.06)))) == list(range(6))


def test_object_from_file_and_bad_files(tmp_path):
    V = box_vertices_3d((0.1, 0.05, 0.04)) + [0.3, 0.2, 0.1]
    good = tmp_path / "v.txt"
    good.write_text("# a box\n" + "\n".join(" ".join(map(str, v)) for v in V) + "\n")
    run = record_sim(SimOptions(object_spec=str(good), pokes=0, **CLEAN))
    assert run.truth.vertices.shape == (8, 3) and run.prior["shape"] == "polytope"
    assert np.allclose(np.sort(np.ptp(run.truth.vertices, axis=0)), [0.04, 0.05, 0.1])
    js = tmp_path / "v.json"
    js.write_text(json.dumps({"vertices": V.tolist()}))
    assert record_sim(SimOptions(object_spec=str(js), pokes=0, **CLEAN)).truth.vertices.shape == (8, 3)
    dent = tmp_path / "dent.txt"
    dent.write_text("\n".join(" ".join(map(str, v)) for v in np.vstack([V, V.mean(axis=0)])))
    with pytest.raises(TacestError, match="not convex"):
        record_sim(SimOptions(object_spec=str(dent), pokes=0, dim=3))
    flat = tmp_path / "flat.txt"
    flat.write_text("0 0\n0.1 0\n0 0.1\n")
    with pytest.raises(TacestError, match="three numbers 'x y z'"):
        record_sim(SimOptions(object_spec=str(flat), pokes=0, dim=3))


@pytest.mark.parametrize("spec", ["sphere", "box:0.1,0.1", "box:0.1,-0.1,0.1", "polytope:3", "polytope:x",
                                  "box:1,2,3"])
def test_bad_object_specs(spec):
    with pytest.raises(TacestError):
        record_sim(SimOptions(dim=3, object_spec=spec, pokes=1))


# ---------------------------------------------------------------------------------
# recordings and run files


def test_random_recording_is_spec_shaped_and_round_trips(tmp_path, random_run):
    run = random_run
    T, F = run.n_samples, 2
    assert run.dim == 3 and np.allclose(run.gravity, [0, 0, -G]) and np.allclose(run.up, [0, 0, 1])
    assert run.finger_position.shape == (T, F, 3) and run.force.shape == (T, F, 3)
    assert run.normal.shape == (T, F, 3) and run.contact.shape == (T, F)
    assert run.truth.pose.shape == (T, 7) and run.pose_obs.shape == (T, 7)
    assert np.allclose(np.linalg.norm(run.truth.pose[:, 3:], axis=1), 1.0, atol=UNIT_TOL), "unit quaternions"
    on = run.contact == 1
    assert on.sum() > 30 and np.allclose(np.linalg.norm(run.normal[on], axis=-1), 1.0, atol=UNIT_TOL)
    # the object moved and turned, and nothing sank or passed through more than 1 mm
    assert np.linalg.norm(run.truth.pose[-1, :2] - run.truth.pose[0, :2]) > 0.005
    assert np.min(_lowest_z(run)) > -PENETRATION_TOL
    seg = run.actions.segments
    assert seg[0, 0] == 0 and np.all(seg[1:, 0] == seg[:-1, 1]) and seg[-1, 1] == T
    assert run.actions.names == list(POKE3_NAMES) and run.actions.params.shape == (3, 8)
    el = run.actions.params[:, 2]
    assert np.all((el >= math.radians(10) - 1e-12) & (el <= math.radians(65) + 1e-12))
    path = tmp_path / "r.h5"
    write_run(run, path)
    back = read_run(path)
    assert back.dim == 3 and np.array_equal(back.truth.pose, run.truth.pose)
    assert np.array_equal(back.truth.inertia, run.truth.inertia) and back.truth.inertia.shape == (3, 3)
    assert np.array_equal(back.force, run.force) and np.array_equal(back.contact, run.contact)
    assert back.prior["shape"] == "polytope" and back.actions.names == list(POKE3_NAMES)
    assert json.loads(json.dumps(back.truth.effects)) == [{"name": "none"}]


def test_finger_forces_lie_in_the_friction_cone_and_every_poke_touches():
    run = record_sim(SimOptions(object_spec="polytope", seed=4, pokes=2, fingers=2, **CLEAN))
    on = run.contact == 1
    f, n = run.force[on], run.normal[on]
    loaded = np.linalg.norm(f, axis=1) > 0.1  # N; a touching sample may carry almost no force
    fn = -np.sum(f * n, axis=1)  # pressing: the force on the object points into it
    ft = np.linalg.norm(f + fn[:, None] * n, axis=1)
    assert loaded.sum() > 30 and np.all(fn[loaded] > 0)
    # Coulomb: |f_t| <= mu_finger·f_n; 1e-5 relative: the elliptic cone holds per substep
    # and the interval mean of forces inside a cone stays inside it (up to the spread of
    # the averaged normal, ~1e-6 rad on a face)
    assert np.all(ft[loaded] <= run.truth.friction_finger * fn[loaded] * (1 + 1e-5))
    assert all(run.contact[a:b].any() for a, b in run.actions.segments), "every poke touches the object"


def test_finger_never_passes_through_the_object(random_run):
    from tacest.geometry.polytope import PolytopeSurface

    run = random_run
    surf = PolytopeSurface(run.truth.vertices)
    faces = hull_faces(run.truth.vertices)
    q = run.truth.pose
    R = quat_to_matrix(q[:, 3:])
    for f in range(run.n_fingers):
        p_body = np.einsum("tji,tj->ti", R, run.finger_position[:, f] - q[:, :3])  # R^T (p - x)
        inside = np.all(p_body @ faces.normals.T <= faces.offsets, axis=1)
        gap = np.where(inside, -1.0, surf.distance(p_body)) - run.finger_radius[f]
        assert np.min(gap) > -PENETRATION_TOL, "finger sphere overlaps the object by more than 1 mm"
        assert np.all(gap[run.contact[:, f] == 1] < 1e-3), "contact only where the finger touches"


def test_same_seed_same_run():
    a = record_sim(SimOptions(dim=3, seed=7, pokes=1))
    b = record_sim(SimOptions(dim=3, seed=7, pokes=1))
    assert np.array_equal(a.truth.pose, b.truth.pose) and np.array_equal(a.force, b.force)


# ---------------------------------------------------------------------------------
# effects


def _free_flight(effects, velocity, obj=None):
    obj = obj or _box()
    effs = fx.resolve_effects(effects, 0, effect_context(obj))
    st = WorldState3(obj, np.array([0, 0, 6.0, 1, 0, 0, 0]), np.asarray(velocity, float), np.array([[3.0, 3, 3]]),
                     np.array([0.01]), effs)
    return simulate_pokes(st, [], SimOptions(**CLEAN))


def test_linear_drag_and_angular_damping_decay_exponentially():
    # 1e-3 relative: MuJoCo's implicit damping over 0.5 ms steps, (1 + b·h/m)^-n vs
    # exp(-b·t/m), plus the central difference of the poses
    run = _free_flight(["linear_drag:b=1.0"], [0.5, 0, 0, 0, 0, 0])
    t = run.time - run.time[0]
    vx = np.gradient(run.truth.pose[:, 0], run.dt)
    assert np.allclose(vx[1:-1], 0.5 * np.exp(-1.0 * t[1:-1] / 0.5), rtol=1e-3)
    obj = _box()
    run = _free_flight(["angular_damping:c=0.001"], [0, 0, 0, 0, 0, 10.0], obj)
    q = run.truth.pose[:, 3:]
    spin = np.gradient(np.unwrap(2 * np.arctan2(q[:, 3], q[:, 0])), run.dt)
    assert np.allclose(spin[1:-1], 10.0 * np.exp(-0.001 * t[1:-1] / obj.inertia[2, 2]), rtol=1e-3)
    plain = _free_flight([], [0.5, 0, 0, 0, 0, 10.0])
    assert np.allclose(np.gradient(plain.truth.pose[:, 0], run.dt)[1:-1], 0.5, rtol=1e-6), "no drag without it"


def test_restitution_bounces_and_plastic_contact_does_not():
    heights = {}
    for e in (None, 0.8):
        obj = _box()
        st = _state(obj, (0.5, 0.5, 0.3), [f"restitution:e={e}"] if e else [])
        st.pose[2] += 0.05  # dropped from 5 cm
        run = simulate_pokes(st, [], SimOptions(**CLEAN))
        low = _lowest_z(run)
        k = int(np.argmax(low < 1e-3))  # first impact
        heights[e] = float(low[k + 2:].max())
    assert heights[None] < 1e-3, "a plastic box stays down"
    # e = 0.8 from 5 cm: an ideal bounce rises e²·5 cm = 32 mm; MuJoCo's spring-damper
    # contact with dampratio -ln e/sqrt(π² + ln² e) gives about that (±15 %)
    assert heights[0.8] == pytest.approx(0.032, rel=0.15)


def test_soft_contact_sinks_by_load_over_stiffness():
    k = 5000.0
    obj = _box(mass=0.5)
    run = simulate_pokes(_state(obj, (0.0, 0.0, 0.12), [f"soft_contact:stiffness={k}"]), [_poke(depth=0.015)],
                         SimOptions(**CLEAN))
    low = _lowest_z(run)
    on = run.contact[:, 0] == 1
    first = int(np.argmax(on))
    # at rest, before the finger arrives: sunk by the weight, m·g/k = 0.98 mm (tolerance:
    # the rigid contact's own sinkage, REST_SINK_TOL)
    assert low[first - 1] == pytest.approx(-obj.mass * G / k, abs=REST_SINK_TOL)
    # pressed: deeper by (m·g + push)/k, the push from the force stream, on the
    # quasi-static samples (second half of the contact, the drive at its limit)
    pressed = np.flatnonzero(on)[on.sum() // 2:]
    pressed = pressed[-run.force[pressed, 0, 2] > 0.99 * MAX_FINGER_FORCE]
    assert len(pressed) > 10
    load = obj.mass * G - run.force[pressed, 0, 2]
    assert np.all(low[pressed] < 5 * low[first - 1])
    # 1e-4 m (the 2-D test's slop): the box's own contact sinkage into the plate under
    # 35 N (~2e-5 m) plus the spring's remaining transient (plate and object ring at
    # ~10 Hz, damped), against a sinkage of 7 mm
    assert np.allclose(low[pressed], -load / k, rtol=0, atol=1e-4)


def test_face_friction_is_the_friction_of_the_face_on_the_ground():
    obj = _box(mass=0.5, mu_g=0.3)
    values = [0.3, 0.3, 0.6, 0.3, 0.3, 0.3]  # the bottom face (normal -z) is face 2
    run = simulate_pokes(_state(obj, (-0.2, 0.0, 0.1), ["face_friction:values=" + ";".join(map(str, values))]),
                         [_poke(az=math.pi, el=0.0, depth=0.03)], SimOptions(**CLEAN))
    f = run.force[run.contact[:, 0] == 1, 0]
    mid = f[len(f) // 4: 3 * len(f) // 4]
    assert np.allclose(mid[:, 0] / (0.6 * (0.5 * G - mid[:, 2])), 1.0, rtol=FRICTION_RTOL)
    with pytest.raises(TacestError, match="6 faces"):
        fx.resolve_effects(["face_friction:values=0.1;0.2"], 0, effect_context(obj))


def test_sensor_effects_change_only_the_streams():
    base = dict(dim=3, seed=3, pokes=1, **{k: v for k, v in CLEAN.items() if k != "dim"})
    clean = record_sim(SimOptions(**base))
    bias = record_sim(SimOptions(**base, effects=["force_bias:fx=0.1,fy=-0.2,fz=0.3"]))
    assert np.array_equal(bias.truth.pose, clean.truth.pose), "sensor effects leave the physics alone"
    assert np.allclose(bias.force - clean.force, [0.1, -0.2, 0.3], atol=1e-12), "offset on every sample"
    lat = record_sim(SimOptions(**base, effects=["latency:samples=3"]))
    assert np.array_equal(lat.contact[3:], clean.contact[:-3]) and not lat.contact[:3].any()
    assert np.array_equal(lat.force[3:], clean.force[:-3])
    scale = record_sim(SimOptions(**base, effects=["force_scale:gain=1.3"]))
    assert np.allclose(scale.force, 1.3 * clean.force, atol=1e-12)
    ts = record_sim(SimOptions(**base, effects=["time_scale:scale=1.04"]))
    assert ts.dt == pytest.approx(1.04 * clean.dt) and np.allclose(ts.time, 1.04 * clean.time)
    with pytest.raises(TacestError, match="not used in 2-D"):
        record_sim(SimOptions(pokes=0, effects=["force_bias:fz=0.1"]))


def test_com_offset_moves_the_truth_vertices_and_keeps_the_inertia():
    base = dict(dim=3, seed=2, pokes=0, object_spec="box:0.1,0.08,0.06")
    plain = record_sim(SimOptions(**base))
    off = record_sim(SimOptions(**base, effects=["com_offset:dx=0.01,dy=-0.005,dz=0.004"]))
    assert np.allclose(off.truth.vertices, plain.truth.vertices - [0.01, -0.005, 0.004], atol=1e-12)
    assert np.allclose(off.truth.inertia, plain.truth.inertia)
    assert np.all(np.abs(_lowest_z(off)) < REST_SINK_TOL), "still rests on its face"
    eff = off.truth.effects[0] if isinstance(off.truth.effects, list) else off.truth.effects
    assert eff["name"] == "com_offset" and eff["dz"] == 0.004


# ---------------------------------------------------------------------------------
# plans, continuation, CLI


def _plan(path, params, names=POKE3_NAMES):
    write_plan(Plan(chosen=np.asarray(params, float), candidates=np.zeros((0, len(names))), scores=np.zeros(0),
                    method="random", score="logdet", names=list(names)), path)


def test_plan_is_executed_and_appends_to_a_run(tmp_path):
    plan = tmp_path / "plan.h5"
    _plan(plan, _poke(az=0.3, el=0.5, target=(0.0, 0.0, 0.02)))
    run = record_sim(SimOptions(dim=3, seed=4), plan_path=plan)
    assert len(run.actions.segments) == 1 and np.allclose(run.actions.params[0], _poke(az=0.3, el=0.5,
                                                                                       target=(0, 0, 0.02)))
    assert run.contact.any()
    path = tmp_path / "run.h5"
    write_run(run, path)
    more = record_sim(SimOptions(dim=3, seed=4), plan_path=plan, append_to=path)
    assert more.n_samples > run.n_samples and np.array_equal(more.truth.pose[:run.n_samples], run.truth.pose)
    assert more.actions.segments[1, 0] == more.actions.segments[0, 1]
    # the continuation starts where the old run ended: no jump in the truth
    assert np.max(np.abs(np.diff(more.truth.pose[:, :3], axis=0))) < 0.01
    st = state_from_run(read_run(path))
    assert np.allclose(st.pose, run.truth.pose[-1]) and np.allclose(st.velocity, 0.0, atol=1e-2)
    bad = tmp_path / "bad.h5"
    _plan(bad, [0, 1.0, 0.0, 0.0, 0.01, 0.03], names=("finger", "approach_angle", "target_x", "target_y",
                                                      "depth", "speed"))
    with pytest.raises(TacestError, match="approach_azimuth"):
        record_sim(SimOptions(dim=3), plan_path=bad)
    below = tmp_path / "below.h5"
    _plan(below, _poke(el=-0.3))
    with pytest.raises(TacestError, match="approach_elevation"):
        record_sim(SimOptions(dim=3), plan_path=below)


def test_cli_records_3d_and_rejects_bad_options(tmp_path, capsys):
    from tacest.cli.main import main

    out = tmp_path / "r.h5"
    with pytest.raises(SystemExit) as ex:
        main(["record", "--source", "sim", "--dim", "3", "--object", "box:0.1,0.08,0.06", "--pokes", "1",
              "--fingers", "3", "--effect", "force_bias", "--no-truth", "--observe-pose", "0.001", "-o", str(out)])
    assert ex.value.code == 0
    assert "poke 1/1" in capsys.readouterr().err
    run = read_run(out)
    assert run.dim == 3 and run.truth is None and run.finger_position.shape[1:] == (3, 3) and run.has_pose_obs
    for args, msg in [(["--object", "box:0.1,0.1"], "three extents"), (["--fingers", "4"], "--fingers"),
                      (["--effect", "bogus"], "unknown effect"), (["--object", "polytope:2"], "K must be in")]:
        bad = tmp_path / "x.h5"
        with pytest.raises(SystemExit) as ex:
            main(["record", "--source", "sim", "--dim", "3", "--pokes", "1", *args, "-o", str(bad)])
        err = capsys.readouterr().err.strip().splitlines()
        assert ex.value.code == 2 and len(err) == 1 and err[0].startswith("tacest: error: ") and msg in err[0], err
        assert not bad.exists()


# ---------------------------------------------------------------------------------
# tosses


def test_toss_flies_ballistically_lands_and_comes_to_rest_before_the_poke():
    """``record --dim 3 --toss``: sample 0 is the release, TOSS_DROP above the ground and
    moving as the TOSS_* ranges say; the COM flies a parabola under g until the first
    touch of the ground; the object is at rest before the first poke starts."""
    from tacest.sim.record import TOSS_DROP, TOSS_LIFT, TOSS_SPEED

    run = record_sim(SimOptions(seed=3, pokes=1, toss=True, observe_pose=5e-4, **CLEAN))
    low = _lowest_z(run)
    assert TOSS_DROP[0] - 1e-9 <= low[0] <= TOSS_DROP[1] + 1e-9
    land = int(np.argmax(low < 1e-3))
    assert land > 5, "the object flies for a while"
    P, dt = run.truth.pose, run.dt
    v0 = (P[1, :3] - P[0, :3]) / dt
    assert TOSS_SPEED[0] - 0.05 <= math.hypot(v0[0], v0[1]) <= TOSS_SPEED[1] + 0.05
    assert TOSS_LIFT[0] - 0.05 <= v0[2] + 0.5 * G * dt <= TOSS_LIFT[1] + 0.05
    # a parabola of g before the landing: the second differences of the COM height are
    # -g to rounding (measured 5e-12 m/s²: constant acceleration makes MuJoCo's
    # semi-implicit Euler exact at the samples); 1e-6 m/s² leaves room for rounding only
    acc = np.diff(P[: land - 1, 2], 2) / dt ** 2
    assert np.allclose(acc, -G, rtol=0, atol=1e-6)
    assert np.allclose(np.diff(P[: land - 1, :2], 2, axis=0), 0.0, atol=1e-9), "no horizontal force in flight"
    start = int(run.actions.segments[0, 0])
    assert start > land
    speed = np.linalg.norm(P[start, :3] - P[start - 1, :3]) / dt
    assert speed < 5e-3, "at rest when the poke starts"
    assert not run.contact[: start + 1].any(), "the parked finger never touches the flying object"
    # the pose is observed from sample 0 on, so the estimator starts the run free
    from tacest.estimation.data import starts_at_rest
    assert run.pose_obs is not None and not starts_at_rest(run)


def test_toss_cannot_continue_a_run(tmp_path):
    path = tmp_path / "a.h5"
    write_run(record_sim(SimOptions(seed=1, pokes=1, **CLEAN)), path)
    with pytest.raises(TacestError, match="--toss starts a new recording"):
        record_sim(SimOptions(seed=1, pokes=1, toss=True, **CLEAN), append_to=path)


# ---------------------------------------------------------------------------------
# several fingers in one action


def test_one_poke_has_the_same_path_alone_and_as_a_one_finger_action():
    """poke_path of a Poke3 and of the list [it]: the same waypoints (the recordings of
    single pokes do not change with the action format)."""
    from tacest.sim3d.pokes import Poke3, poke_path

    pk = Poke3.from_vector(_poke(finger=1, az=0.4, el=0.3), 2)
    p0 = np.array([[0.2, 0.0, 0.1], [-0.2, 0.1, 0.12]])
    one, start, end = poke_path(pk, p0, 0.05, 0.06, np.array([0.01, 0.01]))
    lst, starts, ends = poke_path([pk], p0, [0.05], 0.06, np.array([0.01, 0.01]))
    assert np.array_equal(one.times, lst.times) and np.array_equal(one.p_ctl__world, lst.p_ctl__world)
    assert np.array_equal(starts[0], start) and np.array_equal(ends[0], end)


def test_two_fingers_of_one_action_approach_together_and_squeeze_the_box(tmp_path):
    """An action of two fingers (tacest.sim3d.pokes.action_names(2)) from opposite sides
    at the same speed.  In the path (one finger going 1 cm deeper) both approaches start
    at the same instant and each reaches its end after its own distance / speed.  In the
    world both fingers touch the box in the same samples and it moves less than a fifth
    of what one finger's push moves it (over 1 cm): the squeeze's horizontal impulses
    cancel.  The run file holds one row per finger sharing one segment, and a planned
    action of two fingers is executed with both touching;
    an action that moves a finger twice is one clear error."""
    from tacest.sim3d.pokes import Poke3, action_names, poke_path, pokes_from_vector

    left = _poke(finger=0, az=math.pi, el=0.3, target=(0.0, 0.0, 0.03), depth=0.02, speed=0.05)
    right = _poke(finger=1, az=0.0, el=0.3, target=(0.0, 0.0, 0.03), depth=0.02, speed=0.05)
    deeper = _poke(finger=0, az=math.pi, el=0.3, target=(0.0, 0.0, 0.03), depth=0.03, speed=0.05)
    pokes = pokes_from_vector(np.array(deeper + right), 2)
    assert [p.finger for p in pokes] == [0, 1]
    p0 = np.array([[-0.2, 0.0, 0.1], [0.2, 0.0, 0.1]])
    path, starts, ends = poke_path(pokes, p0, [0.05, 0.05], 0.06, np.array([0.01, 0.01]))
    moving = np.linalg.norm(np.diff(path.p_ctl__world, axis=0), axis=2) > 0  # (N-1, F) which finger moves per leg
    legs = np.flatnonzero(moving.all(axis=1))  # legs where both move: the approach (two pieces) and the retreat
    t_go = path.times[legs[0]]
    for f, (a, e) in enumerate(zip(starts, ends)):
        dur = float(np.linalg.norm(e - a)) / 0.05
        assert np.allclose(path.at(np.array([t_go + dur]))[0, f], e, atol=1e-9)
        assert np.allclose(path.at(np.array([t_go]))[0, f], a, atol=1e-9)
    obj = _box(mass=0.3, mu_g=0.5, mu_f=0.8)
    opts = SimOptions(fingers=2, **CLEAN)
    st = state_at_rest(obj, fingers=2)
    squeeze = simulate_pokes(st, np.array([left + right]), opts, names=action_names(2))
    push = simulate_pokes(state_at_rest(obj, fingers=2), np.array([right]), opts)
    both = squeeze.contact.astype(bool).all(axis=1)
    assert both.sum() >= 10, "both fingers touch the box together"
    moved = lambda run: float(np.linalg.norm(run.truth.pose[-1, :2] - run.truth.pose[0, :2]))  # noqa: E731
    assert moved(push) > 0.01 and moved(squeeze) < 0.2 * moved(push)
    assert squeeze.actions.params.shape == (2, 8) and np.array_equal(squeeze.actions.segments[0],
                                                                      squeeze.actions.segments[1])
    assert isinstance(pokes[0], Poke3)
    with pytest.raises(TacestError, match="twice"):
        pokes_from_vector(np.array(left + left), 2)
    plan = tmp_path / "two.h5"
    _plan(plan, left + right, names=action_names(2))
    run = record_sim(SimOptions(dim=3, seed=4, fingers=2), plan_path=plan)
    assert run.actions.params.shape == (2, 8) and set(run.actions.params[:, 0]) == {0.0, 1.0}
    assert run.contact.astype(bool).any(axis=0).all(), "each finger of the planned action touches"


def test_random_actions_of_several_fingers(tmp_path):
    """``record --dim 3 --fingers-per-action 2``: every random action moves two distinct
    fingers (two rows of /actions/params sharing a segment) and both touch in most
    actions; the recorder's message counts actions and finger pokes; in 2-D, or with more
    fingers per action than fingers, one line and exit 2."""
    run = record_sim(SimOptions(dim=3, fingers=3, fingers_per_action=2, pokes=3, seed=11, force_stream=False))
    seg, fingers = run.actions.segments, run.actions.params[:, 0]
    assert len(seg) == 6 and all(np.array_equal(seg[2 * i], seg[2 * i + 1]) for i in range(3))
    assert all(fingers[2 * i] != fingers[2 * i + 1] for i in range(3))
    both = [run.contact[a:b][:, [int(fingers[2 * i]), int(fingers[2 * i + 1])]].any(axis=0).all()
            for i, (a, b) in enumerate(seg[::2])]
    assert sum(both) >= 2, both
    import subprocess
    import sys

    out = tmp_path / "sq.h5"
    res = subprocess.run([sys.executable, "-m", "tacest", "record", "--dim", "3", "--fingers", "2",
                          "--fingers-per-action", "2", "--pokes", "1", "--no-force", "-o", str(out)],
                         capture_output=True, text=True)
    assert res.returncode == 0 and "1 action(s) (2 finger pokes)" in res.stderr, res.stderr
    for args in (["--fingers", "2", "--fingers-per-action", "2"], ["--dim", "3", "--fingers-per-action", "2"]):
        res = subprocess.run([sys.executable, "-m", "tacest", "record", *args, "-o", str(tmp_path / "bad.h5")],
                             capture_output=True, text=True)
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
