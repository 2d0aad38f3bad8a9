"""Effects: the registry and its parsing, and that each effect changes a recording the
way it physically should (known answers where there is one)."""

import json
import math

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.io.run import read_run, write_run
from tacest.sim import effects as fx
from tacest.geometry.polygon import box_vertices, polygon_centroid, polygon_inertia
from tacest.geometry.transforms import rot2
from tacest.sim.objects import SimObject
from tacest.sim.record import SimOptions, WorldState, record_sim, simulate_pokes
from tacest.sim.world import MAX_FINGER_FORCE

G = 9.81
CLEAN = dict(noise_force=0.0, noise_position=0.0, noise_normal=0.0)
SPEC_NAMES = ["none", "restitution", "angular_damping", "linear_drag", "soft_contact", "force_bias",
              "force_scale", "latency", "face_friction", "com_offset", "time_scale"]
#: pymunk's contact slop: a resting contact may overlap by up to ~1e-4 m
SLOP = 1e-4


def _box(mass=0.5, w=0.1, h=0.06, mu_g=0.3, mu_f=0.4):
    v = box_vertices(w, h)
    return SimObject(v, mass, polygon_inertia(v, mass), mu_g, mu_f, "box")


def _state(obj, effects, pose=None, velocity=(0, 0, 0), finger=(0.5, 0.3)):
    pose = np.array([0.0, np.max(obj.vertices[:, 1]), 0.0]) if pose is None else np.asarray(pose, float)
    ctx = fx.EffectContext(mass=obj.mass, inertia=obj.inertia, n_faces=obj.n_faces,
                           friction_ground=obj.friction_ground)
    return WorldState(obj, pose, np.asarray(velocity, float), np.array([finger], float), np.array([0.01]),
                      effects=fx.resolve_effects(effects, 0, ctx))


def _lowest_y(run):
    """(T,) m, height of the object's lowest vertex over time (from /truth)."""
    v, q = run.truth.vertices, run.truth.pose
    return np.array([np.min((v @ rot2(a).T)[:, 1]) + y for (_, y, a) in q])


# ---------------------------------------------------------------------------------
# registry and parsing


def test_registry_has_every_spec_name_with_documented_parameters():
    assert list(fx.EFFECT_NAMES) == SPEC_NAMES
    for spec in fx.EFFECTS.values():
        assert spec.doc and spec.where
        for p in spec.params:
            assert p.unit and p.doc and p.typical and p.bounds[0] < p.bounds[1]


@pytest.mark.parametrize("text,msg", [
    ("bogus", "unknown effect 'bogus'; valid effects: none, restitution"),
    ("latency:foo=1", "has no parameter 'foo'; valid: samples"),
    ("latency:samples=1.5", "not an integer"),
    ("force_bias:fx=abc", "not a number"),
    ("restitution:e=2", "outside"),
    ("latency:samples", "expected key=value"),
    ("latency:samples=1,samples=2", "given twice"),
    ("face_friction:values=0.3;0.4", "the object has 4 faces"),
    ("none:x=1", "has no parameter 'x'"),
])
def test_effect_parsing_errors(text, msg):
    with pytest.raises(TacestError, match=msg.replace("(", r"\(")):
        fx.resolve_effects([text], 0, fx.EffectContext(n_faces=4))


def test_duplicate_effect_is_an_error_and_none_is_nothing():
    with pytest.raises(TacestError, match="more than once"):
        fx.resolve_effects(["latency", "latency:samples=2"], 0, fx.EffectContext())
    assert fx.resolve_effects(["none"], 0, fx.EffectContext()) == []


