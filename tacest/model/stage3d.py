"""The 3-D stage model: one dynamic interval's whitened residuals as CasADi functions,
and the layouts of their inputs, shared by the NLP (tacest.estimation.problem3d) and the
forward simulator (tacest.estimation.rollout3d).

The model is that of :mod:`tacest.dynamics.rigid3d` (equations D1–D2, C1–C3, see also
docs/estimation3d.md).  The decision variables are the POSES of every sample; the
kinematics (D2) are eliminated: the velocity over the interval (t-1, t] is defined by
the two poses,

    v[t] = (p[t] - p[t-1]) / dt,      omega_b[t] = 2 log(q[t-1]* ⊗ q[t]) / dt,

so that q[t] = q[t-1] ⊗ exp(omega_b[t] dt / 2) and p[t] = p[t-1] + dt v[t] hold exactly by
construction (:func:`body_rate`).  Quaternions enter only normalised (q / |q|), and a
residual (|q|² - 1) / QUAT_NORM_SIGMA fixes their free scale.  The problem is then a
nonlinear least-squares problem with simple bounds, no equality constraints: an
interior-point method takes full Newton steps without second-order corrections.

All runs are laid end to end: samples j = 0 .. S-1 of every run in order.  Dynamics (D1)
are enforced on the intervals (t-1, t] with t >= 2 of each run ("dynamic intervals",
M = Σ (T_i - 2) of them): they involve the poses t-2, t-1, t (and, with an effect that
looks back, restitution, the earlier ones of the window, Layout3D.windows).  ONE stage function is
mapped over all dynamic intervals of all runs, one start function over the runs.

Decision vector z (all scaled to O(1); L length scale, m0 mass scale)::

    theta  = [s (n_s) shape, log(m / m0), c (6) log-Cholesky of Sigma / (m L²),
              mu_ground, mu_finger, ground_offset / L, edge_radius / L]
    P      (7, S):  per sample [p / L (3), q (4)]
    U      (K, M):  per dynamic interval, ground impulse variable of each vertex:
                    lambda_n = softplus(u) in units of m0 g dt (:func:`impulse_of`)
    LF     (3F, M): per dynamic interval, each finger's impulse ON the object, world
                    frame, in units of m0 g dt

Loss: 0.5 |r|² of the stacked whitened residuals (each term times the square root of its
weight) plus the priors.  Terms (names as in estimate files)::

    pose            [(p - p_obs) / sigma_position, 2 vec(q_obs* ⊗ q̂) / sigma_angle]   where observed
    dynamics        [Δv - g dt - Σ λ / m,  Δω - I⁻¹(Σ r × Rᵀλ - dt ω × I ω)] / (process · g dt · [1, 2 / L])
                    (at a run's start without a pose observation: the rest term v[1] / sigma_rest)
    penetration     one_sided(phi_k, sigma_penetration) (problem.py: ≈ 0 for phi >= 0, ≈ phi / sigma below)
    complementarity lambda_n psi(phi_k) / sigma_complementarity, psi = g / (1 + g),
                    g = (phi / sigma_gap - 1)⁺ smoothed: a vertex within ~sigma_gap counts as touching
    force, normal, contact, cone, dissipation   fingertip terms, as in 2-D (problem.py)

Ground friction is in closed form on the cone's boundary against the slip (C2 + C3,
second-order cone, regularized below SLIP_EPS as in 2-D).  The Lagrangian Hessian is
lam_f (Jᵀ J + [exact only] Σ r_i ∇² r_i) + a Levenberg–Marquardt ridge, assembled from
small per-interval blocks; the per-sample functions are compiled to C when a compiler
is available (:mod:`tacest.estimation.kernels`).


Effects (tacest.model.registry) add parameters after PHYS_NAMES_3D in theta and act
through the hooks of tacest.model.effect.Effect: the ground's height (ground_offset), a
box's rounded edges (edge_radius) and the centre of mass's place in the shape (com_offset)
in :meth:`StageModel3D.ground_geometry` and :meth:`StageModel3D.finger_geometry`; the
sunk ground (soft_contact) and the ground friction of the face below (face_friction) on
the stage's :class:`Stage3DContext`; extra impulses on the body (linear_drag,
angular_damping); the force sensor's gain and offset (force_scale, force_bias) on the
force residual, the gain also on the physics residuals (as in 2-D: then a gain and a mass
scaled together are one model, as they are one data).  None of them has per-sample states
in 3-D (docs/estimation3d.md, "Effects").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from tacest.dynamics.laws import CONE_TOLERANCE, SLIP_EPS, contact_residual, one_sided, smooth_pos
from tacest.errors import TacestError
from tacest.dynamics.rigid3d import (cross, ground_contacts, inertia_from_cholesky, qconj, qmul, quat_error_vector,
                                     quat_rotation)
from tacest.geometry.shapes3d import Shape3D, shape_sd_and_normal_function
from tacest.model.effect import parameter_table, physics_gain, sensor_reading
from tacest.model.priors import N_PRIOR_FIXED, ON, parameter_prior_residual
from tacest.model.registry import names_of, resolve

#: squared-residual terms (weights from config.weights under the same names)
TERMS3D = ("force", "normal", "contact", "pose", "dynamics", "penetration", "complementarity", "dissipation",
           "cone")
#: terms of the per-interval stage and of a run's first two samples
STAGE_TERMS = TERMS3D
START_TERMS = ("pose", "dynamics", "penetration", "contact")
NP = 7  # pose size per sample
#: physical parameters in theta after the shape block
PHYS_NAMES_3D = ("log_mass", "inertia_a1", "inertia_a2", "inertia_a3", "inertia_b21", "inertia_b31",
                 "inertia_b32", "friction_ground", "friction_finger")
#: sigma of the residual |q|² - 1 that fixes the free scale of every quaternion variable
#: (the model uses q / |q| only, so any value works; 1e-2 keeps it well conditioned)
QUAT_NORM_SIGMA = 1e-2
#: width of the softplus that maps the ground-impulse variables u to lambda_n >= 0, in
#: units of m0 g dt: an object resting on four corners puts ~0.25 on each, where the map
#: is the identity to 1e-11; a vertex in the air sits at lambda_n ~ 1e-4 with u ~ -0.05
IMPULSE_SOFTPLUS = 0.01
#: coefficients c_k of asin(y) / y = Σ c_k y^(2k): the body rate from two quaternions
#: (:func:`body_rate`); with 10 terms the relative error is below 1e-8 for rotations up
#: to 0.5 rad per sample (73 rad/s at dt = 6.8 ms)
_ASIN_TERMS = 10
_ASIN_COEF = [float(np.prod(np.arange(1, 2 * k + 1)) / (4 ** k * np.prod(np.arange(1, k + 1)) ** 2 * (2 * k + 1)))
              for k in range(_ASIN_TERMS)]

#: per-sample data rows (run constants repeated on every sample, then the streams): dt
#: s, Lam = m0·g·dt N·s, the run's gravity (its magnitude m/s² and its vector), the
#: ground's normal and height, the pose observation's sigmas, weight and value, w_rest
D_NAMES = ("dt", "Lam", "grav", "gx", "gy", "gz", "nx", "ny", "nz", "h", "sig_pos", "sig_ang", "w_pose",
           "px", "py", "pz", "qw", "qx", "qy", "qz", "w_rest")
DI = {n: i for i, n in enumerate(D_NAMES)}
#: per finger data rows: centre (m), velocity (m/s), flag, measured normal and force, weights, radius (m), and
#: the centre at the interval's start (m) and 1 at the last sample of a touch (the flag covers the interval:
#: laws.contact_residual, estimation.data.touch_ends)
DF_NAMES = ("cx", "cy", "cz", "vx", "vy", "vz", "contact", "nmx", "nmy", "nmz", "fx", "fy", "fz", "w_force",
            "w_tact", "radius", "sx", "sy", "sz", "ends")
#: shared settings
G3_NAMES = ("L", "m0", "sig_proc", "sig_pen", "sig_gap", "sig_comp", "eps", "comp_mult", "dyn_mult",
            "sig_force", "sig_normal", "sig_diss", "sig_rest")
G3 = {n: i for i, n in enumerate(G3_NAMES)}
#: prior vector: its fixed head (tacest.model.priors.PRIOR_HEAD), then (centre, sigma) of
#: every effect parameter (scaled), then s_ref (n_s)


def impulse_of(u):
    """lambda_n = softplus(u) = w log(1 + exp(u / w)) > 0 (w = IMPULSE_SOFTPLUS), stable
    for any u.  The variables u carry no bounds: an interior-point method then takes full
    Newton steps instead of steps cut short at lambda_n >= 0 by the fraction-to-boundary rule."""
    x = u / IMPULSE_SOFTPLUS
    return IMPULSE_SOFTPLUS * (ca.fmax(x, 0) + ca.log1p(ca.exp(-ca.fabs(x))))


def impulse_variable(lam):
    """Inverse of :func:`impulse_of` (numpy), for lambda_n > 0 (floored at 1e-9)."""
    lam = np.maximum(np.asarray(lam, float), 1e-9) / IMPULSE_SOFTPLUS
    return IMPULSE_SOFTPLUS * (lam + np.log(-np.expm1(-lam)))


def body_rate(q_prev, q, dt):
    """omega_b (3,) rad/s with q̂ = q̂_prev ⊗ exp(omega_b dt / 2) for two quaternions (any
    norm, same hemisphere or not): with d = q̂_prev* ⊗ q̂ = [cos(a/2), sin(a/2) e],
    y = 2 d_w vec(d) = sin(a) e (unchanged by d -> -d), and omega_b dt = y asin|y| / |y|
    by its series in |y|² (smooth at 0; rotations below 90° per sample)."""
    d = qmul(qconj(q_prev), q)
    y = 2 * d[0] * d[1:4] / ca.dot(d, d)
    s = ca.dot(y, y)
    a = 0
    for k, c in enumerate(_ASIN_COEF):
        a = a + c * s ** k
    return y * a / dt


def pose_velocity(x_prev, x, dt, L):
    """(v (3) m/s world, omega_b (3) rad/s) over an interval from two scaled poses (7,)."""
    return (x[0:3] - x_prev[0:3]) * L / dt, body_rate(x_prev[3:7], x[3:7], dt)


@dataclass(frozen=True)
class Layout3D:
    """Sample bookkeeping for runs laid end to end: lengths T_i (>= 3) and fingers F (max)."""

    lengths: tuple
    F: int

    @property
    def S(self):
        return int(sum(self.lengths))

    @property
    def M(self):
        """Number of dynamic intervals (t >= 2 of every run)."""
        return int(sum(T - 2 for T in self.lengths))

    @property
    def first(self) -> np.ndarray:
        """(R,) index of every run's first sample."""
        return np.concatenate([[0], np.cumsum(self.lengths)[:-1]]).astype(int)

    @property
    def triples(self):
        """(M, 3) sample indices (t-2, t-1, t) of each dynamic interval."""
        return self.windows(3)

    def windows(self, n: int) -> np.ndarray:
        """(M, n) sample indices (t-n+1, ..., t) of each dynamic interval, oldest first;
        the ones before a run's first sample are that first sample (a pose repeated: a
        velocity of 0 in the interval that would end there)."""
        out = []
        for a, T in zip(self.first, self.lengths):
            t = a + np.arange(2, T)
            out.append(np.maximum(t[:, None] + np.arange(1 - n, 1)[None, :], a))
        return np.concatenate(out).astype(int)

    def run_samples(self, i):
        a = int(self.first[i])
        return slice(a, a + int(self.lengths[i]))

    def run_intervals(self, i):
        """Slice of run i's dynamic intervals (its samples 2 .. T-1)."""
        a = int(sum(T - 2 for T in self.lengths[:i]))
        return slice(a, a + int(self.lengths[i]) - 2)


