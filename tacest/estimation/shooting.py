"""Shooting baseline (``tacest estimate --method shooting``, 2-D): differentiable
simulation from the first sample, loss on the measurements only.

DESIGN keeps this baseline to show why the implicit loss (tacest.estimation.problem) is
better conditioned: here the trajectory is not a decision variable but the output of a
forward simulation, so every residual depends on every earlier parameter and contact
event, and the loss inherits the simulation's stiffness and its chaotic sensitivity
(a fingertip pressing on a slightly wrong shape can make d(loss)/d(theta) ~1e16).

Decision variables (scaled, as in the implicit estimator)::

    theta = [shape s (n_s, units of L), log(m / m0), log(I / I_uniform), mu_ground, mu_finger]
    per run i: [x0_i / L (position along the ground), angle0_i]

Each run starts at rest (v0 = 0) with its lowest vertex on the ground: the height of the
start pose follows from the shape and the angle through a soft minimum over the vertices
(:data:`REST_SOFTMIN`).  A box's start angle is held at the start's value (a box at
rest lies on a face); a polygon's start angle of run 0 is held as the gauge.

The model, per physics substep h = dt / SUBSTEPS (semi-implicit Euler v += h M⁻¹ f(q, v),
q += h v; ``casadi.Function.mapaccum`` over samples, so the graph is built once per run
length)::

    ground, per vertex k    f_n = max~(k_g softplus(o_g - phi_k) + c_g u_k gate, 0)   along n_ground
                            f_t = -mu_g f_n s_k / sqrt(s_k² + eps²)                  along t_ground
    fingertip f             f_n = max~(k_f softplus(-phi_f) + c_f u_f gate, 0)        along -n (into the object)
                            f_t =  mu_f f_n s_f / sqrt(s_f² + eps²)                  along t = perp(n)

(u: closing speed; s_k: vertex slip; s_f: fingertip velocity relative to the object's
surface point, along t).  The fingertip is a kinematic circle following the measured
centres, smoothed by a local least-squares line (:func:`finger_track`) and interpolated
linearly within each sample.

- k_g = m g / (2 d_g) per vertex, d_g = :data:`GROUND_SINK`; the offset o_g makes an
  object resting on a face under its own weight sit exactly at phi = 0;
- k_f = m g / d_f, d_f = :data:`FINGER_SINK`; dampers at the given fractions of
  critical damping (c = 2 zeta sqrt(k m));
- normal and friction forces are applied linearly implicitly (:func:`normal_force`,
  :func:`friction_force`), so stiff contacts and sticking friction (eps = SLIP_EPS) are
  stable at a 1 ms substep;
- stiffnesses scale with the (estimated) mass, so the contact frequencies do not depend
  on it.  Without a force stream every force is proportional to m, the trajectory does not
  depend on it, and the mass is held at the prior (not identifiable).

Loss (whitened with the config's noise levels and weighted by its weights; the names are
the estimate file's residual terms)::

    force     (F_sim - F_meas) / sigma_F          mean simulated fingertip force over the interval
    normal    c (n_meas - n_model) / sigma_n      model normal at the end of the interval
    contact   (c phi_f + (1 - c) min~(phi_f, 0)) / sigma_gap
    pose      (q - q_obs) / sigma_pose            where observed

plus the implicit estimator's weak priors on theta.  Start: :meth:`ShootingEstimator.
initial_guess`.  IPOPT with a Gauss–Newton Hessian (JᵀJ by forward derivatives through
the simulation: only theta and the start poses are variables) or L-BFGS; any status other
than success is a SolveFailedError (Maximum_Iterations_Exceeded and
Search_Direction_Becomes_Too_Small included: a baseline that did not converge has no
estimate).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from types import SimpleNamespace

import casadi as ca
import numpy as np

from tacest.constants import STANDARD_GRAVITY
from tacest.dynamics.laws import smooth_abs, smooth_neg, smooth_pos
from tacest.dynamics.rigid2d import generalized_impulse, ground_contacts, mass_matrix_diag, perp, point_velocity
from tacest.errors import TacestError
from tacest.estimation.bounds import FRICTION_BOUNDS, LOG_INERTIA_BOUNDS, LOG_MASS_BOUNDS
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.data import Scales, choose_scales, force_in_contact, pose_observation_columns
from tacest.estimation.estimator import check_runs
from tacest.estimation.initial import initial_extents, initial_pose
from tacest.estimation.result import FitFacts, assemble, shape_seen
from tacest.estimation.solver import SOLVER_CACHE_LIMIT, BuiltSolver, SolverCache, Stage, run_stages
from tacest.estimation.uncertainty import Information, std_of
from tacest.geometry.shapes import Shape, cross2, make_shape, numeric_vertices, polygon_area_centroid_j, \
    polygon_sd_and_normal_function, rot2
from tacest.io.estimate import Estimate, RunEstimate
from tacest.io.run import Run
from tacest.model.priors import N_PRIOR_FIXED, parameter_prior_residual, prior_head
from tacest.model.stage2d import PHYS_NAMES, consecutive_slices

log = logging.getLogger(__name__)

#: physics substeps per sample (h = dt / SUBSTEPS: 1 ms at 100 Hz)
SUBSTEPS = 10
#: m, compression of the ground springs under the object's weight on one face
#: (k_g = m g / (2 d) per vertex).  Stiff, because the recorded fingertips press objects
#: into the ground with up to 30 N (10 m·g for a light object): at 1 mm per m·g the
#: simulated object would sink a centimetre where the real one did not move
GROUND_SINK = 5e-5
#: m, compression of a fingertip spring under a force of m·g (k_f = m g / d): softer than
#: the ground, because the kinematic fingertip's position noise (0.1 mm, smoothed to
#: ~0.04 mm, see finger_track) becomes force noise k_f · noise
FINGER_SINK = 1e-4
#: fractions of critical damping of the ground and fingertip springs (both applied
#: linearly implicitly, see normal_force)
GROUND_DAMPING_RATIO = 1.0
FINGER_DAMPING_RATIO = 1.0
#: m, width of the softplus that smooths the springs' max(penetration, 0) and of the
#: damper gates.  It must span several substeps of fingertip travel (0.04 mm at 4 cm/s),
#: or the sum over substeps makes the loss rugged on that scale; it is far below the
#: 0.5 mm contact-gap noise (a fingertip then touches at a gap of up to ~2 widths)
CONTACT_SMOOTH = 1e-4
#: m, rest offset of the ground springs: softplus(GROUND_OFFSET) = GROUND_SINK, so that an
#: object resting on a face under its own weight sits exactly at phi = 0
GROUND_OFFSET = CONTACT_SMOOTH * math.log(math.expm1(GROUND_SINK / CONTACT_SMOOTH))
#: m/s, slip speed below which the simulated Coulomb friction is regularized (linearly
#: implicit, so it need not grow with the substep: see friction_force).  A law of the
#: forward simulation, not the implicit model's smoothing of |slip| (laws.SLIP_EPS)
FRICTION_REGULARIZATION_SPEED = 2e-3
#: m, temperature of the soft minimum over the vertices that puts the start pose on the
#: ground (the start is at most REST_SOFTMIN · ln K above the exact resting height)
REST_SOFTMIN = 2e-5
#: smoothing of max(f_n, 0), as a fraction of m·g (a spring at rest leaks half of it)
FORCE_SMOOTH = 1e-4
#: candidate start extents (width, height), in units of the length scale L: the start
#: is the candidate with the smallest shooting loss (see ShootingEstimator.initial_guess)
START_GRID = (0.4, 0.55, 0.75, 1.0, 1.35)
#: relative step and tolerance of the information matrix's pseudo-inverse
INFO_RCOND = 1e-10

#: Hessian model for IPOPT: "gauss-newton" (JᵀJ of the whitened residuals from forward
#: derivatives through the simulation: a few times one simulation per iteration, since
#: only theta and the start poses are variables) or "limited-memory" (IPOPT's L-BFGS)
HESSIAN_MODES = ("gauss-newton", "limited-memory")
DEFAULT_HESSIAN = "gauss-newton"

#: measurement terms, in the order the measurement function returns them
TERMS = ("force", "normal", "contact", "pose")
#: per-run outputs of ShootingProblem.outputs, in order
OUTPUT_NAMES = ("Q", "V", "F_sim", "imp_ground_n", "imp_ground_t", *TERMS, "gap", "n_model")
#: names of the physical parameters in theta after the shape block (as in problem.py)

#: built shooting problems by structure (the problem, not its solvers: BuiltSolver per estimate)
_CACHE = SolverCache(limit=SOLVER_CACHE_LIMIT)


def softplus(x, w):
    """Smoothed max(x, 0) of width w: w log(1 + exp(x / w)), stable for any x."""
    return -smooth_neg(-x, w)


def sigmoid(x, w):
    """Smoothed step of width w: 1 / (1 + exp(-x / w))."""
    return 0.5 * (1 + ca.tanh(x / (2 * w)))


# ------------------------------------------------------------------------------------
# the model


def phys_function(shape: Shape) -> ca.Function:
    """SX Function (theta, L, m0) -> (V (K, 2) m, mass kg, inertia kg·m², mu_g, mu_f);
    theta as in the module docstring (the same map as the implicit estimator's)."""
    ns = shape.n_params
    th = ca.SX.sym("theta", ns + len(PHYS_NAMES))
    L, m0 = ca.SX.sym("L"), ca.SX.sym("m0")
    V = shape.vertices(th[:ns], L)
    area, _, J = polygon_area_centroid_j(V)
    mass = m0 * ca.exp(th[ns])
    inertia = mass * (J / area) * ca.exp(th[ns + 1])
    return ca.Function("phys", [th, L, m0], [V, mass, inertia, th[ns + 2], th[ns + 3]],
                       ["theta", "L", "m0"], ["V", "mass", "inertia", "mu_g", "mu_f"])


def friction_force(mu, f_n, s, inv_m_t, h):
    """Magnitude (along the slip s) of the regularized Coulomb force mu f_n s / sqrt(s² + eps²),
    eps = FRICTION_REGULARIZATION_SPEED, applied linearly implicitly: divided by 1 + h inv_m_t d/ds(force), so
    that one step cannot reverse the slip however small eps is (an explicit step needs
    eps >~ h mu g (1 + lever terms), several cm/s at 1 ms, and then underestimates
    friction in slow pushes).  inv_m_t : 1/kg, inverse effective mass along the tangent."""
    eps = FRICTION_REGULARIZATION_SPEED
    den = smooth_abs(s, eps)
    f = mu * f_n * s / den
    slope = mu * f_n * eps ** 2 / den ** 3
    return f / (1 + h * inv_m_t * slope)


def finger_geometry(q, V, c_f, radius, sd_fun):
    """Gap phi_f (m), outward object normal n (2, world) and lever r (2, world, from the
    COM to the closest surface point) of a fingertip centre c_f (2, world)."""
    R = rot2(q[2])
    sd, n_body = sd_fun(R.T @ (c_f - q[0:2]), V)
    n_w = R @ n_body
    return sd - radius, n_w, c_f - q[0:2] - sd * n_w


def normal_force(k, c, delta, u, inv_m_n, a_close, h, f_eps):
    """Penalty normal force magnitude (N) of one contact, applied linearly implicitly.

    The explicit law f(delta, u) = max~(k softplus(delta) + c u gate(delta), 0) (delta:
    penetration, m; u: its rate, m/s) is replaced by its value at the end of the substep,
    linearized: with u' = u + h a_close - h inv_m_n f_app and delta' = delta + h u',

        f_app = (f + h f_delta (u + h a_close) + h f_u a_close) / (1 + h inv_m_n (h f_delta + f_u)),

    so stiff springs and dampers stay stable at a 1 ms substep, and at rest under
    gravity (a_close: gravity's acceleration along the closing direction) f_app = f
    exactly.  inv_m_n : 1/kg, inverse effective mass along the normal."""
    w = CONTACT_SMOOTH
    sg = sigmoid(delta, w)
    x = k * softplus(delta, w) + c * u * sg
    f = smooth_pos(x, f_eps)
    dpos = 0.5 * (1 + x / ca.sqrt(x * x + f_eps * f_eps))
    f_d = dpos * (k * sg + c * u * sg * (1 - sg) / w)
    f_u = dpos * c * sg
    num = f + h * f_d * (u + h * a_close) + h * f_u * a_close
    return smooth_pos(num, f_eps) / (1 + h * inv_m_n * (h * f_d + f_u))


def contact_forces(q, v, V, mass, inertia, mu_g, mu_f, c_f, v_f, radius, n_g, h_g, g_vec, h, sd_fun):
    """Penalty contact forces of the model (module docstring) at state (q, v).

    c_f, v_f : (2, F) fingertip centres (m) and velocities (m/s), world;
    radius : (F,) m;  n_g : (2,) ground normal;  h_g : ground height, m;  g_vec : (2,)
    gravity, m/s² world;  h : substep, s.  Stiffnesses are in units of the object's
    standard weight (m·STANDARD_GRAVITY).
    Returns (generalized force (3,), finger forces on the object (2, F) N,
    ground normal forces (K,) N, ground tangential forces (K,) N).
    """
    K = V.shape[0]
    F = c_f.shape[1]
    t_g = perp(n_g)
    k_g = mass * STANDARD_GRAVITY / (2 * GROUND_SINK)
    c_g = 2 * GROUND_DAMPING_RATIO * ca.sqrt(k_g * mass / 2)  # two vertices share the weight
    k_f = mass * STANDARD_GRAVITY / FINGER_SINK
    c_fd = 2 * FINGER_DAMPING_RATIO * ca.sqrt(k_f * mass)
    f_eps = FORCE_SMOOTH * mass * STANDARD_GRAVITY
    gen = ca.SX.zeros(3)
    phi, slip, levers = ground_contacts(q, v, V, n_g, h_g)
    fn_g, ft_g = [], []
    for k in range(K):
        r = levers[k]
        u = -ca.dot(n_g, point_velocity(v, r))
        fn = normal_force(k_g, c_g, GROUND_OFFSET - phi[k], u, cross2(r, n_g) ** 2 / inertia + 1 / mass,
                          -ca.dot(n_g, g_vec), h, f_eps)
        ft = -friction_force(mu_g, fn, slip[k], cross2(r, t_g) ** 2 / inertia + 1 / mass, h)
        gen += generalized_impulse(r, fn * n_g + ft * t_g)
        fn_g.append(fn)
        ft_g.append(ft)
    fingers = []
    for f in range(F):
        phi_f, n_w, lever = finger_geometry(q, V, c_f[:, f], radius[f], sd_fun)
        t_w = perp(n_w)
        rel = v_f[:, f] - point_velocity(v, lever)  # fingertip relative to the surface point
        fn = normal_force(k_f, c_fd, -phi_f, -ca.dot(n_w, rel), cross2(lever, n_w) ** 2 / inertia + 1 / mass,
                          ca.dot(n_w, g_vec), h, f_eps)
        s = ca.dot(t_w, rel)
        ft = friction_force(mu_f, fn, s, cross2(lever, t_w) ** 2 / inertia + 1 / mass, h)
        force = -fn * n_w + ft * t_w
        gen += generalized_impulse(lever, force)
        fingers.append(force)
    fingers = ca.horzcat(*fingers) if F else ca.SX.zeros(2, 0)
    return gen, fingers, ca.vertcat(*fn_g), ca.vertcat(*ft_g)


#: per-run environment vector: dt, ground normal (2), ground height, fingertip radii (F)
def env_vector(run: Run) -> np.ndarray:
    return np.concatenate([[run.dt], run.up, [run.ground_height], np.asarray(run.gravity, float),
                           run.finger_radius if run.n_fingers else np.zeros(0)])


def step_function(K: int, F: int, substeps: int = SUBSTEPS) -> ca.Function:
    """SX Function of one sample interval (t-1, t]:

    (x (6) [q, v] SI, u (6F) [c_prev (2F), c_next (2F), v_f (2F)], phys (2K+4) [vec V, m,
    I, mu_g, mu_f], env (6+F) [dt, ground normal (2), ground height, gravity (2), radii])
    -> (x_next (6), mean finger force on the object (2F) N,
    ground normal impulses (K) N·s, ground tangential impulses (K) N·s).
    Substeps: semi-implicit Euler, the fingertip centre moving linearly from c_prev to c_next.
    """
    x = ca.SX.sym("x", 6)
    u = ca.SX.sym("u", 6 * F)
    phys = ca.SX.sym("phys", 2 * K + 4)
    env = ca.SX.sym("env", 6 + F)
    V = ca.reshape(phys[: 2 * K], K, 2)
    mass, inertia, mu_g, mu_f = (phys[2 * K + i] for i in range(4))
    dt, n_g, h_g, g_vec, radius = env[0], env[1:3], env[3], env[4:6], env[6:]
    h = dt / substeps
    c_prev = ca.reshape(u[0: 2 * F], 2, F)
    c_next = ca.reshape(u[2 * F: 4 * F], 2, F)
    v_f = ca.reshape(u[4 * F: 6 * F], 2, F)
    sd_fun = polygon_sd_and_normal_function(K)
    Minv = 1 / mass_matrix_diag(mass, inertia)
    grav = ca.vertcat(g_vec, 0)
    q, v = x[0:3], x[3:6]
    f_sum = ca.SX.zeros(2, F)
    in_sum = ca.SX.zeros(K)
    it_sum = ca.SX.zeros(K)
    for j in range(substeps):
        c = c_prev + (j + 1) / substeps * (c_next - c_prev)
        gen, ff, fn, ft = contact_forces(q, v, V, mass, inertia, mu_g, mu_f, c, v_f, radius, n_g, h_g, g_vec, h,
                                         sd_fun)
        v = v + h * (grav + Minv * gen)
        q = q + h * v
        f_sum += ff
        in_sum += h * fn
        it_sum += h * ft
    return ca.Function(f"shoot_step_K{K}_F{F}", [x, u, phys, env],
                       [ca.vertcat(q, v), ca.vec(f_sum) / substeps, in_sum, it_sum],
                       ["x", "u", "phys", "env"], ["x_next", "force", "imp_ground_n", "imp_ground_t"])


def data_rows(F: int) -> int:
    """Rows of the per-sample data matrix: c (2F), v_f (2F), contact (F), n_meas (2F),
    F_meas (2F), w_force (F), w_tact (F), q_obs (3), w_pose (1)."""
    return 11 * F + 4


#: half-width (samples) of the local least-squares line through the measured fingertip
#: positions that drives the kinematic fingertip: 0.1 mm position noise becomes ~0.045 mm
#: (and k_f times that in force); at a sudden stop the line lags by ~0.6 v·dt (0.25 mm at
#: 4 cm/s, outward)
FINGER_SMOOTH_HALF_WIDTH = 2


def finger_track(run: Run):
    """(T, F, 2) smoothed fingertip positions (m) and velocities (m/s): value and slope of a
    least-squares line through the samples within ±FINGER_SMOOTH_HALF_WIDTH (shorter
    windows at the ends)."""
    fp = run.finger_position
    T = fp.shape[0]
    hw = FINGER_SMOOTH_HALF_WIDTH
    pos, vel = fp.copy(), np.zeros_like(fp)
    for t in range(T):
        a, b = max(0, t - hw), min(T, t + hw + 1)
        if b - a < 2:
            continue
        tt = np.arange(a, b) - t
        tm = tt.mean()
        mean = fp[a:b].mean(0)
        slope = np.tensordot(tt - tm, fp[a:b] - mean, axes=(0, 0)) / np.sum((tt - tm) ** 2)
        pos[t] = mean - slope * tm
        vel[t] = slope / run.dt
    return pos, vel


def data_matrix(run: Run) -> np.ndarray:
    """(data_rows(F), T) per-sample data of a run (see :func:`data_rows`): the smoothed
    fingertip track (:func:`finger_track`), with column t of v_f the fingertip velocity
    over the interval (t-1, t] (mean of the slopes at its ends)."""
    T, F = run.n_samples, run.n_fingers
    rows = []
    if F:
        fp, vf = finger_track(run)
        valid = np.ones(T) if run.missing is None else 1.0 - run.missing.astype(float)
        vf_int = np.concatenate([vf[:1], 0.5 * (vf[1:] + vf[:-1])], axis=0)
        contact = run.contact.astype(float) * valid[:, None]
        n_meas = np.where(np.isfinite(run.normal), run.normal, 0.0)
        force = run.force if run.force is not None else np.zeros_like(fp)
        w_force = np.zeros((T, F)) if run.force is None else np.repeat(valid[:, None], F, 1)
        w_force[0] = 0.0  # sample 0 closes no interval
        w_tact = np.repeat(valid[:, None], F, 1)
        rows += [fp.reshape(T, -1), vf_int.reshape(T, -1), contact, n_meas.reshape(T, -1), force.reshape(T, -1),
                 w_force, w_tact]
    rows += list(pose_observation_columns(run))
    D = np.concatenate(rows, axis=1).T
    assert D.shape[0] == data_rows(F)
    return D


def measurement_function(K: int, F: int) -> ca.Function:
    """SX Function of one sample: (q (3), phys, d (data column), f_sim (2F), sig (5)
    [sigma_F, sigma_n, sigma_gap, sigma_pos, sigma_ang], env) -> whitened residuals
    force (2F), normal (2F), contact (F), pose (3), the gaps phi_f (F) m and the model's
    contact normals (2F, world)."""
    q = ca.SX.sym("q", 3)
    phys = ca.SX.sym("phys", 2 * K + 4)
    d = ca.SX.sym("d", data_rows(F))
    f_sim = ca.SX.sym("f_sim", 2 * F)
    sig = ca.SX.sym("sig", 5)
    env = ca.SX.sym("env", 6 + F)
    V = ca.reshape(phys[: 2 * K], K, 2)
    radius = env[6:]
    take = consecutive_slices(d)

    c_f = ca.reshape(take(2 * F), 2, F)
    take(2 * F)  # fingertip velocity: the dynamics only
    contact = take(F)
    n_meas = ca.reshape(take(2 * F), 2, F)
    F_meas = ca.reshape(take(2 * F), 2, F)
    w_force, w_tact = take(F), take(F)
    q_obs, w_pose = take(3), take(1)
    sd_fun = polygon_sd_and_normal_function(K)
    r_force, r_normal, r_contact, gaps, normals = [], [], [], [], []
    for f in range(F):
        phi_f, n_w, _ = finger_geometry(q, V, c_f[:, f], radius[f], sd_fun)
        gaps.append(phi_f)
        normals.append(n_w)
        r_force.append(w_force[f] * (f_sim[2 * f: 2 * f + 2] - F_meas[:, f]) / sig[0])
        r_normal.append(w_tact[f] * contact[f] * (n_meas[:, f] - n_w) / sig[1])
        r_contact.append(w_tact[f] * (contact[f] * phi_f + (1 - contact[f]) * smooth_neg(phi_f, sig[2])) / sig[2])
    r_pose = w_pose * (q - q_obs) / ca.vertcat(sig[3], sig[3], sig[4])

    def cat(parts):
        return ca.vertcat(*parts) if parts else ca.SX.zeros(0)

    return ca.Function(f"shoot_meas_K{K}_F{F}", [q, phys, d, f_sim, sig, env],
                       [cat(r_force), cat(r_normal), cat(r_contact), r_pose, cat(gaps), cat(normals)],
                       ["q", "phys", "d", "f_sim", "sig", "env"],
                       ["force", "normal", "contact", "pose", "gap", "n_model"])


def rest_pose(x0, angle0, V, n_g, h_g):
    """Pose (3,) at rest on the ground: position x0 (m) along the ground tangent, the
    lowest vertex (soft minimum, :data:`REST_SOFTMIN`) on the ground plane."""
    R = rot2(angle0)
    heights = [ca.dot(n_g, R @ V[k, :].T) for k in range(V.shape[0])]
    hs = ca.vertcat(*heights)
    lo = ca.mmin(hs)
    softmin = lo - REST_SOFTMIN * ca.log(ca.sum1(ca.exp(-(hs - lo) / REST_SOFTMIN)))
    p = x0 * perp(n_g) + (h_g - softmin) * n_g
    return ca.vertcat(p, angle0)


# ------------------------------------------------------------------------------------
# the NLP


@dataclass(frozen=True)
class Structure:
    T: int
    F: int


class ShootingProblem:
    """The shooting NLP for runs of the given structures (built once, data as parameters).

    z = [theta (n_theta), per run (x0 / L, angle0)];  p = [L, m0, prior (N_PRIOR_FIXED), s_ref (n_s),
    weights (4), per run: env (4+F), sig (5), data (data_rows(F) · T)].

    Attributes: ``loss`` Function (z, p) -> objective; ``nlp`` dict for nlpsol;
    ``outputs`` Function (z, p) -> per run (Q (3, T), V (3, T), finger force (2F, T),
    ground impulses (K, T) x 2, residuals force, normal, contact, pose).
    """

    def __init__(self, shape: Shape, structures, substeps: int = SUBSTEPS):
        self.shape = shape
        self.structures = [Structure(s.T, s.F) for s in structures]
        self.substeps = substeps
        self.K = shape.n_vertices
        self.n_shape = shape.n_params
        self.n_theta = self.n_shape + len(PHYS_NAMES)
        self.n_z = self.n_theta + 2 * len(self.structures)
        self._build()

    def run_offset(self, i):
        return self.n_theta + 2 * i

    def _build(self):
        K, ns = self.K, self.n_shape
        z = ca.MX.sym("z", self.n_z)
        theta = z[: self.n_theta]
        L, m0 = ca.MX.sym("L"), ca.MX.sym("m0")
        prior = ca.MX.sym("prior", N_PRIOR_FIXED)  # tacest.model.priors.PRIOR_HEAD
        s_ref = ca.MX.sym("s_ref", ns)
        w = ca.MX.sym("w", len(TERMS))
        p_parts = [L, m0, prior, s_ref, w]
        self.phys = phys_function(self.shape)
        V, mass, inertia, mu_g, mu_f = self.phys(theta, L, m0)
        phys_vec = ca.vertcat(ca.vec(V), mass, inertia, mu_g, mu_f)
        outs = []
        r_parts = []  # whitened residuals, sqrt(weight) applied: loss = 0.5 ||r||² + prior
        self.p_run_offsets = []
        n_p = 2 + N_PRIOR_FIXED + ns + len(TERMS)
        for i, st in enumerate(self.structures):
            T, F = st.T, st.F
            env = ca.MX.sym("env", 6 + F)
            sig = ca.MX.sym("sig", 5)
            D = ca.MX.sym("D", data_rows(F), T)
            self.p_run_offsets.append(n_p)
            n_p += 6 + F + 5 + data_rows(F) * T
            p_parts += [env, sig, ca.vec(D)]
            a = self.run_offset(i)
            q0 = rest_pose(z[a] * L, z[a + 1], V, env[1:3], env[3])
            x0 = ca.vertcat(q0, ca.MX.zeros(3))
            C = D[0: 2 * F, :]
            U = ca.vertcat(C[:, :-1], C[:, 1:], D[2 * F: 4 * F, 1:])
            step = step_function(K, F, self.substeps)
            X, Fm, IGn, IGt = step.mapaccum(f"shoot_run{i}", T - 1)(x0, U, phys_vec, env)
            Q = ca.horzcat(q0, X[0:3, :])
            Vel = ca.horzcat(ca.MX.zeros(3, 1), X[3:6, :])
            Fsim = ca.horzcat(ca.MX.zeros(2 * F, 1), Fm)
            meas = measurement_function(K, F).map(T)
            res = meas(Q, phys_vec, D, Fsim, sig, env)
            r_parts += [ca.sqrt(w[k]) * ca.vec(res[k]) for k in range(len(TERMS))]
            outs += [Q, Vel, Fsim, ca.horzcat(ca.MX.zeros(K, 1), IGn), ca.horzcat(ca.MX.zeros(K, 1), IGt),
                     *res]
            assert len(outs) == len(OUTPUT_NAMES) * (i + 1)
        self.n_p = n_p
        p = ca.vertcat(*p_parts)
        assert p.shape[0] == n_p
        r = ca.vertcat(*r_parts)
        # weak priors of the implicit estimator (theta only)
        th = ca.SX.sym("theta", self.n_theta)
        pr_sx = ca.SX.sym("prior", N_PRIOR_FIXED)
        sref_sx = ca.SX.sym("s_ref", ns)
        lm, lI, mg, mf = (th[ns + i] for i in range(4))
        r_prior_sx = parameter_prior_residual(lm, lI, mg, mf, th[:ns] - sref_sx, pr_sx)
        f_prior_sx = 0.5 * ca.sumsqr(r_prior_sx)
        sc = self.shape.constraints(th[:ns])
        g_sx = ca.vertcat(*sc) if sc else ca.SX.zeros(0)
        lam_g_sx = ca.SX.sym("lam_g", g_sx.shape[0])
        lam_f_sx = ca.SX.sym("lam_f")
        theta_fun = ca.Function("shoot_theta", [th, pr_sx, sref_sx, lam_f_sx, lam_g_sx],
                                [f_prior_sx, g_sx,
                                 ca.densify(ca.hessian(lam_f_sx * f_prior_sx + ca.dot(lam_g_sx, g_sx), th)[0])])
        f_prior, g, _ = theta_fun(theta, prior, s_ref, 1.0, ca.DM.zeros(g_sx.shape[0]))
        f = 0.5 * ca.sumsqr(r) + f_prior
        self.lbg = np.zeros(g.shape[0])
        self.ubg = np.full(g.shape[0], np.inf)
        self.nlp = {"x": z, "p": p, "f": f, "g": g}
        self.loss = ca.Function("shoot_loss", [z, p], [f], ["z", "p"], ["f"])
        self.loss_grad = ca.Function("shoot_loss_grad", [z, p], [f, ca.gradient(f, z)], ["z", "p"], ["f", "grad"])
        self.outputs = ca.Function("shoot_outputs", [z, p], outs)
        J = ca.jacobian(r, z)
        self.residual_jacobian = ca.Function("shoot_rjac", [z, p], [r, J])
        # Gauss–Newton model of the Lagrangian's Hessian (nlpsol's hess_lag): JᵀJ for the
        # squared residuals, exact second derivatives of the priors and shape constraints
        lam_f = ca.MX.sym("lam_f")
        lam_g = ca.MX.sym("lam_g", g.shape[0])
        _, _, H_theta = theta_fun(theta, prior, s_ref, lam_f, lam_g)
        H = lam_f * ca.mtimes(J.T, J)
        H = H + ca.diagcat(H_theta, ca.MX.zeros(self.n_z - self.n_theta, self.n_z - self.n_theta))
        self.hess_lag = {"gauss-newton": ca.Function("nlp_hess_l", [z, p, lam_f, lam_g], [ca.triu(ca.densify(H))],
                                                     ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])}
        #: the priors' Gauss–Newton Hessian (JᵀJ of their residuals, scaled theta), for the
        #: posterior std
        J_prior = ca.jacobian(r_prior_sx, th)
        self.prior_hessian = ca.Function("shoot_prior_hess", [th, pr_sx, sref_sx],
                                         [ca.densify(ca.mtimes(J_prior.T, J_prior))])
        self.g = g
        #: IPOPT options of the shooting solve on top of solver.ipopt_options: one stage from
        #: a start chosen by the loss itself, not a consistent point of the implicit problem,
        #: so IPOPT's own defaults for the barrier, the bound push and the acceptable point
        self.nlpsol_options = {"ipopt": {"mu_init": 0.1, "bound_push": 0.01, "bound_frac": 0.01,
                                         "warm_start_init_point": "no", "acceptable_constr_viol_tol": 0.01,
                                         "acceptable_compl_inf_tol": 0.01, "acceptable_obj_change_tol": 1e-6}}

    def run_outputs(self, z, p, runs):
        """Per run: dict with pose (T, 3), velocity (T, 3), finger_force (T, F, 2) N,
        ground_normal and ground_tangent impulses (T, K) N·s, residuals {term: (n, T)}
        (whitened, weights not applied), gap (T, F) m, n_model (T, F, 2)."""
        out = self.outputs(z, p)
        n = len(OUTPUT_NAMES)
        result = []
        for i, run in enumerate(runs):
            o = dict(zip(OUTPUT_NAMES, (np.asarray(a) for a in out[n * i: n * (i + 1)])))
            T, F = run.n_samples, run.n_fingers
            result.append({
                "pose": o["Q"].T, "velocity": o["V"].T, "finger_force": o["F_sim"].T.reshape(T, F, 2),
                "ground_normal": o["imp_ground_n"].T, "ground_tangent": o["imp_ground_t"].T,
                "residuals": {t: o[t] for t in TERMS}, "gap": o["gap"].T.reshape(T, F),
                "n_model": o["n_model"].T.reshape(T, F, 2),
            })
        return result

    # --------------------------------------------------------------------------------
    def parameters(self, runs, scales: Scales, config: EstimatorConfig, s_ref) -> np.ndarray:
        pr, nz, wt = config.prior, config.noise, config.weights
        parts = [np.array([scales.L, scales.m0]),
                 prior_head(pr),
                 np.asarray(s_ref, float), np.array([getattr(wt, t) for t in TERMS], float)]
        for run, st in zip(runs, self.structures):
            if run.n_samples != st.T or run.n_fingers != st.F:
                raise TacestError("internal: run does not match the shooting problem's structure")
            parts += [env_vector(run), np.array([nz.force, nz.normal, nz.contact_gap, run.sigma_position,
                                                 run.sigma_angle]),
                      data_matrix(run).T.reshape(-1)]  # column-major vec of (rows, T)
        p = np.concatenate(parts)
        assert p.shape[0] == self.n_p
        return p