def test_explicit_and_random_parameters():
    ctx = fx.EffectContext(mass=0.4, inertia=5e-4, inradius=0.03, n_faces=5, friction_ground=0.5)
    a = fx.resolve_effects(SPEC_NAMES, 3, ctx)
    b = fx.resolve_effects(SPEC_NAMES, 3, ctx)
    c = fx.resolve_effects(SPEC_NAMES, 4, ctx)
    assert a == b and a != c, "seeded"
    assert [e.name for e in a] == SPEC_NAMES[1:]
    for e in a:
        for p in e.spec.params:
            vals = e[p.name] if isinstance(e[p.name], list) else [e[p.name]]
            assert all(p.bounds[0] <= v <= p.bounds[1] for v in vals), (e.name, p.name)
    by = {e.name: e for e in a}
    assert fx.RESTITUTION_DRAW[0] <= by["restitution"]["e"] <= fx.RESTITUTION_DRAW[1]
    assert 1 <= by["latency"]["samples"] <= 25 and isinstance(by["latency"]["samples"], int)
    assert 0.15 <= abs(by["force_scale"]["gain"] - 1) <= 0.35
    assert 0.02 <= abs(by["time_scale"]["scale"] - 1) <= 0.15
    assert len(by["face_friction"]["values"]) == 5
    assert math.hypot(by["com_offset"]["dx"], by["com_offset"]["dy"]) < 0.03  # inside the inradius
    given = fx.resolve_effects(["force_bias:fx=0.25", "face_friction:values=0.1;0.2;0.3;0.4;0.5"], 3, ctx)
    assert given[0]["fx"] == 0.25 and 0.1 <= abs(given[0]["fy"]) <= 0.4  # fy drawn
    assert given[1]["values"] == [0.1, 0.2, 0.3, 0.4, 0.5]


def test_truth_json_forms_and_run_file_round_trip(tmp_path):
    assert json.loads(fx.effects_to_json([])) == {"name": "none"}
    one = [fx.Effect("latency", {"samples": 2})]
    assert json.loads(fx.effects_to_json(one)) == {"name": "latency", "samples": 2}
    two = one + [fx.Effect("force_bias", {"fx": 0.1, "fy": -0.2})]
    assert json.loads(fx.effects_to_json(two)) == [{"name": "latency", "samples": 2},
                                                   {"name": "force_bias", "fx": 0.1, "fy": -0.2}]
    for effects in ([], one, two):
        assert fx.effects_from_json(fx.effects_to_json(effects)) == effects
    run = record_sim(SimOptions(seed=1, pokes=1, effects=["latency:samples=2", "force_bias:fx=0.1,fy=-0.2"]))
    write_run(run, tmp_path / "r.h5")
    back = read_run(tmp_path / "r.h5")
    assert fx.effects_from_json(back.truth.effects) == two
    with pytest.raises(TacestError, match="parameter 'samples' is missing"):
        fx.effects_from_json({"name": "latency"})


# ---------------------------------------------------------------------------------
# sensor and clock effects: compared with the same seed without the effect


def _pair(effect, seed=7, pokes=2):
    base = record_sim(SimOptions(seed=seed, pokes=pokes, **CLEAN))
    eff = record_sim(SimOptions(seed=seed, pokes=pokes, effects=[effect], **CLEAN))
    assert np.array_equal(base.truth.pose, eff.truth.pose), "a sensor effect leaves the physics alone"
    return base, eff


def test_latency_delays_tactile_streams_by_whole_samples():
    base, eff = _pair("latency:samples=3")
    k = 3
    assert np.array_equal(eff.force[k:], base.force[:-k])
    assert np.array_equal(eff.contact[k:], base.contact[:-k])
    assert np.array_equal(eff.normal[k:], base.normal[:-k], equal_nan=True)
    assert np.all(eff.contact[:k] == 0) and np.all(eff.force[:k] == 0)
    assert np.array_equal(eff.finger_position, base.finger_position), "positions are not delayed"


def test_force_bias_offsets_every_sample():
    base, eff = _pair("force_bias:fx=0.2,fy=-0.1")
    off = base.contact == 0
    assert np.all(eff.force[off] == np.array([0.2, -0.1])), "off contact the sensor reads its offset"
    # on contact: true force + offset; 1e-12 N is float rounding of a sum of ~1 N terms
    assert np.allclose(eff.force - base.force, [0.2, -0.1], rtol=0, atol=1e-12)