def n_data(F):
    return len(D_NAMES) + len(DF_NAMES) * F


@dataclass
class Stage3DContext:
    """What an effect's 3-D hooks see of one interval (tacest.model.effect.Effect):
    u {effect: {parameter: scaled value}}; L m, m0 kg, grav m/s², dt s; v (3) m/s world
    and w (3) rad/s body, the interval's velocity; R (3, 3) body to world; n_g (3) the
    ground's normal; lam_n (K) normal ground impulses (units of m0·g·dt); levers (K x
    (3,)) the body-frame contact points, m; sig_v m/s the
    process sigma of a velocity change over the interval; past: the earlier poses of
    the stage's window, newest first (t-1, t-2, ...: as many as have an interval ending
    at them in the window, :attr:`StageModel3D.n_poses`; none for a window of three),
    each a :class:`PastPose`.
    Hooks change mu_g (the ground's friction), phi (K vertex gaps, m, as the contact
    laws see them), impulse_R (K rotations body to world, None: R, under which each
    vertex's ground impulse acts on the body) and add whitened law rows to the dynamics
    term (dynamics_rows)."""

    u: dict
    L: Any
    m0: Any
    grav: Any
    dt: Any
    v: Any
    w: Any
    R: Any
    n_g: Any
    lam_n: Any
    mu_g: Any
    phi: list
    sig_v: Any = None
    levers: list = field(default_factory=list)
    past: list = field(default_factory=list)
    impulse_R: Any = None
    dynamics_rows: list = field(default_factory=list)