def get_problem(shape: Shape, structures, substeps: int = SUBSTEPS) -> ShootingProblem:
    key = (shape.name, tuple((s.T, s.F) for s in structures), substeps)
    return _CACHE.get(key, lambda: ShootingProblem(shape, structures, substeps))


# ------------------------------------------------------------------------------------
# the estimator


class ShootingEstimator:
    """Set up, start and solve the shooting problem for runs of one object."""

    def __init__(self, runs: list[Run], shape_spec: str = "box", config: EstimatorConfig | None = None,
                 substeps: int = SUBSTEPS, hessian: str = DEFAULT_HESSIAN):
        check_runs(runs)
        if hessian not in HESSIAN_MODES:
            raise TacestError(f"shooting: unknown Hessian model {hessian!r}; use {' or '.join(HESSIAN_MODES)}")
        self.hessian = hessian
        self.runs = runs
        self.config = config or EstimatorConfig()
        self.shape = make_shape(shape_spec, dim=2)
        self.scales = choose_scales(runs, self.config)
        self.has_force = force_in_contact(runs)  # a force measured in contact: the mass is told
        size_bounds = [float(r.prior["size_bound"]) for r in runs if "size_bound" in r.prior]
        self.size_bound = min(size_bounds) if size_bounds else self.config.prior.size_bound
        t0 = time.perf_counter()
        self.problem = get_problem(self.shape, [Structure(r.n_samples, r.n_fingers) for r in runs], substeps)
        self.build_time = time.perf_counter() - t0
        self.z0 = self.initial_guess()
        self.p_sref = self.z0[: self.shape.n_params].copy()
        self.p = self.problem.parameters(runs, self.scales, self.config, self.p_sref)

    def initial_guess(self) -> np.ndarray:
        """Start of the solve: the implicit estimator's kind of start (initial_extents,
        initial_pose: the object at rest on the ground, its side at the first side touch),
        with the extents chosen on :data:`START_GRID` by the shooting loss itself; log
        mass and log inertia ratio 0; friction 0.5, 0.5.

        Choosing the extents matters more here than for the implicit estimator: a shape
        too large collides early, and the simulated impacts make the loss rugged, whereas
        a shape too small misses touches and the contact-gap residual pulls its faces
        out smoothly."""
        L = self.scales.L
        w, h = initial_extents(self.runs, L)
        pr = self.problem
        cands = [(w, h)] + [(fw * L, fh * L) for fw in START_GRID for fh in START_GRID]
        best, best_f = None, np.inf
        for cw, ch in cands:
            z = self._start_vector(cw, ch)
            f = float(pr.loss(z, self.problem.parameters(self.runs, self.scales, self.config,
                                                         z[: pr.n_shape])))
            if np.isfinite(f) and f < best_f:
                best, best_f = z, f
        return best if best is not None else self._start_vector(w, h)

    def _start_vector(self, width, height):
        L, pr = self.scales.L, self.problem
        s0 = self.shape.initial(width / L, height / L)
        V = numeric_vertices(self.shape, s0, L)
        ext = V.max(0) - V.min(0)
        z0 = np.zeros(pr.n_z)
        z0[: pr.n_shape] = s0
        z0[pr.n_shape: pr.n_theta] = [0.0, 0.0, 0.5, 0.5]
        for i, run in enumerate(self.runs):
            pose0 = initial_pose(run, float(ext[0]), float(ext[1]))
            a = pr.run_offset(i)
            z0[a] = float(pose0[:2] @ np.array([run.up[1], -run.up[0]])) / L
            z0[a + 1] = float(pose0[2])
        return z0

    def bounds(self):
        pr, ns = self.problem, self.problem.n_shape
        lbx = np.full(pr.n_z, -np.inf)
        ubx = np.full(pr.n_z, np.inf)
        lbx[:ns], ubx[:ns] = self.shape.bounds(self.size_bound / self.scales.L)
        lbx[ns:ns + 4] = [LOG_MASS_BOUNDS[0], LOG_INERTIA_BOUNDS[0], FRICTION_BOUNDS[0], FRICTION_BOUNDS[0]]
        ubx[ns:ns + 4] = [LOG_MASS_BOUNDS[1], LOG_INERTIA_BOUNDS[1], FRICTION_BOUNDS[1], FRICTION_BOUNDS[1]]
        if not self.has_force:  # every simulated force scales with m: the mass is not identifiable
            lbx[ns] = ubx[ns] = self.z0[ns]
        if not any(r.pose_obs is not None for r in self.runs):
            if self.shape.name == "box":
                # a box at rest lies on a face: its start angle is the start's multiple of
                # 90° (its extents swap for the others); a free angle only opens local minima
                # where the box starts on a corner and tips over
                fixed = range(len(self.runs))
            else:
                # gauge: a free polygon can rotate in its body frame; fix run 0's start angle
                fixed = [0]
            for i in fixed:
                a = pr.run_offset(i) + 1
                lbx[a] = ubx[a] = self.z0[a]
        return lbx, ubx

    def solve(self):
        """One IPOPT solve (solver.run_stages, a single stage with the final budget)."""
        cfg = self.config.solver
        lbx, ubx = self.bounds()
        stage = Stage("shooting", 0.0, 0.0, 1.0, impulses_only=False, hessian=self.hessian, max_iter=cfg.max_iter,
                      final=True)
        out = run_stages(BuiltSolver(self.problem, self.config), np.clip(self.z0, lbx, ubx), [stage],
                         lambda st, retry=False: self.p, lambda st, z: (lbx, ubx))
        self.z = out.z
        self.lbx, self.ubx = lbx, ubx
        return out

    # --------------------------------------------------------------------------------
    def physical(self, z):
        V, mass, inertia, mu_g, mu_f = self.problem.phys(z[: self.problem.n_theta], self.scales.L, self.scales.m0)
        return np.array(V), float(mass), float(inertia), float(mu_g), float(mu_f)

    def run_outputs(self, z):
        """Per run: dict with pose (T, 3), velocity (T, 3), finger forces (T, F, 2) N,
        ground impulses (T, K) x 2 N·s, residual arrays {term: (n, T)}, gaps (T, F) m."""
        return self.problem.run_outputs(z, self.p, self.runs)

    def information(self, z) -> Information:
        """Gauss–Newton information JᵀJ of the parameters (physical units: lengths m,
        mass kg, log inertia ratio, frictions), the start poses profiled out (Schur
        complement); held variables get no row (uncertainty.std_of)."""
        from tacest.estimation.uncertainty import information_names_2d, schur_information
        import scipy.sparse as sps

        pr, L = self.problem, self.scales.L
        _, J = pr.residual_jacobian(z, self.p)
        J = np.asarray(J)
        free = self.lbx < self.ubx
        # d(scaled variable)/d(physical parameter)
        scale = np.ones(pr.n_theta)
        scale[: pr.n_shape] = 1.0 / L
        mass = float(self.scales.m0 * np.exp(z[pr.n_shape]))
        scale[pr.n_shape] = 1.0 / mass
        nu = pr.n_theta + np.flatnonzero(free[pr.n_theta:])
        I_s = schur_information(sps.csc_matrix(J[:, : pr.n_theta]), sps.csc_matrix(J[:, nu]))
        I_phys = I_s * np.outer(scale, scale)
        held_rows = ~free[: pr.n_theta]
        I_phys[held_rows, :] = 0.0
        I_phys[:, held_rows] = 0.0
        names = information_names_2d(SimpleNamespace(shape=self.shape, effect_params=()))[: pr.n_theta]
        prior = prior_head(self.config.prior)
        H = np.asarray(pr.prior_hessian(z[: pr.n_theta], prior, self.p_sref), float)
        std_data, _ = std_of(I_phys, free[: pr.n_theta], names)
        std, _ = std_of(I_phys + H * np.outer(scale, scale), free[: pr.n_theta], names)
        return Information(matrix=I_phys, names=names, std_data=std_data, std=std)