def test_force_scale_scales_the_force():
    base, eff = _pair("force_scale:gain=1.25")
    assert np.allclose(eff.force, 1.25 * base.force, rtol=1e-12, atol=0)
    assert np.abs(base.force).max() > 1.0


def test_time_scale_scales_the_written_clock():
    base, eff = _pair("time_scale:scale=1.03")
    assert eff.dt == pytest.approx(1.03 * base.dt, rel=1e-12)
    assert np.allclose(eff.time, 1.03 * base.time, rtol=1e-12)
    assert np.array_equal(eff.finger_position, base.finger_position)
    assert np.array_equal(eff.force, base.force)
    eff.validate()


# ---------------------------------------------------------------------------------
# physical effects: known answers on hand-built cases


def test_restitution_makes_the_object_bounce():
    # a box dropped from 3 cm: plastic landing without, a bounce with restitution
    obj = _box()
    pose0 = [0.0, 0.03 + 0.03, 0.0]
    plain = simulate_pokes(_state(obj, [], pose=pose0), [], SimOptions(**CLEAN))
    bouncy = simulate_pokes(_state(obj, ["restitution:e=0.8"], pose=pose0), [], SimOptions(**CLEAN))
    for run, bounces in ((plain, False), (bouncy, True)):
        y = run.truth.pose[:, 1]
        first_impact = int(np.argmax(np.diff(y) >= 0))  # y stops falling
        rise = np.max(y[first_impact:]) - y[first_impact]
        if bounces:
            # e² · 3 cm ≈ 1.9 cm ideally; more than 5 mm is a clear bounce
            assert rise > 5e-3
        else:
            assert rise < SLOP
    assert np.any(bouncy.truth.pose[:, 1] > 0.03 + 5e-3)


def _flight_rate(run, col, k):
    # central difference of the truth pose at sample k (s⁻¹ units of the column)
    return (run.truth.pose[k + 1, col] - run.truth.pose[k - 1, col]) / (2 * run.dt)


def test_linear_drag_slows_translation_exponentially():
    obj = _box(mass=0.5)
    b = 1.0  # N·s/m: time constant m/b = 0.5 s
    pose0, v0 = [0.0, 1.0, 0.0], [0.5, 0.0, 0.0]  # in flight for ~0.45 s
    plain = simulate_pokes(_state(obj, [], pose=pose0, velocity=v0), [], SimOptions(**CLEAN))
    drag = simulate_pokes(_state(obj, [f"linear_drag:b={b}"], pose=pose0, velocity=v0), [], SimOptions(**CLEAN))
    k = 20  # t = 0.2 s, still in the air
    assert _flight_rate(plain, 0, k) == pytest.approx(0.5, rel=1e-9)
    # vx = v0·exp(-b t / m); 2e-3 relative covers pymunk's explicit Euler at h = 0.5 ms
    # ((b/m)²·h·t/2 ~ 2e-4) and the central difference ((b/m)²·dt²/6 ~ 7e-5)
    assert _flight_rate(drag, 0, k) == pytest.approx(0.5 * math.exp(-b * 0.2 / 0.5), rel=2e-3)


def test_angular_damping_slows_spin_exponentially():
    obj = _box(mass=0.5)
    c = obj.inertia / 0.3  # time constant 0.3 s
    pose0, v0 = [0.0, 1.0, 0.0], [0.0, 0.0, 5.0]
    plain = simulate_pokes(_state(obj, [], pose=pose0, velocity=v0), [], SimOptions(**CLEAN))
    damped = simulate_pokes(_state(obj, [f"angular_damping:c={c}"], pose=pose0, velocity=v0), [],
                            SimOptions(**CLEAN))
    k = 20
    assert _flight_rate(plain, 2, k) == pytest.approx(5.0, rel=1e-9)
    # same error budget as for linear drag, with rate 1/0.3 s⁻¹
    assert _flight_rate(damped, 2, k) == pytest.approx(5.0 * math.exp(-0.2 / 0.3), rel=2e-3)


