"""Effects at the ground contact: restitution, soft_contact and face_friction (2-D and
3-D), edge_radius and ground_offset (3-D).

docs/diagnosis.md ("NLP augmentations") gives the equations and the measurements behind
each choice made here; docs/estimation3d.md those of the 3-D ones.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from tacest.dynamics.laws import smooth_pos
from tacest.dynamics.rigid2d import ground_contacts, point_velocity
from tacest.dynamics.rigid3d import cross
from tacest.geometry.shapes import rot2
from tacest.model.effect import Effect, EffectParameter

# ---------------------------------------------------------------------------------------
# restitution

#: m/s: restitution's impact gate a² / (a² + BOUNCE_SPEED²) on the approach speed a of
#: a vertex (0.5 at BOUNCE_SPEED, 0.9 at 3 × it): the share of Newton's rebound e·a a
#: vertex gets, and the weight of its impact law.  Slower approaches land plastically,
#: as resting contacts do in the simulators (which bounce only on new contacts).  A
#: bounce from below 0.1 m/s rises at most v²/2g = 0.5 mm, within a motion-capture pose
#: sigma, so no data tell it; without the gate a trajectory that jitters along the
#: ground (fitting pose noise) got that jitter free of the contact laws through e, and a
#: clean recording of sliding pushes fitted e = 0.93 (objective 465 -> 398)
BOUNCE_SPEED = 0.1
#: restitution: per-impact scatter of the coefficient of restitution; the impact law's
#: residual is whitened by process·g·dt + RESTITUTION_SCATTER × the approach speed (a
#: bounce at 1 m/s off by 0.5 in e costs 0.5·(0.5/0.1)² ≈ 12, not 0.5·(0.5/0.005)² ≈ 5000
#: with the process noise alone, which made every fit avoid touching the ground)
RESTITUTION_SCATTER = 0.1
#: m: smoothing width of restitution's would-be penetration max(a·dt - phi_prev, 0)
IMPACT_DEPTH_EPS = 1e-4
#: m/s: smoothing width of restitution's rebound speed max(e·A - g·dt, 0): 0.02 m/s at
#: e = 0 (negligible against the law's scatter), and a gradient in e there
REBOUND_SMOOTHING = 0.1
#: m: restitution counts an approach as an impact within the interval where it would
#: carry the vertex to within this of the ground: the first-order path (constant
#: velocity over the interval) misses the true one by a fraction of a mm either side on
#: a spinning box (an impact right at a sample had p = -0.3 mm), and one that ends 4 mm
#: above the ground (the sample before a landing) must not count
IMPACT_REACH = 1e-3
#: where a fit from the estimator's own start begins e (scaled): a bounce is a change of
#: contact mode, and from e = 0 a fit of a dropped box bouncing with e = 0.7 stayed
#: plastic (e 0.07, objective above the plain model's)
RESTITUTION_START = 0.5


def _gate(speed):
    """speed²/(speed² + BOUNCE_SPEED²): how much of an impact at this approach speed
    (m/s) counts as one (slower landings are plastic)."""
    return speed ** 2 / (speed ** 2 + BOUNCE_SPEED ** 2)


def _impact(normal_velocity, gap, dt):
    """An impact of a vertex within the next interval, from its normal velocity
    (m/s, along the ground normal: negative approaching) and its gap (m) at the
    interval's start: ``(a, weight, p)`` with a m/s the approach speed, p = a·dt - gap m
    how far the approach would carry it below the ground, and weight the impact gate
    :func:`_gate` (a) × whether it reached the ground within the interval (p >
    -IMPACT_REACH, to within the first-order path's error), smoothed."""
    a = smooth_pos(-normal_velocity, 1e-3)  # m/s, approach
    p = a * dt - gap
    reach = smooth_pos(p + IMPACT_REACH, IMPACT_DEPTH_EPS)
    return a, _gate(a) * reach / (reach + IMPACT_DEPTH_EPS), p


class Restitution(Effect):
    """Newton's impact law with the impact inside a sample interval: after an impact a
    vertex leaves with -e × its approach velocity.  2-D state: per vertex, the approach
    speed of an impact within the sample's interval (the impact memory, m/s).  3-D: no
    state; the stage looks back two more poses and computes the memory from them
    (:meth:`impacts_3d`)."""

    name = "restitution"
    dims = (2, 3)
    doc = "bouncy impacts: a vertex leaves the ground with e times its approach speed"
    #: the 3-D stage of (t-1, t] sees the poses t-4 .. t: the approach before an impact
    #: in (t-2, t-1] is the velocity of (t-3, t-2], and whether that interval was itself
    #: the one after an impact needs (t-4, t-3]
    history_3d = 2

    def parameters(self, K, dim):
        return (EffectParameter("e", 0.0, 0.5, 0.0, 0.95, start=RESTITUTION_START,
                                doc="coefficient of restitution"),)

    def state_rows(self, K, dim):
        return K if dim == 2 else 0

    def state_lower(self):
        return 0.0  # approach speeds (m/s)

    settled_output = "impact_target"

    def impacts_2d(self, ctx):
        """Newton's impact law with the impact inside an interval, for every vertex k.
        Relaxes the contact laws' gaps ``ctx.phi_c`` and normal velocities ``ctx.vn_c``
        (relative to a soft ground's plate), sets the levers at which the ground impulses
        act (``ctx.impulse_levers``), adds its residuals (whitened like the dynamics: the
        law of the interval after an impact, then the impact memory's definition) and
        the impact memory's values as its law sets them from the interval's motion
        (stage output ``impact_target``).

        A vertex approaching at a (its normal velocity at t-1, from its lever then)
        from the gap phi_prev would end the interval p = a·dt - phi_prev below the
        ground: where p > -IMPACT_REACH (it reached the ground within the interval, to
        within the first-order path's error) it hit the ground, and its approach a is
        kept in the impact memory A_k(t).  In the next interval it leaves with e·A_k(t),
        less what gravity takes in the interval since the impact on average (the law's
        residual, whitened by process·g·dt + RESTITUTION_SCATTER·A; without the gravity
        term a dropped box's e came out 0.16 for 0.3).  In both intervals the contact laws
        do not count the vertex's rise off the ground against the impulse that makes it:
        its gap and its upward normal velocity (what it has of them) are taken off what
        complementarity sees, so the ground may push a vertex that it sends up (the
        impact's impulse stops the approach and sends it off at e·a; the end-of-interval
        velocities of a first-order scheme mix the two).  This relief does not depend on
        e: at e = 0 the model is looser than the plain one at impacts (a box turning onto
        its next corner lifts the first one, and clean toss recordings fit e 0.09 with
        held-out gains of 45-81; the diagnosis does not blame e below
        diagnose.MATERIAL_SIZE for that reason).  Impacts are gated by
        a²/(a² + BOUNCE_SPEED²) (slower landings are plastic), and the interval after an
        impact by the same gate on A, which turns the impact detection off there (its
        mixed velocity is no approach).

        Why so: a law that asks for the rebound velocity in the interval of the impact
        itself (this model until the toss design) cannot follow an impact in mid-
        interval (at 1-3 m/s a 10 ms interval holds up to 3 cm of motion): even with the
        truth's e held the pose misfit was 100-200 units per landing.  Relaxing the
        contact laws by the rebound the law predicts (e·p, dt·e·A) asked the approach
        speed to within a gap sigma per interval (0.1 m/s), which the first-order
        estimate a misses by 0.2 m/s on a spinning box; switching them off at every
        impact let the candidate fit clean landings better than the plain model at e =
        0.001; switching them off by a share growing with e·a, or relieving the rise
        only up to twice the rebound's travel, drove e up (to its bound; +26-47 %).

        The impulses of an impact act at the vertex's lever at the impact, not at the end
        of the interval: in the impact's interval at the pose a fraction phi_prev/(a·dt)
        into it (the levers interpolated between the interval's ends), in the interval
        after it at the pose it ended the impact's interval with.  At the end pose a box
        spinning at 15 rad/s has turned 0.15 rad further, and the torque of a landing's
        impulse came out 69 % too large there (the same impulse at the impact's pose has
        exactly the spin change of the simulated landing)."""
        K = ctx.K
        dt, grav = ctx.dt, ctx.grav
        sig_v = ctx.sig_v
        e_r = ctx.u[self.name]["e"]
        phi_prev, _, levers_prev = ground_contacts(ctx.q_start, ctx.v_prev, ctx.V, ctx.n_g, ctx.h)
        if ctx.plate is not None:  # gaps relative to a soft ground's plate
            sink, rate = ctx.plate
            prev_sink = sink - dt * rate
            phi_prev = [p + prev_sink for p in phi_prev]
        A_prev, A_now = ctx.s_prev[self.name], ctx.s[self.name]
        r_after, r_memory, impulse_levers, targets = [], [], [], []
        phi_c, vn_c, levers = ctx.phi_c, ctx.vn_c, ctx.levers
        for k in range(K):
            # the interval after an impact: the vertex leaves with e × its approach
            after = _gate(A_prev[k])
            # its normal velocity over the interval (the first-order scheme's v(t) is the
            # interval's mean): e·A less what gravity took since the impact, one interval
            # on average (from an impact at a uniform time in the previous interval to
            # this one's middle; a rebound slower than that is back on the ground).
            # Smoothed over REBOUND_SMOOTHING: with a sharp max(·, 0) the law was flat in
            # e below that speed, and a fit starting at e = 0 stayed there (e 0.03 for a
            # dropped box bouncing with 0.6)
            leave = smooth_pos(e_r * A_prev[k] - grav * dt, REBOUND_SMOOTHING)
            r_after.append(after * (vn_c[k] - leave) / (sig_v + RESTITUTION_SCATTER * A_prev[k]))
            # an impact within this interval
            a, hit, p = _impact(ca.dot(ctx.n_g, point_velocity(ctx.v_prev, levers_prev[k])), phi_prev[k], dt)
            struck = (1 - after) * hit
            targets.append(struck * a)
            r_memory.append((A_now[k] - struck * a) / sig_v)
            # the contact laws: the rise the impact gives the vertex is not held against
            # the impulse that gives it
            freed = struck + after - struck * after
            phi_c[k] = phi_c[k] - freed * smooth_pos(phi_c[k], IMPACT_DEPTH_EPS)
            vn_c[k] = vn_c[k] - freed * smooth_pos(vn_c[k], 1e-3)
            # the levers of the impact's impulses: at the impact's pose
            above = smooth_pos(phi_prev[k], IMPACT_DEPTH_EPS)
            into = above / (above + smooth_pos(p, IMPACT_DEPTH_EPS) + IMPACT_DEPTH_EPS)  # impact time / dt
            at_impact = levers_prev[k] + into * (levers[k] - levers_prev[k])
            impulse_levers.append(levers[k] + struck * (at_impact - levers[k]) + after * (levers_prev[k] - levers[k]))
        ctx.impulse_levers = impulse_levers
        ctx.dynamics_rows[self.name] = r_after + r_memory
        ctx.outputs["impact_target"] = ca.vertcat(*targets)

    def start_2d(self, ctx):
        # no impact before sample 0: the impact memory starts empty
        ctx.rest_rows[self.name] = [ctx.s[self.name] / (ctx.g_sig_proc * ctx.grav * ctx.dt)]

    @staticmethod
    def _impact_3d(ctx, past, k):
        """:func:`_impact` of vertex k in the interval after the past pose ``past``
        (stage3d.PastPose), from the velocity it had there."""
        point_v = past.v + ca.mtimes(past.R, cross(past.w, past.levers[k]))
        return _impact(ca.dot(ctx.n_g, point_v), past.phi[k], ctx.dt)

    def impacts_3d(self, ctx):
        """The law of :meth:`impacts_2d` in 3-D, with the impact memory computed from the
        stage's earlier poses instead of held as a state.  ctx.past holds the poses t-1,
        t-2, t-3 with the velocities of the intervals ending there.  For vertex k:

        - A' = w(t-2)·a(t-2): an impact in (t-3, t-2] from the approach of (t-4, t-3];
        - A = (1 - gate(A'))·w(t-1)·a(t-1): an impact in (t-2, t-1] (not counted in the
          interval right after one, whose velocity mixes approach and rebound);
        - after = gate(A): this interval follows an impact; the vertex's normal velocity
          over it must be e·A less what gravity took (a dynamics row, whitened by the
          process sigma + RESTITUTION_SCATTER·A, as in 2-D);
        - struck = (1 - after)·w(t): an impact within this interval;
        - the gap the contact laws see loses what the rise has of it, by
          struck + after - struck·after (the ground may push a vertex that it sends up);
        - the ground impulse of the vertex acts on the body under the rotation at the
          impact: for an impact within the interval, interpolated between the poses t-1
          and t at the impact's fraction of the interval; after an impact, at t-1.

        The memory of 2-D is exact recursively; here A' has no guard of its own: where
        (t-4, t-3] held an impact, the mixed velocity of (t-3, t-2] may be taken for a
        second approach, and that A' may switch off A, the law row of a real impact in
        (t-2, t-1].  With soft_contact as well, the past poses' gaps are to the rigid
        ground: the 3-D sink is quasi-static under the interval's own load, and the loads
        of past intervals are not inputs of the stage (an impact is then detected up to a
        sink, about a millimetre, late)."""
        if len(ctx.past) < 3:
            raise AssertionError("internal: restitution's 3-D stage needs the poses t-4 .. t")
        e_r = ctx.u[self.name]["e"]
        now, before, earliest = ctx.past[0], ctx.past[1], ctx.past[2]
        frames, rows = [], []
        for k in range(len(ctx.phi)):
            a_old, w_old, _ = self._impact_3d(ctx, earliest, k)
            memory_old = w_old * a_old
            a_prev, w_prev, _ = self._impact_3d(ctx, before, k)
            A = (1 - _gate(memory_old)) * w_prev * a_prev  # m/s
            after = _gate(A)
            vn = ca.dot(ctx.n_g, ctx.v + ca.mtimes(ctx.R, cross(ctx.w, ctx.levers[k])))
            leave = smooth_pos(e_r * A - ctx.grav * ctx.dt, REBOUND_SMOOTHING)
            rows.append(after * (vn - leave) / (ctx.sig_v + RESTITUTION_SCATTER * A))
            a_now, w_now, p = self._impact_3d(ctx, now, k)
            struck = (1 - after) * w_now
            freed = struck + after - struck * after
            ctx.phi[k] = ctx.phi[k] - freed * smooth_pos(ctx.phi[k], IMPACT_DEPTH_EPS)
            above = smooth_pos(now.phi[k], IMPACT_DEPTH_EPS)
            into = above / (above + smooth_pos(p, IMPACT_DEPTH_EPS) + IMPACT_DEPTH_EPS)  # impact time / dt
            at_impact = now.R + into * (ctx.R - now.R)
            frames.append(ctx.R + struck * (at_impact - ctx.R) + after * (now.R - ctx.R))
        ctx.impulse_R = frames
        ctx.dynamics_rows += rows


# ---------------------------------------------------------------------------------------
# soft_contact

#: soft_contact: the compliance parameter's unit, as a fraction of the length scale L
#: (a 1 kg box on a 3000 N/m ground with L = 0.1 m sinks 3.3 mm: compliance ≈ 3)
COMPLIANCE_UNIT = 0.01
#: s: soft_contact's tau unit (the ground's time constant damping / stiffness; a plate
#: damped at 0.5-1 × critical under a 0.2-1 kg object on 1500-6000 N/m has 6-50 ms)
TAU_UNIT = 0.01
#: soft_contact: unit of the plate's sink state, a fraction of the length scale L (as
#: COMPLIANCE_UNIT, so that the sink at rest is compliance × the load)
PLATE_UNIT = COMPLIANCE_UNIT
#: s: added to soft_contact's tau in the plate's decay exp(-dt / tau) over a sample, so
#: that tau = 0 (no damper: the plate follows its load) has finite derivatives
TAU_FLOOR = 1e-6


def weight_sink(compliance_m_per_n: float, mass_kg: float) -> float:
    """m, how far a ground of ``compliance_m_per_n`` (m/N, 1/stiffness) sinks at rest
    under an object of ``mass_kg`` (its weight m g); scalars."""
    from tacest.constants import STANDARD_GRAVITY

    return float(compliance_m_per_n) * float(mass_kg) * STANDARD_GRAVITY


def compliance_for_sink(sink_m: float, mass_kg: float) -> float:
    """m/N, the compliance under which an object of ``mass_kg`` sinks ``sink_m`` at rest
    (the inverse of :func:`weight_sink`); scalars, mass > 0."""
    return float(sink_m) / weight_sink(1.0, mass_kg)


class SoftContact(Effect):
    """A compliant ground: a massless plate on a spring k and damper c (Kelvin–Voigt)
    under the sample's load W (the normal ground impulses over dt): k·s + c·ds/dt = W.
    State: the plate's sink s of every sample (units of PLATE_UNIT·L).

    Its sink is a state of every sample, so the plate's velocity ds/dt = (s - s_prev)/dt
    pays for itself: it follows from the loads of consecutive samples, and a plate that
    moved within one sample to excuse a vertex's jitter (as a per-sample velocity did:
    16 of 20 clean benchmark recordings were blamed on soft_contact) needs the loads to
    jump with it.  The law is a residual of the dynamics term (:meth:`plate_law`); its
    load is the ground's normal impulse.  A vertex may penetrate the fixed ground by s,
    and the contact laws see its normal velocity relative to the plate."""

    name = "soft_contact"
    dims = (2, 3)
    doc = "compliant ground: a plate on a spring and damper sinks under the load"

    def parameters(self, K, dim):
        compliance = EffectParameter("compliance", 0.0, 5.0, 0.0, 100.0, unit="m/N",
                                     per_unit=lambda sc: COMPLIANCE_UNIT * sc.L / (sc.m0 * sc.g),
                                     doc="1 / stiffness")
        if dim == 3:  # the 3-D ground sinks quasi-statically (ground_surface_3d): no damper
            return (compliance,)
        return (compliance, EffectParameter("tau", 0.0, 5.0, 0.0, 20.0, unit="s", per_unit=lambda sc: TAU_UNIT,
                                            doc="damping / stiffness"))

    def state_rows(self, K, dim):
        return 1 if dim == 2 else 0

    def report(self, u, sc, K, mu_ground):
        c = u["compliance"] * COMPLIANCE_UNIT * sc.L / (sc.m0 * sc.g)
        out = {"soft_contact.compliance": c, "soft_contact.stiffness": 1.0 / c if c > 0 else float("inf")}
        if "tau" in u:
            tau = u["tau"] * TAU_UNIT
            out.update({"soft_contact.tau": tau, "soft_contact.damping": tau / c if c > 0 else float("inf")})
        return out

    def ground_surface_3d(self, ctx):
        """The ground sinks under the interval's load W (the normal ground impulses over
        dt) by compliance × W, quasi-statically (no damper and no plate velocity in 3-D:
        the contact laws see the gaps to the sunk plate, the normal velocities as on a
        rigid ground)."""
        sink = ctx.u[self.name]["compliance"] * COMPLIANCE_UNIT * ctx.L * ca.sum1(ctx.lam_n)  # m
        ctx.phi = [p + sink for p in ctx.phi]

    @staticmethod
    def plate_law(ctx, u, s, s_prev, load):
        """soft_contact's plate over one sample: (sink m, its downward rate m/s, the
        law's whitened residual).  s, s_prev: the sample's and the previous sample's
        sinks (units of PLATE_UNIT·L), s_prev None for a plate at rest; load: the normal
        ground impulse over the sample in units of m0·g·dt; u: the effect's values.

        The law k·s + c·ds/dt = W over the interval, exact for a load held constant
        across it: (s - a·s_prev)/(1 - a) = C·W with a = exp(-dt/tau) (a backward
        difference, s + tau·(s - s_prev)/dt, would put the fitted tau at exp(dt/tau) - 1
        = dt/tau_fit: 25 ms for 30 at dt = 10 ms); at rest s = C·W.  Whitened by the
        sink one process sigma of velocity makes in one sample: it holds as tightly as
        the momentum balance does."""
        L, dt = ctx.L, ctx.dt
        unit = PLATE_UNIT * L  # m per unit of s
        sink = s * unit
        sink_static = u["compliance"] * COMPLIANCE_UNIT * L * load  # m, W/k
        sig_sink = ctx.g_sig_proc * ctx.grav * dt * dt  # m
        if s_prev is None:
            return sink, 0.0, (sink - sink_static) / sig_sink
        before = s_prev * unit
        decay = ca.exp(-dt / (u["tau"] * TAU_UNIT + TAU_FLOOR))
        return sink, (sink - before) / dt, ((sink - decay * before) / (1 - decay) - sink_static) / sig_sink

    def ground_surface_2d(self, ctx):
        u = ctx.u[self.name]
        s_now, rate, r = self.plate_law(ctx, u, ctx.s[self.name][0], ctx.s_prev[self.name][0],
                                        ca.sum1(ctx.lam_ground[:ctx.K]))
        ctx.dynamics_rows[self.name] = [r]
        ctx.phi_c = [p + s_now for p in ctx.phi_c]
        ctx.vn_c = [vn + rate for vn in ctx.vn_c]
        ctx.plate = (s_now, rate)

    def start_2d(self, ctx):
        # at rest on a compliant ground: the plate sunk by the object's weight (the load
        # m·g·dt is the mass ratio m / m0 in impulse units), whitened as the plate law of
        # every later sample; a free start (w_rest 0) leaves the plate free too
        sink, _, r = self.plate_law(ctx, ctx.u[self.name], ctx.s[self.name][0], None, ctx.mass_ratio)
        ctx.rest_rows[self.name] = [ctx.w_rest * r]
        ctx.phi = [p + sink for p in ctx.phi]

    def initial_states_2d(self, u, mass_ratio, LG_normal, K):
        # the plate rests under its load (s = compliance × load; the law without its
        # damper), the object's weight at sample 0
        comp = u["compliance"]
        return (comp * np.concatenate([[mass_ratio], np.asarray(LG_normal, float).sum(axis=0)]))[None, :]


# ---------------------------------------------------------------------------------------
# face_friction

#: face_friction: prior sigma and bounds of the per-face friction offsets d_i
FACE_FRICTION_PRIOR = (0.0, 0.5, -1.5, 1.5)
#: face_friction: sharpness of the softmax that picks the face facing the ground most
#: (weights exp(-FACE_SHARPNESS · n_face·up)): between the faces of a box resting flat
#: (n·up = -1 vs 0) the ratio is e^-20; at 45° the two lower faces share equally
FACE_SHARPNESS = 20.0
#: face_friction: smoothing of the floor at 0 of the friction of the face below
#: (laws.smooth_pos): a friction coefficient is not negative (a negative one would push
#: a sliding box along its slip); 1e-3 changes a friction of 0.1 by 2.5e-6
FACE_FRICTION_FLOOR_EPS = 1e-3


#: face_friction in 3-D (boxes): the outward body-frame normals of a box's six faces, in
#: SPEC's face order (tacest.sim3d.objects.hull_faces: sorted by the normal's x, then y,
#: then z component)
BOX_FACE_NORMALS = np.array([[-1, 0, 0], [0, -1, 0], [0, 0, -1], [0, 0, 1], [0, 1, 0], [1, 0, 0]], float)


def _floored(mu, offset):
    """mu + offset floored smoothly at 0 (a friction coefficient is not negative: a
    negative one would push a sliding box along its slip), exactly mu at offset 0 (the
    effect at "no effect" is the plain model): mu + s(mu + offset) - s(mu), s the
    smoothed max(x, 0) of width FACE_FRICTION_FLOOR_EPS (laws.smooth_pos), which is
    x + O(eps² / x) above 0 and O(eps² / |x|) below."""
    return mu + smooth_pos(mu + offset, FACE_FRICTION_FLOOR_EPS) - smooth_pos(mu, FACE_FRICTION_FLOOR_EPS)


class FaceFriction(Effect):
    """Ground friction differs from face to face: face i has friction_ground + d_i, the
    friction under the object is that of the face facing the ground most, floored
    smoothly at 0 (:func:`_floored`: the offsets are bounded, not their sum with the
    ground's friction).  In 2-D face i runs from vertex i to i+1 of the CCW polygon;
    in 3-D the shape is a box and its faces are in SPEC's order (BOX_FACE_NORMALS)."""

    name = "face_friction"
    dims = (2, 3)
    doc = "ground friction differs from face to face"

    @staticmethod
    def n_faces(K, dim):
        return K if dim == 2 else len(BOX_FACE_NORMALS)

    def parameters(self, K, dim):
        return tuple(EffectParameter(f"d{i}", *FACE_FRICTION_PRIOR, doc=f"friction offset of face {i}")
                     for i in range(self.n_faces(K, dim)))

    def report(self, u, sc, K, mu_ground):
        """friction_ground + d_i per face (the model floors a negative one at ~0)."""
        return {"face_friction.values": np.array([mu_ground + u[f"d{i}"] for i in range(len(u))])}

    def scaled(self, params, sc, K, mu_ground, dim):
        if "face_friction.values" not in params:
            raise KeyError("face_friction.values")
        vals = np.asarray(params["face_friction.values"], float).reshape(-1)
        n = self.n_faces(K, dim)
        if vals.size != n:
            raise ValueError(f"face_friction.values has {vals.size} entries, the shape has {n} faces")
        return {f"d{i}": float(vals[i]) - mu_ground for i in range(n)}

    def ground_friction_3d(self, ctx):
        """As in 2-D: the offset Σ_i w_i d_i of the box face facing the ground most,
        w_i ∝ exp(-FACE_SHARPNESS · (R n_i)·n_g), n_i of BOX_FACE_NORMALS."""
        u = ctx.u[self.name]
        scores = [-FACE_SHARPNESS * ca.dot(ctx.n_g, ca.mtimes(ctx.R, ca.DM(n))) for n in BOX_FACE_NORMALS]
        w = ca.exp(ca.vertcat(*scores))
        d = ca.vertcat(*(u[f"d{i}"] for i in range(len(BOX_FACE_NORMALS))))
        ctx.mu_g = _floored(ctx.mu_g, ca.dot(w, d) / ca.sum1(w))

    def ground_friction_2d(self, ctx):
        """Ground friction offset Σ_i w_i d_i of the face that faces the ground most:
        softmax weights w_i ∝ exp(-FACE_SHARPNESS · n_i·n_g), n_i the outward normal
        (world) of face i, from vertex i to i+1 of the CCW polygon V (K, 2) m."""
        K, V, u = ctx.K, ctx.V, ctx.u[self.name]
        R = rot2(ctx.q[2])
        scores, d = [], []
        for i in range(K):
            e = V[(i + 1) % K, :] - V[i, :]
            n_body = ca.vertcat(e[1], -e[0]) / ca.sqrt(e[0] * e[0] + e[1] * e[1])
            scores.append(-FACE_SHARPNESS * ca.dot(ctx.n_g, R @ n_body))
            d.append(u[f"d{i}"])
        w = ca.exp(ca.vertcat(*scores))
        ctx.mu_g = _floored(ctx.mu_g, ca.dot(w, ca.vertcat(*d)) / ca.sum1(w))


# ---------------------------------------------------------------------------------------
# 3-D: the ground plane's height and a box's rounded edges


class GroundOffset(Effect):
    """The ground plane higher than the runs' /scene ground_height by an estimated offset
    (3-D; a tacest extension of SPEC's effects).  Prior: zero-mean, sigma
    ``solver3d.ground_offset_sigma`` (m); bounds ±10 sigma and at most a length scale."""

    name = "ground_offset"
    dims = (3,)
    doc = "the ground plane's height above /scene's ground_height (m)"

    def parameters(self, K, dim):
        return (EffectParameter("offset", 0.0, 1.0, -1.0, 1.0, unit="m", per_unit=lambda sc: sc.L,
                                doc="height of the ground plane above /scene's"),)

    def prior(self, par, config, L):
        return 0.0, float(config.solver3d.ground_offset_sigma) / L

    def bounds(self, par, config, L, shape_lower):
        b = min(10 * float(config.solver3d.ground_offset_sigma) / L, 1.0)
        return -b, b

    def report(self, u, sc, K, mu_ground):
        return {"ground_offset": float(u["offset"]) * sc.L}

    def scaled(self, params, sc, K, mu_ground, dim):
        return {"offset": float(params["ground_offset"]) / sc.L}

    def info_name(self, par):
        return "ground_offset"

    def ground_height_3d(self, u, L):
        return u["offset"] * L


class EdgeRadius(Effect):
    """A box's edges and corners rounded with an estimated radius r (3-D, box only; a
    tacest extension of SPEC's effects): the shape is the inner box of half extents
    s L / 2 - r swept by a ball of radius r (the extents stay the outer size).  Prior:
    half-normal at 0, sigma ``solver3d.edge_radius_sigma`` (m); bounds 0 .. 10 sigma and
    at most a quarter of the smallest extent."""

    name = "edge_radius"
    dims = (3,)
    doc = "radius of a box's rounded edges and corners (m)"

    def parameters(self, K, dim):
        return (EffectParameter("radius", 0.0, 1.0, 0.0, 1.0, unit="m", per_unit=lambda sc: sc.L,
                                doc="radius of the rounded edges"),)

    def prior(self, par, config, L):
        return 0.0, float(config.solver3d.edge_radius_sigma) / L

    def bounds(self, par, config, L, shape_lower):
        return 0.0, min(10 * float(config.solver3d.edge_radius_sigma) / L, 0.25 * float(np.min(shape_lower)))

    def report(self, u, sc, K, mu_ground):
        return {"edge_radius": float(u["radius"]) * sc.L}

    def scaled(self, params, sc, K, mu_ground, dim):
        return {"radius": float(params["edge_radius"]) / sc.L}

    def info_name(self, par):
        return "edge_radius"

    def rounding_3d(self, u, L):
        return u["radius"] * L