def estimate_shooting(runs: list[Run], shape_spec: str = "box", config: EstimatorConfig | None = None,
                      hessian: str = DEFAULT_HESSIAN) -> Estimate:
    """Shooting-baseline estimate of one object from its runs (2-D; see the module docstring).

    Raises TacestError for 3-D runs or bad input, SolveFailedError when IPOPT does not
    return a solution (Maximum_Iterations_Exceeded included).
    """
    from tacest.io.run import run_sha256

    t_start = time.perf_counter()
    est = ShootingEstimator(runs, shape_spec, config, hessian=hessian)
    log.info(f"built shooting NLP: {est.problem.n_z} variables, {sum(s.T for s in est.problem.structures)} samples "
             f"x {est.problem.substeps} substeps ({est.build_time:.1f} s)")
    out = est.solve()
    z = out.z
    V, mass, inertia, mu_g, mu_f = est.physical(z)
    run_ests = []
    for run, o in zip(runs, est.run_outputs(z)):
        res = {t: 0.5 * np.sum(o["residuals"][t] ** 2, axis=0) for t in TERMS}
        imp = {"ground_normal": o["ground_normal"], "ground_tangent": o["ground_tangent"]}
        for f in range(run.n_fingers):
            imp[f"finger_{f}"] = o["finger_force"][:, f] * run.dt
        src = run.filename or ""
        run_ests.append(RunEstimate(pose=o["pose"], velocity=o["velocity"], impulses=imp, residuals=res,
                                    source_file=src, source_sha256=run_sha256(run)))
    try:
        info = est.information(z)
    except (np.linalg.LinAlgError, RuntimeError):
        info = None
    params = {"mass": mass, "inertia": inertia, "friction_ground": mu_g, "friction_finger": mu_f}
    facts = FitFacts(has_force=est.has_force, has_fingers=any(r.n_fingers for r in runs), shape_seen=shape_seen(runs))
    return assemble(2, est.shape.name, V, params, run_ests, out, time.perf_counter() - t_start, info, facts,
                    est.config.to_dict(), "shooting",
                    extra={"length_scale": est.scales.L, "mass_scale": est.scales.m0,
                           "substeps": est.problem.substeps, "ground_sink": GROUND_SINK, "finger_sink": FINGER_SINK,
                           "hessian": est.hessian})