def test_soft_contact_sinks_with_load():
    k_s = 5000.0
    obj = _box(mass=0.5)
    run = simulate_pokes(_state(obj, [f"soft_contact:stiffness={k_s}"], finger=(0.0, 0.2)),
                         [[0, math.pi / 2, 0.0, 0.03, 0.015, 0.03]], SimOptions(**CLEAN))
    low = _lowest_y(run)
    on = run.contact[:, 0] == 1
    first = int(np.argmax(on))
    # at rest (just before the finger arrives): sunk by the weight, m·g/k = 0.98 mm;
    # tolerance: the contact slop (1e-4 m)
    assert low[first - 1] == pytest.approx(-obj.mass * G / k_s, abs=SLOP)
    # pressed by the finger: deeper, by (m·g + push)/k with the push from the force
    # stream, on the quasi-static samples of the press (the drive at its limit, the
    # spring transient over: the second half of the contact)
    pressed = np.flatnonzero(on)[on.sum() // 2:]
    pressed = pressed[-run.force[pressed, 0, 1] > 0.99 * MAX_FINGER_FORCE]
    assert len(pressed) > 10
    load = obj.mass * G - run.force[pressed, 0, 1]
    assert np.all(low[pressed] < 5 * low[first - 1])
    assert np.allclose(low[pressed], -load / k_s, rtol=0, atol=SLOP)
    # a rigid ground does not sink (only the slop)
    rigid = simulate_pokes(_state(obj, [], finger=(0.0, 0.2)), [[0, math.pi / 2, 0.0, 0.03, 0.015, 0.03]],
                           SimOptions(**CLEAN))
    assert _lowest_y(rigid).min() > -SLOP


def test_soft_ground_settles_as_a_spring_and_damper_under_the_weight():
    # a box set down on an unloaded soft ground (plate at y = 0 at rest) sinks as the
    # massless ground of the effect says, M s'' + c s' + k s = m g with M = m + the
    # plate's mass, which is kept a few percent of the object's (SOFT_PLATE_MASS): an
    # underdamped k, c (zeta 0.3) so that the overshoot and the period are both checked
    from tacest.sim.world import World

    k_s, c_s, m = 5000.0, 30.0, 0.5
    obj = _box(mass=m)
    state = _state(obj, [f"soft_contact:stiffness={k_s},damping={c_s}"], finger=(0.0, 0.2))
    run = simulate_pokes(state, [[0, math.pi / 2, 0.0, 0.03, 0.015, 0.03]], SimOptions(**CLEAN))
    free = int(np.argmax(run.contact[:, 0] == 1))  # samples before the finger arrives
    assert free > 30  # the transient (1/(zeta wn) = 0.07 s) is over by then
    plate = World(obj, state.pose, state.velocity, np.array([[0.0, 0.2]]), np.array([0.01]),
                  effects=state.effects).plate_mass
    assert plate <= 0.05 * m
    M = m + plate
    wn, zeta = math.sqrt(k_s / M), c_s / (2.0 * math.sqrt(k_s * M))
    wd = wn * math.sqrt(1.0 - zeta ** 2)
    t = run.time[:free] - run.time[0]
    sink = m * G / k_s * (1.0 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta ** 2)
                                                            * np.sin(wd * t)))
    assert sink.max() > 1.3 * m * G / k_s  # the premise: an overshoot of 35 %
    # tolerance: the contact slop (measured 0.034 mm; the sink is 0.98 mm, 1.33 at its peak)
    assert np.allclose(-_lowest_y(run)[:free], sink, rtol=0, atol=SLOP)