@dataclass
class PastPose:
    """An earlier pose of a 3-D stage's window (Stage3DContext.past): the vertices' gaps
    phi (K, m), levers (K x (3,), body-frame contact points, m) and R (3, 3) there, and the
    velocity of the interval ending there: v (3) m/s world, w (3) rad/s body."""

    phi: list
    levers: list
    R: Any
    v: Any
    w: Any


class StageModel3D:
    """The model's per-sample residual functions (SX) for a shape and F fingers: what
    the NLP maps over samples and what the forward simulator (rollout3d.py) solves
    step by step."""

    def __init__(self, shape: Shape3D, F: int, effects=()):
        self.shape = shape
        self.K = shape.n_vertices
        self.F = int(F)
        self.n_shape = shape.n_params
        self.effect_objects = resolve(effects, 3)
        #: names of the modelled effects, canonical order
        self.effects = names_of(self.effect_objects)
        if "face_friction" in self.effects and shape.name != "box":
            raise TacestError(f"effect face_friction is modelled in 3-D for boxes only, not {shape.name}")
        #: [(Effect, EffectParameter)] of the effect block (theta after PHYS_NAMES_3D)
        self.effect_params = parameter_table(self.effect_objects, self.K, 3)
        self.n_eff = len(self.effect_params)
        self.n_theta = self.n_shape + len(PHYS_NAMES_3D) + self.n_eff
        self.n_d = n_data(self.F)
        #: poses the stage of the interval (t-1, t] sees: t-2, t-1, t and the earlier
        #: ones its effects look back at (Effect.history_3d), oldest first
        self.n_poses = 3 + max([e.history_3d for e in self.effect_objects], default=0)

    def theta_index(self, name):
        """Index in theta of a physical parameter (PHYS_NAMES_3D), of an effect's first
        parameter (its name), or of ``effect.parameter``."""
        if name in PHYS_NAMES_3D:
            return self.n_shape + PHYS_NAMES_3D.index(name)
        for j, (e, p) in enumerate(self.effect_params):
            if name in (e.name, f"{e.name}.{p.name}"):
                return self.n_shape + len(PHYS_NAMES_3D) + j
        raise KeyError(name)

    def effect_values(self, th):
        """{effect name: {parameter: value}} of theta's effect block."""
        out = {e.name: {} for e in self.effect_objects}
        a = self.n_shape + len(PHYS_NAMES_3D)
        for j, (e, p) in enumerate(self.effect_params):
            out[e.name][p.name] = th[a + j]
        return out

    def effect_priors(self, config, L) -> np.ndarray:
        """(2 n_eff,) [centre, sigma] of every effect parameter's prior (scaled)."""
        out = []
        for e, p in self.effect_params:
            out += list(e.prior(p, config, L))
        return np.asarray(out, float)

    def n_prior(self):
        return N_PRIOR_FIXED + 2 * self.n_eff + self.n_shape

    def ground_offset(self, th, L):
        """Height (m) of the ground plane along its normal above the run's ``/scene
        ground_height`` that the effects give (ground_offset; 0 without)."""
        u = self.effect_values(th)
        total = 0
        for e in self.effect_objects:
            h = e.ground_height_3d(u[e.name], L)
            if h is not None:
                total = total + h
        return total

    def edge_radius(self, th, L):
        """Radius (m) of the box's rounded edges and corners that the effects give
        (edge_radius; None without)."""
        u = self.effect_values(th)
        for e in self.effect_objects:
            r = e.rounding_3d(u[e.name], L)
            if r is not None:
                return r
        return None

    def com_shift(self, th, L):
        """(3,) m: the centre of mass in the shape's own frame (com_offset), or None."""
        u = self.effect_values(th)
        for e in self.effect_objects:
            d = e.com_shift_3d(u[e.name], L)
            if d is not None:
                return d
        return None

    def body_vertices(self, th, L):
        """(K, 3) m: the vertices in the body frame (its origin at the centre of mass)."""
        V = self.shape.vertices(th[: self.n_shape], L)
        shift = self.com_shift(th, L)
        return V if shift is None else V - ca.repmat(shift.T, self.K, 1)

    def ground_geometry(self, p, q, v, w, th, d, L):
        """Ground contact of every vertex: (phi (K) m, slip (K x (3,)) m/s world, levers
        (K x (3,)) body-frame contact points m, R (3, 3)), with the augmentations: the ground
        raised by ``ground_offset`` and, for a box, the edges and corners rounded with radius
        ``edge_radius`` r (the box's extents are its outer size: the shape is the inner box
        of half extents s L / 2 - r swept by a ball of radius r, so its lowest point is an
        inner vertex minus r along the ground normal)."""
        n_g = d[DI["nx"]: DI["nz"] + 1]
        V = self.body_vertices(th, L)
        r = self.edge_radius(th, L) if self.shape.name == "box" else None
        if r is not None:
            V = V - r * ca.DM(np.sign(np.array(ca.DM(self.shape.vertices(np.ones(3), 1.0)))))
        phi, slip, levers, R = ground_contacts(p, q, v, w, V, n_g, d[DI["h"]] + self.ground_offset(th, L))
        if r is None:
            return phi, slip, levers, R
        n_b = r * ca.mtimes(R.T, n_g)  # from an inner vertex to its contact point is -n_b
        spin = ca.mtimes(R, cross(w, n_b))  # the contact point moves by -spin relative to the vertex
        return ([ph - r for ph in phi], [sl - spin + ca.dot(n_g, spin) * n_g for sl in slip],
                [lv - n_b for lv in levers], R)

    def unpack_theta(self, th, L, m0):
        """(s (n_s), mass kg, a (3, 3) = I / m in m², mu_g, mu_f) from theta."""
        ns = self.n_shape
        I_s, _ = inertia_from_cholesky(th[ns + 1: ns + 7])
        return th[:ns], m0 * ca.exp(th[ns]), I_s * L * L, th[ns + 7], th[ns + 8]

    def prior_residual(self, th, pr):
        """Whitened prior residual of theta under the prior vector pr (N_PRIOR_FIXED)."""
        ns = self.n_shape
        s = th[:ns]
        c_ref = self.shape.uniform_cholesky_reference(s)
        a, b = ns + len(PHYS_NAMES_3D), N_PRIOR_FIXED
        effects = [(th[a + j] - pr[b + 2 * j]) / pr[b + 2 * j + 1] for j in range(self.n_eff)]
        r = ca.vertcat(parameter_prior_residual(th[ns], th[ns + 1: ns + 7] - c_ref, th[ns + 7], th[ns + 8],
                                                s - pr[b + 2 * self.n_eff:], pr), *effects)
        return ca.sqrt(pr[ON]) * r

    @staticmethod
    def finger_geometry(p, R, s, L, c_f, radius, sd_fun, shift=None):
        """Gap phi_f (m), outward normal n (3, world) and body-frame contact point r_b
        (3, m) of one fingertip sphere centred at c_f (3, world); shift (3,) m: the centre
        of mass in the shape's frame (:meth:`com_shift`), None at its centroid."""
        c_b = ca.mtimes(R.T, c_f - p)
        sd, n_b = sd_fun(c_b if shift is None else c_b + shift, s, L)
        n_b = n_b / ca.sqrt(ca.dot(n_b, n_b) + 1e-12)
        return sd - radius, ca.mtimes(R, n_b), c_b - sd * n_b

    @staticmethod
    def pose_residual(p, q, d):
        """Whitened pose observation residual (6,) of the pose (p m, q) at one sample."""
        q_hat = q / ca.sqrt(ca.dot(q, q))
        return d[DI["w_pose"]] * ca.vertcat((p - d[DI["px"]: DI["pz"] + 1]) / d[DI["sig_pos"]],
                                            quat_error_vector(d[DI["qw"]: DI["qz"] + 1], q_hat) / d[DI["sig_ang"]])

    def pose_input_names(self):
        """Names of the stage's pose inputs, oldest first (n_poses of them: ..., x_tm2,
        x_tm1, x_t)."""
        return [f"x_tm{k}" for k in range(self.n_poses - 1, 0, -1)] + ["x_t"]

    def _past_poses(self, xs, th, d, L):
        """[PastPose] of the window's poses t-1, t-2, ... that have an interval ending
        at them in the window (xs: the scaled pose inputs, oldest first)."""
        dt = d[DI["dt"]]
        out = []
        for j in range(len(xs) - 2, 0, -1):
            v, w = pose_velocity(xs[j - 1], xs[j], dt, L)
            phi, _, levers, R = self.ground_geometry(xs[j][0:3] * L, xs[j][3:7], v, w, th, d, L)
            out.append(PastPose(phi=phi, levers=levers, R=R, v=v, w=w))
        return out

    def _ground_context(self, xs, v, w, th, d, L, m0, ln, mu_g, sig_v):
        """(Stage3DContext after the effects' ground hooks, slip (K x (3,)) m/s) of the
        interval ending at the last of the scaled poses xs (oldest first)."""
        phi, slip, levers, R = self.ground_geometry(xs[-1][0:3] * L, xs[-1][3:7], v, w, th, d, L)
        ctx = Stage3DContext(u=self.effect_values(th), L=L, m0=m0, grav=d[DI["grav"]], dt=d[DI["dt"]], v=v, w=w,
                             R=R, n_g=d[DI["nx"]: DI["nz"] + 1], lam_n=ln, mu_g=mu_g, phi=list(phi), sig_v=sig_v,
                             levers=list(levers), past=self._past_poses(xs, th, d, L) if self.n_poses > 3 else [])
        for e in self.effect_objects:
            e.ground_surface_3d(ctx)
            e.ground_friction_3d(ctx)
        for e in self.effect_objects:
            e.impacts_3d(ctx)
        return ctx, slip

    def _stage_function(self, direct=False):
        """Residuals of one dynamic interval (t-1, t] from the poses t-2, t-1, t (and
        the earlier ones of :attr:`n_poses`).  The ground-impulse input is the variable u
        (lambda_n = softplus(u)) or, with ``direct``, lambda_n itself (for the
        non-negative least squares start)."""
        K, F = self.K, self.F
        xs = [ca.SX.sym(n, NP) for n in self.pose_input_names()]
        xa, xb, xc = xs[-3:]
        u_in = ca.SX.sym("lam_ground" if direct else "u_ground", K)
        ln = u_in if direct else impulse_of(u_in)
        lf = ca.SX.sym("lam_finger", 3 * F)
        th = ca.SX.sym("theta", self.n_theta)
        d = ca.SX.sym("d", self.n_d)
        g = ca.SX.sym("g", len(G3_NAMES))
        L, m0 = g[G3["L"]], g[G3["m0"]]
        dt, Lam = d[DI["dt"]], d[DI["Lam"]]
        n_g = d[DI["nx"]: DI["nz"] + 1]
        s, mass, a_inertia, mu_g, mu_f = self.unpack_theta(th, L, m0)
        p, q = xc[0:3] * L, xc[3:7]
        v, w = pose_velocity(xb, xc, dt, L)
        v_prev, w_prev = pose_velocity(xa, xb, dt, L)
        grav = d[DI["grav"]]  # m/s², the run's gravity
        sig_v = g[G3["sig_proc"]] * grav * dt
        ctx, slip = self._ground_context(xs, v, w, th, d, L, m0, ln, mu_g, sig_v)
        phi, levers, R, mu_g, gain = ctx.phi, ctx.levers, ctx.R, ctx.mu_g, physics_gain(self.effect_objects, ctx.u)
        frames = ctx.impulse_R or [R] * K
        shift = self.com_shift(th, L)
        imp_world = ca.SX.zeros(3)  # Σ impulses / (m0 g dt), world
        torque_b = ca.SX.zeros(3)  # Σ r × Rᵀ impulse, body frame, m · (m0 g dt)
        comp, pen, lt_out = [], [], []
        for k in range(K):
            # C2 + C3 in closed form: on the cone's boundary, against the slip
            lt = -mu_g * ln[k] * slip[k] / ca.sqrt(ca.dot(slip[k], slip[k]) + SLIP_EPS ** 2)
            lt_out.append(lt)
            imp = ln[k] * n_g + lt
            imp_world += imp
            torque_b += cross(levers[k], ca.mtimes(frames[k].T, imp))
            # smoothed gap in units of sig_gap, shifted by one as in 2-D: within about one
            # sig_gap of the ground a vertex counts as touching; saturating, and relative
            # to the object's own weight (lambda_n is in units of m0 g dt)
            gap = smooth_pos(phi[k] / g[G3["sig_gap"]] - 1, g[G3["eps"]])
            # in units of the reference weight m0 g dt, like the impulses (as in 2-D):
            # relative to the object's own weight (a factor m0 / m), a heavy fit made every
            # violation cheap (a poked box came out 5x too heavy, its ground friction 76 %
            # off; with the reference weight 3.6 % and 3.2 %)
            comp.append(gain * ln[k] * gap / (1 + gap))
            # penetration: the shifted one-sided penalty of 2-D (≈ 0 at phi = 0, so that
            # resting contacts are not pushed off the ground)
            pen.append(one_sided(phi[k], g[G3["sig_pen"]]))
        r_force, r_normal, r_contact, cone, diss, imp_f_out = [], [], [], [], [], []
        sd_fun = shape_sd_and_normal_function(self.shape) if F else None
        for f in range(F):
            o = len(D_NAMES) + len(DF_NAMES) * f
            c_f, v_f = d[o: o + 3], d[o + 3: o + 6]
            contact, n_meas, F_meas = d[o + 6], d[o + 7: o + 10], d[o + 10: o + 13]
            w_force, w_tact, radius = d[o + 13], d[o + 14], d[o + 15]
            phi_f, n_w, r_b = self.finger_geometry(p, R, s, L, c_f, radius, sd_fun, shift)
            # the gap at the interval's start too: the flag covers the interval (contact_residual)
            phi_f_start, _, _ = self.finger_geometry(xb[0:3] * L, quat_rotation(xb[3:7]), s, L, d[o + 16: o + 19],
                                                     radius, sd_fun, shift)
            imp_s = lf[3 * f: 3 * f + 3]
            lam_n = -ca.dot(imp_s, n_w)
            lam_t = imp_s + lam_n * n_w  # tangential part
            u_rel = v + ca.mtimes(R, cross(w, r_b)) - v_f
            s_t = (u_rel - ca.dot(u_rel, n_w) * n_w) / L  # object lengths per second
            # eq. C3 at the fingertip: zero when lambda_t opposes the slip at the cone's edge
            diss.append(gain * (mu_f * lam_n * ca.sqrt(ca.dot(s_t, s_t) + (SLIP_EPS / L) ** 2) + ca.dot(lam_t, s_t)))
            # |lambda_t| <= mu lambda_n (and lambda_n >= 0) as a smooth penalty; the 1e-12
            # (scaled impulse units squared) keeps |lambda_t| differentiable at 0
            cone.append(one_sided(gain * (mu_f * lam_n - ca.sqrt(ca.dot(lam_t, lam_t) + 1e-12)), CONE_TOLERANCE)
                        * CONE_TOLERANCE)
            imp_world += imp_s
            torque_b += cross(r_b, ca.mtimes(R.T, imp_s))
            imp_f_out.append(Lam * imp_s)
            r_force.append(w_force * (sensor_reading(self.effect_objects, ctx, Lam * imp_s / dt) - F_meas) / g[G3["sig_force"]])
            r_normal.append(w_tact * contact * (n_meas - n_w) / g[G3["sig_normal"]])
            r_contact.append(contact_residual(phi_f, contact, w_tact, g[G3["sig_gap"]], phi_start=phi_f_start,
                                              ends=d[o + 19]))
        for e in self.effect_objects:  # extra impulses on the body over the interval
            extra = e.body_impulse_3d(ctx)
            if extra is not None:
                imp_world += extra[0] / Lam
                torque_b += extra[1] / Lam
        # D1 divided by the mass (matrix), whitened as process noise on the velocity change
        acc_scale = grav * dt * (m0 / mass)  # scaled impulse -> velocity change, m/s
        r_lin = (v - v_prev) - dt * d[DI["gx"]: DI["gz"] + 1] - acc_scale * imp_world
        r_ang = (w - w_prev) - ca.solve(a_inertia, acc_scale * torque_b - dt * cross(w, ca.mtimes(a_inertia, w)))
        r_dyn = ca.sqrt(g[G3["dyn_mult"]]) * ca.vertcat(r_lin / sig_v, r_ang * (L / 2) / sig_v, *ctx.dynamics_rows)
        empty = ca.SX.zeros(0)
        outs = {
            "force": ca.vertcat(*r_force) if F else empty,
            "normal": ca.vertcat(*r_normal) if F else empty,
            "contact": ca.vertcat(*r_contact) if F else empty,
            "pose": self.pose_residual(p, q, d),
            "dynamics": r_dyn,
            "penetration": ca.vertcat(*pen),
            "complementarity": ca.sqrt(g[G3["comp_mult"]]) * ca.vertcat(*comp) / g[G3["sig_comp"]],
            "dissipation": (ca.vertcat(*diss) if F else empty) / g[G3["sig_diss"]],
            "cone": (ca.vertcat(*cone) if F else empty) / g[G3["sig_comp"]],
            "quat_norm": (ca.dot(q, q) - 1) / QUAT_NORM_SIGMA,
            # diagnostics (not in the loss): normal (K) and tangential (3K) ground
            # impulses in units of m0 g dt, finger impulses on the object (3F, N·s),
            # vertex gaps (K, m), velocity [v world, omega body] (6)
            "lam_n_ground": ln,
            "lam_t_ground": ca.vertcat(*lt_out),
            "imp_finger": ca.vertcat(*imp_f_out) if F else empty,
            "phi_ground": ca.vertcat(*phi),
            "velocity": ca.vertcat(v, w),
        }
        names = list(outs)
        tag = f"_P{self.n_poses}" if self.n_poses != 3 else ""
        return ca.Function(f"stage3d_K{K}_F{F}{tag}" + ("_direct" if direct else ""),
                           [*xs, u_in, lf, th, d, g], [outs[n] for n in names],
                           self.pose_input_names() + ["lam_ground" if direct else "u_ground", "lam_finger",
                                                      "theta", "d", "g"], names)

    def _start_function(self):
        """Terms of a run's first two samples: pose observations, penetration, finger gaps,
        the quaternion norms, and the rest term v[1] ≈ 0 where the run has no pose
        observation at its start (an unobserved object starts at rest)."""
        F = self.F
        xa, xb = ca.SX.sym("x_0", NP), ca.SX.sym("x_1", NP)
        th = ca.SX.sym("theta", self.n_theta)
        da, db = ca.SX.sym("d_0", self.n_d), ca.SX.sym("d_1", self.n_d)
        g = ca.SX.sym("g", len(G3_NAMES))
        L, m0 = g[G3["L"]], g[G3["m0"]]
        s, *_ = self.unpack_theta(th, L, m0)
        sd_fun = shape_sd_and_normal_function(self.shape) if F else None
        pose, pen, contact, qn = [], [], [], []
        shift = self.com_shift(th, L)
        for x, d in ((xa, da), (xb, db)):
            p, q = x[0:3] * L, x[3:7]
            phi, _, _, R = self.ground_geometry(p, q, ca.SX.zeros(3), ca.SX.zeros(3), th, d, L)
            # the ground as the effects move it under the object's own weight (at rest)
            ctx = Stage3DContext(u=self.effect_values(th), L=L, m0=m0, grav=d[DI["grav"]], dt=d[DI["dt"]],
                                 v=ca.SX.zeros(3), w=ca.SX.zeros(3), R=R, n_g=d[DI["nx"]: DI["nz"] + 1],
                                 lam_n=ca.repmat(ca.exp(th[self.n_shape]) / self.K, self.K, 1), mu_g=0, phi=list(phi))
            for e in self.effect_objects:
                e.ground_surface_3d(ctx)
            phi = ctx.phi
            pose.append(self.pose_residual(p, q, d))
            pen += [one_sided(ph, g[G3["sig_pen"]]) for ph in phi]
            for f in range(F):
                o = len(D_NAMES) + len(DF_NAMES) * f
                phi_f, _, _ = self.finger_geometry(p, R, s, L, d[o: o + 3], d[o + 15], sd_fun, shift)
                contact.append(contact_residual(phi_f, d[o + 6], d[o + 14], g[G3["sig_gap"]]))
            qn.append((ca.dot(q, q) - 1) / QUAT_NORM_SIGMA)
        v, w = pose_velocity(xa, xb, da[DI["dt"]], L)
        rest = da[DI["w_rest"]] * ca.vertcat(v, w * (L / 2)) / g[G3["sig_rest"]]
        return ca.Function("start3d", [xa, xb, th, da, db, g],
                           [ca.vertcat(*pose), rest, ca.vertcat(*pen),
                            ca.vertcat(*contact) if F else ca.SX.zeros(0), ca.vertcat(*qn)],
                           ["x_0", "x_1", "theta", "d_0", "d_1", "g"],
                           ["pose", "dynamics", "penetration", "contact", "quat_norm"])