# ------------------------------------------------------------------------------------
# forward simulation of a run (synthetic data, tests)

#: N, a simulated interval counts as contact where the mean finger force exceeds this
CONTACT_FORCE_THRESHOLD = 1e-2


def simulate_run(template: Run, shape_spec: str, s, mass: float, friction_ground: float, friction_finger: float,
                 start: list, log_inertia_ratio: float = 0.0, length_scale: float = 0.1,
                 substeps: int = SUBSTEPS) -> Run:
    """Noiseless run of the shooting model: the fingertips of ``template`` (positions,
    radii, dt, ground) push the object, and contact, normal and force are what the
    model says (contact where the mean finger force exceeds CONTACT_FORCE_THRESHOLD).

    s : shape parameters in units of ``length_scale`` (box: [w, h] / L);
    start : [x0 m along the ground, angle0 rad] (the object starts at rest on the ground).
    Returns a copy of ``template`` with /tactile and /truth filled (filename None).
    """
    from tacest.io.run import Truth

    shape = make_shape(shape_spec, dim=2)
    T, F = template.n_samples, template.n_fingers
    pr = get_problem(shape, [Structure(T, F)], substeps)
    z = np.concatenate([np.asarray(s, float), [math.log(mass / 1.0), log_inertia_ratio, friction_ground,
                                               friction_finger, start[0] / length_scale, start[1]]])
    blank = template.replace(contact=np.zeros((T, F), np.uint8), normal=np.full((T, F, 2), np.nan),
                             force=np.zeros((T, F, 2)), pose_obs=None, truth=None, filename=None)
    cfg = EstimatorConfig()
    p = pr.parameters([blank], Scales(L=length_scale, m0=1.0), cfg, z[: shape.n_params])
    o = pr.run_outputs(z, p, [blank])[0]
    pose, force = o["pose"], o["finger_force"]
    V, m, inertia, mu_g, mu_f = (np.array(a) if k == 0 else float(a)
                                 for k, a in enumerate(pr.phys(z[: pr.n_theta], length_scale, 1.0)))
    contact = (np.linalg.norm(force, axis=-1) > CONTACT_FORCE_THRESHOLD).astype(np.uint8)
    contact[0] = 0
    n = o["n_model"]
    normal = np.where(contact[:, :, None] == 1, n / np.linalg.norm(n, axis=-1, keepdims=True), np.nan)
    force = force * contact[:, :, None]
    truth = Truth(pose=pose, vertices=V, mass=m, inertia=inertia, friction_ground=mu_g, friction_finger=mu_f)
    return blank.replace(contact=contact, normal=normal, force=force, truth=truth, source="shooting-sim")