def test_face_friction_sets_the_sliding_friction_of_the_face_on_the_ground():
    obj = _box(mass=0.5, mu_g=0.3)
    push = [[0, math.pi, 0.0, 0.03, 0.03, 0.03]]  # from the left, sliding the box on face 0
    runs = {}
    for name, eff in (("plain", []), ("faces", ["face_friction:values=0.6;0.3;0.3;0.3"])):
        runs[name] = simulate_pokes(_state(obj, eff, finger=(-0.2, 0.2)), push, SimOptions(**CLEAN))
    for name, mu in (("plain", 0.3), ("faces", 0.6)):
        run = runs[name]
        f = run.force[run.contact[:, 0] == 1, 0]
        mid = f[len(f) // 4: 3 * len(f) // 4]
        # Coulomb sliding on the bottom face (face 0); 1e-3: solver convergence
        assert np.allclose(mid[:, 0], mu * (obj.mass * G - mid[:, 1]), rtol=1e-3), name
    # the finger contact keeps friction_finger: the box slides as far either way
    assert runs["faces"].truth.pose[-1, 0] == pytest.approx(runs["plain"].truth.pose[-1, 0], abs=2e-3)


def test_com_offset_moves_the_truth_vertices():
    opts = dict(object_spec="box:0.1,0.06", seed=3, pokes=2, **CLEAN)
    base = record_sim(SimOptions(**opts))
    off = record_sim(SimOptions(effects=["com_offset:dx=0.01,dy=0.005"], **opts))
    d = np.array([0.01, 0.005])
    assert np.allclose(off.truth.vertices, base.truth.vertices - d, atol=1e-12)
    assert np.allclose(polygon_centroid(off.truth.vertices), -d, atol=1e-12)
    assert off.truth.inertia == pytest.approx(base.truth.inertia)
    # random pokes aim at the centroid, which is no longer the COM
    for (s, _), p in zip(off.actions.segments, off.actions.params):
        q = off.truth.pose[s]
        assert np.allclose(p[2:4], q[:2] + rot2(q[2]) @ (-d), atol=1e-9)
    with pytest.raises(TacestError, match="outside the object"):
        record_sim(SimOptions(effects=["com_offset:dx=0.2,dy=0"], **opts))


def test_face_friction_under_the_object_is_never_negative():
    """The friction of the face below is friction_ground + d_i floored smoothly at 0
    (effects_contact._floored): an offset below -friction_ground gives ~0, not a
    negative friction that would push a sliding box along its slip; no offset gives the
    ground's friction exactly; a positive one adds to within eps²/(4 mu) (eps = 1e-3:
    below 1e-5 here)."""
    import casadi as ca

    from tacest.model.effects_contact import _floored

    def f(mu, d):
        return float(ca.DM(_floored(ca.DM(mu), ca.DM(d))))

    assert f(0.3, 0.0) == pytest.approx(0.3, abs=1e-15)
    assert abs(f(0.3, -1.4)) < 1e-5
    assert f(0.3, 0.2) == pytest.approx(0.5, abs=1e-5)
    assert f(0.3, -0.1) == pytest.approx(0.2, abs=1e-5)


def test_the_sink_under_the_weight_and_its_inverse():
    """Known answer: 0.5 kg on a 5000 N/m ground sinks 0.5 g / 5000 m (g the project's
    tacest.constants.STANDARD_GRAVITY), and the compliance that gives that sink is
    1/5000 m/N again (to rounding)."""
    from tacest.constants import STANDARD_GRAVITY
    from tacest.model.effects_contact import compliance_for_sink, weight_sink

    sink = weight_sink(1.0 / 5000.0, 0.5)
    assert sink == pytest.approx(0.5 * STANDARD_GRAVITY / 5000.0, rel=1e-12)
    assert compliance_for_sink(sink, 0.5) == pytest.approx(1.0 / 5000.0, rel=1e-12)
