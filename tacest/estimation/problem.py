"""The physics-constrained maximum-likelihood problem as ONE CasADi NLP (2-D).

Decision variables (all scaled to O(1); see :class:`Scales`):

- shared parameters ``theta`` = [shape s (n_s), log(m/m0), log(I / I_uniform), mu_ground, mu_finger]
- lifted physical quantities ``phys`` = [V / L (2K), m / m0, I / (m0 L²), mu_ground,
  mu_finger] with the equality constraint phys = phys(theta)
- per run i, per sample t: pose q[t] (3), velocity v[t] (3); per interval (t-1, t]:
  ground impulses [lambda_n (K), lambda_t (K)] at each shape vertex and, per finger,
  its impulse on the object as a world-frame vector [x, y] (all scaled by m0 g dt);
  with soft_contact, per sample: the sink of the ground's plate (units of PLATE_UNIT·L).

Data (recorded streams, noise levels, homotopy settings) are CasADi *parameters*, so the
NLP is built once per structure (shape, run lengths, fingers) and re-solved with new data.

Loss (whitened residuals, names as written into estimate files; every term is squared,
so that a Gauss–Newton Hessian models the whole loss)::

    force          (lambda_f / dt - F_meas) / sigma_F                 where a force stream exists
    normal         c (n_meas - n_model) / sigma_n
    contact        c phi_f / sigma_gap  +  (1 - c) min~(phi_f) (fingertip gap / no overlap,
                   at the interval's end)
    pose           (q - q_obs) / sigma_pose                           where observed
    dynamics       eq. D1 residual M(v - v_prev) - dt f_ext - Jᵀλ, whitened as process
                   noise on the velocity change of a reference body (m_ref, I_ref)
    penetration    min~(phi_ground) with tolerance sigma_pen
    cone           min~(mu lambda_n ∓ lambda_t) / sigma_comp, ground vertices and fingertips (eq. C2)
                   (min~ is a one-sided smooth penalty, ≈ 0 at the limit: see one_sided)
    complementarity  lambda_n psi / sigma_comp (eq. C1, relaxed): psi = x / (x + 1) with
                   x = phi⁺ + vn⁺, phi⁺ a softplus of (phi / sigma_gap - 1) (gap beyond one
                   tolerance), vn⁺ one of (vn / sigma_v - 1) (the vertex separating faster than
                   one process sigma: velocity-level complementarity); psi saturates at 1 so
                   that a vertex far above the ground costs lambda_n, not lambda_n · phi (the
                   unbounded bilinear form makes IPOPT's Hessian badly indefinite); with
                   noise.complementarity_reach > 0, + lambda_n max~(phi - reach, 0) / reach:
                   an impulse far above the ground grows with the height (off by default)
    dissipation    (mu lambda_n |s| + lambda_t s) / sigma_diss (eq. C3, maximal dissipation:
                   0 when friction opposes the slip s at the cone's limit, or when sticking);
                   sigma_diss at the fingertips (slip from filtered positions), the tighter
                   sigma_diss_g at the ground vertices

The flags, forces and normals of the tactile stream describe the interval (t-1, t]
(SPEC), so a fingertip's impulse acts in the contact frame and at the lever of the
interval's middle (pose and fingertip position averaged over its ends); the ground's
impulses act at its end (implicit Euler).

Ground and finger friction are both impulses (variables) inside the Coulomb cone with a
maximal-dissipation residual, as in the violation-implicit loss of ContactNets: every
term is polynomial in the impulses and the slip, so the Gauss–Newton model stays valid
across stick–slip transitions (a closed-form regularized Coulomb law, mu lambda_n s /
|s|_eps, is stiff as 1/eps and made IPOPT crawl), and static friction is represented
exactly.  Impulse residuals are whitened in units of a fixed reference weight m0·g·dt
(the dynamics by a fixed reference body): a whitening that scaled with the estimated
mass would itself pull the mass estimate.

Non-penetration and the fingertip cone are smooth penalties rather than inequality
constraints: hard ones made IPOPT's filter trade huge objective increases for tiny
feasibility gains, and hinge penalties are invisible to a Gauss–Newton model until
crossed.  The problem is subject to eq. D2 (kinematics, equality), lambda_n >= 0 and
the shape's validity constraints.  Objective = 0.5 Σ w ||r||² + w_c Σ comp + w_d Σ diss
+ priors.  (The relaxations are squared too: complementarity and dissipation residuals
are whitened by sigma_comp and sigma_diss, see configs/estimate.toml.)
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from tacest.dynamics.rigid2d import generalized_impulse, ground_contacts, mass_matrix_diag, perp, point_velocity
from tacest.estimation.config import EstimatorConfig
from tacest.geometry.shapes import Shape, polygon_area_centroid_j, polygon_sd_and_normal_function, rot2

#: squared-residual terms, in the order the stage function returns them
SQUARED_TERMS = ("force", "normal", "contact", "pose", "dynamics", "penetration", "complementarity",
                 "dissipation", "cone")
#: loss terms of a run's first sample (rest, penetration, pose, finger gap) and the
#: start-function outputs holding them
START_TERM_OUTPUTS = (("dynamics", "rest"), ("penetration", "penetration"), ("pose", "pose"), ("contact", "contact"))
#: penalty terms (non-negative, not squared; their exact Hessian enters every Hessian
#: model): the Occam term of a pose-observed trajectory (see pose_occam)
PENALTY_TERMS = ("occam",)
TERMS = SQUARED_TERMS + PENALTY_TERMS
#: the terms that measure how far a fit violates its own model (rigid-body dynamics,
#: contact and friction), as opposed to the measurement terms
PHYSICS_TERMS = ("dynamics", "penetration", "complementarity", "dissipation", "cone")
#: m/s: smoothing of |slip| in the maximal-dissipation residual (see
#: dissipation_shortfall); well below poke speeds of several cm/s
SLIP_EPS = 3e-3
#: scaled impulse (units of m0·g·dt): tolerance of the fingertip friction cone penalty
#: (1 % of the reference weight's impulse; finger impulses are ~5-50 % of it)
CONE_TOLERANCE = 0.01
#: Hessian models built for every problem (see Problem2D._local_hessian)
HESSIAN_MODES = ("gauss-newton", "exact")
#: names of the physical parameters in theta after the shape block
PHYS_NAMES = ("log_mass", "log_inertia_ratio", "friction_ground", "friction_finger")

#: Model augmentations (SPEC effect names) the NLP can include as extra parameters
#: (docs/diagnosis.md, "NLP augmentations").  Per effect, its parameters in theta:
#: (name, prior centre, prior sigma, lower bound, upper bound), all scaled (O(1)):
#:
#: - force_bias fx, fy: offset on every measured force sample, units of m0·g (N);
#: - force_scale log_gain: measured force = exp(log_gain) × model force;
#: - linear_drag b: force -b·v on the COM, units of m0 per second (N·s/m);
#: - angular_damping c: torque -c·ω, units of m0·L² per second (N·m·s);
#: - soft_contact compliance, tau: the ground is a massless plate on a spring and damper
#:   (Kelvin–Voigt) whose sink s is a state of every sample: s + tau·ds/dt = compliance ×
#:   (total normal ground impulse in units of m0·g·dt), compliance in units of
#:   COMPLIANCE_UNIT·L, tau (= damping / stiffness) in units of TAU_UNIT;
#: - restitution e: after an impact a vertex leaves with -e × its approach velocity;
#: - face_friction d0..d{K-1}: ground friction of face i is friction_ground + d_i;
#: - com_offset dx, dy: the COM in the centroid frame (body axes), units of L.
#:
#: Priors are centred on "no effect"; their sigmas are weak (a few times the typical
#: size of the effect) so that only the data decide.
NLP_EFFECTS = {
    "restitution": (("e", 0.0, 0.5, 0.0, 0.95),),
    "angular_damping": (("c", 0.0, 5.0, 0.0, 200.0),),
    "linear_drag": (("b", 0.0, 5.0, 0.0, 200.0),),
    "soft_contact": (("compliance", 0.0, 5.0, 0.0, 100.0), ("tau", 0.0, 5.0, 0.0, 20.0)),
    "force_bias": (("fx", 0.0, 1.0, -10.0, 10.0), ("fy", 0.0, 1.0, -10.0, 10.0)),
    "force_scale": (("log_gain", 0.0, 0.5, float(np.log(0.1)), float(np.log(10.0))),),
    "face_friction": (),  # one parameter per face, see effect_parameters
    "com_offset": (("dx", 0.0, 0.3, -0.5, 0.5), ("dy", 0.0, 0.3, -0.5, 0.5)),
}
#: where a fit from the estimator's own start begins an effect parameter (scaled; the
#: others begin at "no effect", their prior centre): a bounce is a change of contact
#: mode, and from e = 0 a fit of a dropped box bouncing with e = 0.7 stayed plastic
#: (e 0.07, objective above the plain model's)
EFFECT_STARTS = {"restitution.e": 0.5}
#: face_friction: prior sigma and bounds of the per-face friction offsets d_i
FACE_FRICTION_PRIOR = (0.0, 0.5, -1.5, 1.5)
#: soft_contact: the compliance parameter's unit, as a fraction of the length scale L
#: (a 1 kg box on a 3000 N/m ground with L = 0.1 m sinks 3.3 mm: compliance ≈ 3)
COMPLIANCE_UNIT = 0.01
#: s: soft_contact's tau unit (the ground's time constant damping / stiffness; a plate
#: damped at 0.5-1 × critical under a 0.2-1 kg object on 1500-6000 N/m has 6-50 ms)
TAU_UNIT = 0.01
#: soft_contact: unit of the plate's sink state (the S block), a fraction of the length
#: scale L (as COMPLIANCE_UNIT, so that the sink at rest is compliance × the load)
PLATE_UNIT = COMPLIANCE_UNIT
#: s: added to soft_contact's tau in the plate's decay exp(-dt / tau) over a sample, so
#: that tau = 0 (no damper: the plate follows its load) has finite derivatives
TAU_FLOOR = 1e-6
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
#: m: smoothing width of the complementarity's reach term max(phi - reach, 0), a
#: softplus with an exponential tail (as ground_gap_indicator): at a vertex on the
#: ground (phi = 0, reach 1 cm) it adds 5e-6 of the saturated psi, so a resting vertex
#: under load costs nothing.  The algebraic tail of smooth_pos (eps²/4r, 0.25 % there)
#: priced the weight itself and pulled the mass of pushed boxes away (bench_estimate,
#: median mass error 21 % -> 30 % on seeds 0-5)
REACH_SMOOTHING = 1e-3
#: face_friction: sharpness of the softmax that picks the face facing the ground most
#: (weights exp(-FACE_SHARPNESS · n_face·up)): between the faces of a box resting flat
#: (n·up = -1 vs 0) the ratio is e^-20; at 45° the two lower faces share equally
FACE_SHARPNESS = 20.0


def effect_parameters(effects, n_vertices):
    """[(effect, parameter, prior centre, prior sigma, lower, upper)] of the NLP's
    effect block, in the order of ``effects`` (see NLP_EFFECTS)."""
    out = []
    for e in effects:
        if e == "face_friction":
            out += [(e, f"d{i}", *FACE_FRICTION_PRIOR) for i in range(n_vertices)]
        else:
            out += [(e, *p) for p in NLP_EFFECTS[e]]
    return out


def check_effects(effects) -> tuple:
    """The effects as a canonical tuple (NLP_EFFECTS order, no repeats); a TacestError
    (one line) for an unknown name or an effect the NLP does not model."""
    from tacest.errors import TacestError

    if isinstance(effects, str):
        effects = (effects,)
    names = []
    for e in effects or ():
        e = str(e).strip()
        if e in ("", "none"):
            continue
        if e not in NLP_EFFECTS:
            from tacest.sim.effects import EFFECTS

            if e in EFFECTS:
                raise TacestError(f"effect {e!r} is not modelled inside the estimator's NLP (it is a data "
                                  f"transform); NLP effects: {', '.join(NLP_EFFECTS)}")
            raise TacestError(f"unknown effect {e!r}; NLP effects: {', '.join(NLP_EFFECTS)}")
        if e not in names:
            names.append(e)
    return tuple(n for n in NLP_EFFECTS if n in names)


@dataclass(frozen=True)
class RunStructure:
    """What fixes the NLP's structure for one run: samples T, fingers F, and whether
    its poses are observed (the Occam term is built only for problems with such runs)."""

    T: int
    F: int
    observed: bool = False


def consecutive_slices(vector):
    """take(n) -> the next n entries of vector (CasADi or numpy), in order."""
    i = 0

    def take(n):
        nonlocal i
        out = vector[i: i + n]
        i += n
        return out

    return take


def smooth_pos(x, eps):
    """Smoothed max(x, 0): 0.5 (x + sqrt(x² + eps²)); exact as eps → 0."""
    return 0.5 * (x + ca.sqrt(x * x + eps * eps))


def smooth_neg(x, delta):
    """Smoothed min(x, 0): -delta · log(1 + exp(-x / delta)), stable for any x; it keeps
    a little curvature on the feasible side so that a Gauss–Newton model sees an
    approaching limit before it is crossed."""
    y = -x / delta
    return -delta * (ca.fmax(y, 0) + ca.log1p(ca.exp(-ca.fabs(y))))


#: a one-sided penalty's smoothing width is its tolerance divided by this, and it is
#: shifted by one tolerance into the violated side: at the limit itself the whitened
#: residual is -log(1 + e^-3) / 3 ≈ -0.016 instead of the -log 2 ≈ -0.69 of an unshifted
#: softplus, whose gradient pushes every resting contact off its limit and biases the
#: parameters (the object floats, the finger friction cone widens)
SOFT_SHIFT = 3.0


def one_sided(x, sigma):
    """Whitened smooth penalty of a limit x >= 0 with tolerance sigma (same units as x):
    ≈ 0 for x >= 0, -0.23 at x = -sigma, ≈ (x + sigma) / sigma below (see SOFT_SHIFT)."""
    return smooth_neg(x + sigma, sigma / SOFT_SHIFT) / sigma


#: Newton steps of pose_occam's innovation equation: from its two asymptotes, 4 steps
#: solve it to machine precision for every tracking index in [1e-8, 1e6]
OCCAM_NEWTON_STEPS = 4


def pose_occam(log_lam):
    """Occam term (dimensionless) of one pose-observed degree of freedom per sample.

    The loss fits each run's trajectory jointly with the parameters (a MAP of the
    latent trajectory), which is biased where the parameters set how freely the
    trajectory may move: the dynamics residual costs an object of mass m a velocity
    change w with sd s = sigma_v m_ref / m, so a light object follows the pose noise
    at no cost (docs/estimation.md, "Pose observations and light objects").  The
    marginal likelihood of the pose observations, with the trajectory integrated out,
    carries the missing term.  For a body moving freely (implicit Euler,
    q_t = q_(t-1) + dt v_t, v_t = v_(t-1) + w_t), observed with noise sigma_p at every
    sample, it is exact in the steady state of the Kalman filter: per sample
    0.5 log(S / sigma_p²), S the innovation variance.  With the tracking index
    lam = s dt / sigma_p and a = S / sigma_p² - 1, the Riccati equation reduces to
    a⁴ = lam² (a + 1) (a + 2)², solved here by Newton steps in log a.

    log_lam : log of the tracking index.  Returns 0.5 log(1 + a): ≈ (lam / 2)^½ for a
    heavy body (physics tighter than the data), ≈ log lam for a light one (the data
    resolve each velocity change: the object pays for the freedom it uses).
    """
    lam = ca.exp(log_lam)
    u = ca.log(ca.sqrt(2 * lam) + lam * lam)  # asymptotes: a ≈ sqrt(2 lam), a ≈ lam²
    for _ in range(OCCAM_NEWTON_STEPS):
        a = ca.exp(u)
        f = 2 * u - ca.log(a + 2) - 0.5 * ca.log1p(a) - log_lam
        u = u - f / (2 - a / (a + 2) - 0.5 * a / (a + 1))
    return 0.5 * ca.log1p(ca.exp(u))


#: free-direction weights of the Occam term (occam_free_weights): a contact row of
#: weight s takes a direction's freedom to OCCAM_HELD_EPS / (s + OCCAM_HELD_EPS), 3 % for
#: a touching contact (s = 1)
OCCAM_HELD_EPS = 0.03
#: sharpness of a ground vertex's touch weight exp(-OCCAM_TOUCH_SHARPNESS x (gap in
#: sig_gap - 1)+): 1 within one sig_gap of the ground, 0.05 at two, 0.0025 at three, so
#: that a vertex off the ground holds nothing
OCCAM_TOUCH_SHARPNESS = 3.0


def occam_free_weights(rows, weights, half_length):
    """Per-degree-of-freedom freedom (3,) of the object at one sample, for the Occam term.

    The Occam term (pose_occam) prices the freedom of a body that moves by process noise
    alone.  A direction held by a contact is not free: there the contact impulse, not the
    mass, absorbs any velocity change, so the mass does not set how freely it moves (a box
    resting on a face is held in height and angle whatever its mass; a finger pushing it
    holds it along the push).  Counting such directions as free prices light objects
    wrongly and pulled slow sliding pushes to twice their mass (docs/estimation.md).

    rows : list of (normal (2,) world, lever (2,) world m) of the contacts; weights :
    list of their weights in [0, 1] (a ground vertex's touch, a finger's flag);
    half_length : m, the length that puts the angle in length units (L/2, as the
    dynamics residual).  Each contact constrains the generalized direction
    a = [n_x, n_y, (r × n) / half_length]; with A = Σ s a aᵀ the freedom of degree j is
    the diagonal of ε (A + ε I)⁻¹ (ε = OCCAM_HELD_EPS): 1 where nothing holds it,
    ε / (s + ε) along a held axis.  Smooth in the contact weights and geometry."""
    A = OCCAM_HELD_EPS * ca.SX.eye(3)
    for (n, r), w in zip(rows, weights):
        a = ca.vertcat(n[0], n[1], (r[0] * n[1] - r[1] * n[0]) / half_length)
        A = A + w * (a @ a.T)
    return OCCAM_HELD_EPS * ca.diag(ca.inv(A))


def ground_gap_indicator(phi, sigma_gap, eps):
    """Smoothed (phi / sigma_gap - 1)⁺, a softplus of width eps / SOFT_SHIFT (in units of
    sigma_gap): ≈ 0 for a vertex within one sigma_gap of the ground, ≈ phi / sigma_gap - 1
    above.  Its tail is exponential: at phi = 0 it is (eps/3)·exp(-3/eps) (5e-6 at eps =
    0.3), so a resting vertex that carries a large load (a heavy object, a finger pressing
    down) costs nothing in the complementarity residual lambda_n·psi.  The algebraic tail
    of 0.5 (x + sqrt(x² + eps²)) (eps²/4 = 0.02 at phi = 0) made that residual grow with
    the load and pulled the mass estimate down (~3x on pressed boxes)."""
    w = eps / SOFT_SHIFT
    return -smooth_neg(-(phi / sigma_gap - 1), w)


def reach_excess(phi, reach):
    """A vertex's height beyond the complementarity's reach, in reaches: smoothed
    max(phi - reach, 0) / reach (phi, reach in m), a softplus of width REACH_SMOOTHING
    whose tail is exponential, so a vertex on the ground (phi = 0) gets 5e-6 at a 1 cm
    reach and a resting vertex under load costs nothing."""
    return -smooth_neg(reach - phi, REACH_SMOOTHING) / reach


def contact_residual(phi_f, contact, weight, sigma_gap):
    """Whitened contact-flag residual of one fingertip: its gap phi_f (m) at the end of
    the interval where the flag is 1, its (smoothed) penetration where the flag is 0.
    (The flag covers the interval (t[k-1], t[k]], so at the last sample of a touch the
    fingertip may have let go inside it; docs/estimation.md says why the end's gap is
    kept there.)"""
    return weight * (contact * phi_f / sigma_gap + (1 - contact) * one_sided(phi_f, sigma_gap))


def smooth_abs(x, eps):
    """Smoothed |x|: sqrt(x² + eps²)."""
    return ca.sqrt(x * x + eps * eps)


def dissipation_shortfall(mu, lam_n, lam_t, slip, eps):
    """Maximal-dissipation residual (eq. C3) of one contact: mu lam_n |slip| + lam_t slip,
    >= 0 inside the friction cone, 0 when friction opposes the slip at the cone's limit
    (or the contact sticks).  |slip| is smoothed as slip² / sqrt(slip² + eps²): 0 at slip
    0 (no artificial residual while sticking), relative error ≈ eps² / (2 slip²) when
    sliding (0.3 % at 13 eps), slope bounded (< 1.3), so the Gauss–Newton model stays
    valid across stick–slip transitions.  (The earlier sqrt(slip² + eps²) - eps is low
    by eps / |slip|: 7 % at 40 mm/s, 30 % at 10 mm/s, which made the residual vanish
    only with friction that far inside the cone and biased the friction estimate up.)"""
    return mu * lam_n * slip * slip / smooth_abs(slip, eps) + lam_t * slip


def stage_local_variables(ins):
    """The local variables y (a column) of a stage function's inputs ``ins`` (its
    sx_in()): [q_prev, v_prev, q, v, lam_ground, lam_finger, phys, s_prev, s] (the
    plate's sinks are empty without soft_contact); data d and globals g are not."""
    qp, vp, q, v, lg, lf, phys, _d, _g, sp, s = ins
    return ca.vertcat(qp, vp, q, v, lg, lf, phys, sp, s)


def start_local_variables(ins):
    """The local variables [q, v, phys, s] of a start function's inputs (its sx_in())."""
    q, v, phys, _d, _g, s = ins
    return ca.vertcat(q, v, phys, s)


# indices into the per-run global parameter vector
G_NAMES = ("dt", "L", "Lam", "m0", "nx", "ny", "h", "sig_force", "sig_normal", "sig_gap", "sig_proc",
           "sig_pen", "sig_rest", "sig_pos", "sig_ang", "eps", "comp_mult", "dyn_mult", "sig_comp", "sig_diss", "m_ref", "I_ref", "sig_diss_g",
           "w_rest", "reach")
G = {n: i for i, n in enumerate(G_NAMES)}


class Problem2D:
    """The NLP for a set of runs of one object (see module docstring).

    Parameters
    ----------
    shape : Shape parameterization (box, polygon:K)
    structures : list of RunStructure, one per run
    config : EstimatorConfig
    effects : SPEC effect names modelled as extra parameters (NLP_EFFECTS); their
        parameters follow PHYS_NAMES in theta and are appended to phys unchanged
    """

    def __init__(self, shape: Shape, structures: list[RunStructure], config: EstimatorConfig, effects=()):
        self.shape = shape
        self.structures = list(structures)
        self.config = config
        self.K = shape.n_vertices
        self.n_shape = shape.n_params
        self.effects = check_effects(effects)
        #: the complementarity's reach term is built only when configured (a structural
        #: choice, like the Occam term: part of the solver cache's key)
        self.reach_on = config.noise.complementarity_reach > 0
        #: [(effect, parameter, prior centre, prior sigma, lower, upper)] of the effect block
        self.effect_params = effect_parameters(self.effects, self.K)
        self.n_eff = len(self.effect_params)
        #: "effect.parameter" -> index within the effect block (theta after PHYS_NAMES,
        #: phys after the 2K + 4 physical entries)
        self.eff_index = {f"{e}.{n}": j for j, (e, n, *_) in enumerate(self.effect_params)}
        self.n_theta = self.n_shape + len(PHYS_NAMES) + self.n_eff
        #: per-sample states (the S block, state_block): soft_contact's plate sink (one
        #: row), then restitution's impact memory (one row per vertex: the approach speed
        #: of an impact within the sample's interval, m/s)
        self.n_plate = 1 if "soft_contact" in self.effects else 0
        self.n_impact = self.K if "restitution" in self.effects else 0
        self.n_state = self.n_plate + self.n_impact
        #: the Occam term (pose_occam) is part of the NLP only where it is weighted and
        #: some run's poses are observed (it prices pose-observed samples only; without
        #: it no sample's function and Hessian carries it)
        self.with_occam = config.weights.occam > 0 and any(s.observed for s in structures)
        self._build()

    # ------------------------------------------------------------------------------
    # layout of the decision vector z and the parameter vector p

    def _layout(self):
        K = self.K
        self.offsets = []
        self.n_phys = 2 * K + 4 + self.n_eff
        self.phys_offset = self.n_theta
        n = self.n_theta + self.n_phys
        for st in self.structures:
            T, F = st.T, st.F
            blk = {"Q": (n, 3 * T)}
            n += 3 * T
            blk["V"] = (n, 3 * T)
            n += 3 * T
            blk["LG"] = (n, 2 * K * (T - 1))
            n += 2 * K * (T - 1)
            blk["LF"] = (n, 2 * F * (T - 1))
            n += 2 * F * (T - 1)
            blk["S"] = (n, self.n_state * T)
            n += self.n_state * T
            self.offsets.append(blk)
        self.n_z = n

    def n_data(self, F):
        """Per-sample data length: c_f (2F), v_f (2F), contact (F), n_meas (2F),
        F_meas (2F), w_force (F), w_tact (F), radius (F), c_f_start (2F) (the fingertip
        at the interval's start), q_obs (3), w_pose (1)."""
        return 14 * F + 4

    def _build(self):
        self._layout()
        K = self.K
        z = ca.MX.sym("z", self.n_z)
        theta = z[: self.n_theta]

        # parameters: per run, a global block and a data matrix; plus L and m0 shared
        p_parts = []
        self.p_offsets = []
        np_ = 0
        L_sym = ca.MX.sym("L")
        m0_sym = ca.MX.sym("m0")
        p_parts += [L_sym, m0_sym]
        np_ += 2
        run_syms = []
        for st in self.structures:
            gsym = ca.MX.sym("g", len(G_NAMES))
            dsym = ca.MX.sym("d", self.n_data(st.F), st.T)
            self.p_offsets.append((np_, len(G_NAMES), self.n_data(st.F) * st.T))
            np_ += len(G_NAMES) + self.n_data(st.F) * st.T
            p_parts += [gsym, ca.vec(dsym)]
            run_syms.append((gsym, dsym))
        self.n_p = np_
        p = ca.vertcat(*p_parts)

        # physical quantities, lifted: decision variables phys (scaled) with the
        # equality constraint phys = phys(theta), so that every per-sample Hessian block
        # is local (the shape's nonlinear map enters only the small theta block)
        self.phys_sx = self._phys_function()
        phys = z[self.phys_offset: self.phys_offset + self.n_phys]
        g_lift = phys - self.phys_sx(theta, L_sym, m0_sym)
        w_sym = ca.MX.sym("w", len(TERMS))
        # priors: lm_sigma, lI_sigma, mu0, mu_sigma, shape_sigma, on/off, s_ref (n_shape)
        prior_sym = ca.MX.sym("prior", 6 + self.n_shape)
        self.n_p_total = self.n_p + len(TERMS) + 6 + self.n_shape
        p_all = ca.vertcat(p, w_sym, prior_sym)
        lam_f = ca.MX.sym("lam_f")
        lam_g_parts = []  # symbolic multipliers, in the order of g

        obj_terms = {t: 0 for t in TERMS}
        r_stack = {t: [] for t in SQUARED_TERMS + ("kinematics",)}
        penalty_sx = {t: [] for t in PENALTY_TERMS}
        g_list, lbg, ubg = [g_lift], [np.zeros(self.n_phys)], [np.zeros(self.n_phys)]
        # per Hessian model: (mapped local Hessians (n_y, n_y * N), global indices (N, n_y))
        hess_blocks = {mode: [] for mode in HESSIAN_MODES}
        self.stage_funs = []
        self.start_funs = []
        lam_lift = ca.MX.sym("lam_lift", self.n_phys)
        lam_g_parts.append(lam_lift)
        n_g = self.n_phys
        for i, st in enumerate(self.structures):
            gsym, dsym = run_syms[i]
            T, F = st.T, st.F
            stage = self._stage_function(F)
            start = self._start_function(F)
            self.stage_funs.append(stage)
            self.start_funs.append(start)
            # the loss and its gradient run through compiled copies (kernels.py); the SX
            # functions stay for the Hessian builders and the residual stack (information)
            kern = self._compiled([stage, start], f"F{F}", derivatives=(stage.name(), start.name()))
            stage_k, start_k = kern[stage.name()], kern[start.name()]
            off = self.offsets[i]
            Q = ca.reshape(z[off["Q"][0]: off["Q"][0] + off["Q"][1]], 3, T)
            Vv = ca.reshape(z[off["V"][0]: off["V"][0] + off["V"][1]], 3, T)
            LG = ca.reshape(z[off["LG"][0]: off["LG"][0] + off["LG"][1]], 2 * K, T - 1)
            LF = ca.reshape(z[off["LF"][0]: off["LF"][0] + off["LF"][1]], 2 * F, T - 1)
            S = ca.reshape(z[off["S"][0]: off["S"][0] + off["S"][1]], self.n_state, T)
            stage_args = (Q[:, :-1], Vv[:, :-1], Q[:, 1:], Vv[:, 1:], LG, LF, phys, dsym[:, 1:], gsym,
                          S[:, :-1], S[:, 1:])
            res = dict(zip(stage.name_out(), stage_k.map(T - 1, "serial")(*stage_args)))
            res_sx = dict(zip(stage.name_out(), stage.map(T - 1, "serial")(*stage_args)))
            for t in SQUARED_TERMS:
                obj_terms[t] = obj_terms[t] + 0.5 * ca.sumsqr(res[t])
                r_stack[t].append(ca.vec(res_sx[t]))
            # eq. D2 (linear) directly in MX: its Jacobian is then not taken through the
            # per-sample functions (the stage's g_kin output is the same expression)
            g_kin = (Q[:, 1:] - Q[:, :-1]) / gsym[G["dt"]] - Vv[:, 1:]
            r_stack["kinematics"].append(ca.vec(g_kin))
            for t in PENALTY_TERMS:
                obj_terms[t] = obj_terms[t] + ca.sum2(res[t])
                penalty_sx[t].append(ca.sum2(res_sx[t]))
            # sample 0: the object starts at rest and above the ground
            start_args = (Q[:, 0], Vv[:, 0], phys, dsym[:, 0], gsym, S[:, 0])
            o0 = dict(zip(start.name_out(), start_k(*start_args)))
            o0_sx = dict(zip(start.name_out(), start(*start_args)))
            for t, name in START_TERM_OUTPUTS:
                obj_terms[t] = obj_terms[t] + 0.5 * ca.sumsqr(o0[name])
                r_stack[t].append(ca.vec(o0_sx[name]))
            g_list.append(ca.vec(g_kin))
            lbg.append(np.zeros(3 * (T - 1)))
            ubg.append(np.zeros(3 * (T - 1)))
            lam_kin = ca.MX.sym("lam_kin", 3, T - 1)
            lam_g_parts.append(ca.vec(lam_kin))
            n_g += 3 * (T - 1)
            # Hessian blocks of the Lagrangian, one small dense block per sample
            for mode in HESSIAN_MODES:
                hs = self._stage_hessian_function(stage, mode)
                h0 = self._start_hessian_function(start, mode)
                if mode == "gauss-newton":  # the default model: compiled (the exact one on demand only)
                    kh = self._compiled([hs, h0], f"F{F}_hess_gn")
                    hs, h0 = kh[hs.name()], kh[h0.name()]
                Hs = hs.map(T - 1, "serial")(*stage_args, w_sym, lam_f, lam_kin)
                hess_blocks[mode].append((Hs, self._stage_indices(i)))
                H0 = h0(*start_args, w_sym, lam_f)
                hess_blocks[mode].append((H0, self._start_indices(i)))
        # shape validity constraints and priors (theta only)
        theta_sx = ca.SX.sym("theta", self.n_theta)
        sc = self.shape.constraints(theta_sx[: self.n_shape])
        n_sc = len(sc)
        prior_sx = ca.SX.sym("prior", 6 + self.n_shape)
        f_prior_sx = self._prior_expression(theta_sx, prior_sx)
        lam_sc = ca.MX.sym("lam_shape", n_sc)
        lam_sc_sx = ca.SX.sym("lam_shape", n_sc)
        g_sc_sx = ca.vertcat(*sc) if n_sc else ca.SX.zeros(0)
        self.prior_fun = ca.Function("prior", [theta_sx, prior_sx], [f_prior_sx])
        lag_theta = prior_sx[5] * f_prior_sx + (ca.dot(lam_sc_sx, g_sc_sx) if n_sc else 0)
        lf_sx = ca.SX.sym("lam_f")
        lam_lift_sx = ca.SX.sym("lam_lift", self.n_phys)
        L_sx, m0_sx = ca.SX.sym("L"), ca.SX.sym("m0")
        lag_theta = lf_sx * prior_sx[5] * f_prior_sx - ca.dot(lam_lift_sx, self.phys_sx(theta_sx, L_sx, m0_sx))
        if n_sc:
            lag_theta = lag_theta + ca.dot(lam_sc_sx, g_sc_sx)
        h_theta = ca.Function("hess_theta", [theta_sx, prior_sx, lf_sx, lam_sc_sx, lam_lift_sx, L_sx, m0_sx],
                              [ca.densify(ca.hessian(lag_theta, theta_sx)[0])])
        shared = [(h_theta(theta, prior_sym, lam_f, lam_sc, lam_lift, L_sym, m0_sym),
                   np.arange(self.n_theta)[None, :])]
        # Levenberg–Marquardt damping of the Hessian model (not of the objective): a ridge
        # parameter times lam_f on every variable, so the Gauss–Newton steps stay local
        ridge_sym = ca.MX.sym("ridge")
        self.n_p_total += 1
        p_all = ca.vertcat(p_all, ridge_sym)
        shared.append((ca.repmat(ridge_sym * lam_f, 1, self.n_z), np.arange(self.n_z)[:, None]))
        if n_sc:
            g_list.append(ca.Function("g_shape", [theta_sx], [g_sc_sx])(theta))
            lbg.append(np.zeros(n_sc))
            ubg.append(np.full(n_sc, np.inf))
            lam_g_parts.append(lam_sc)
            n_g += n_sc

        f = 0
        for k, t in enumerate(TERMS):
            f = f + w_sym[k] * obj_terms[t]
        f_prior = self.prior_fun(theta, prior_sym)
        f = f + prior_sym[5] * f_prior
        #: the same objective through the SX per-sample functions (not compiled): CasADi
        #: differentiates it to any order, so tests check the Hessian models against it
        #: (compiled kernels carry first derivatives only)
        self.f_reference = prior_sym[5] * f_prior
        for k, t in enumerate(SQUARED_TERMS):
            self.f_reference = self.f_reference + w_sym[TERMS.index(t)] * 0.5 * ca.sumsqr(ca.vertcat(*r_stack[t]))
        #: the weighted penalty terms alone, through the SX functions (tests)
        self.f_penalty_reference = sum(w_sym[TERMS.index(t)] * sum(penalty_sx[t]) for t in PENALTY_TERMS)
        self.f_reference = self.f_reference + self.f_penalty_reference
        self.z_sym, self.p_sym = z, p_all
        V, mass, inertia, mu_g, mu_f = self._unpack_phys(self.phys_sx(theta, L_sym, m0_sym), L_sym, m0_sym)
        area, _, _ = polygon_area_centroid_j(V)
        self.phys_fun = ca.Function("phys", [z, p_all], [V, mass, inertia, mu_g, mu_f, area])
        self.f = f
        self.g = ca.vertcat(*g_list)
        assert self.g.shape[0] == n_g
        self.lbg = np.concatenate(lbg)
        self.ubg = np.concatenate(ubg)
        self.term_fun = ca.Function("terms", [z, p_all], [ca.vertcat(*[obj_terms[t] for t in TERMS]), f_prior])
        self.nlp = {"x": z, "p": p_all, "f": f, "g": self.g}
        lam_g = ca.vertcat(*lam_g_parts)
        #: {"gauss-newton" | "exact": CasADi Function (x, p, lam_f, lam_g) -> upper triangle
        #: of the Lagrangian Hessian model}, for nlpsol's hess_lag option
        self.hess_lag = {
            mode: ca.Function("nlp_hess_l", [z, p_all, lam_f, lam_g],
                              [self._assemble_hessian(hess_blocks[mode] + shared)],
                              ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])
            for mode in HESSIAN_MODES}
        #: stacked whitened residuals per squared term (for Gauss-Newton information);
        #: "kinematics" holds the eq. D2 constraint values
        self.residual_stack = {t: ca.vertcat(*v) if v else ca.MX.zeros(0) for t, v in r_stack.items()}
        self.weight_sym = w_sym

    def _compiled(self, funs, part, derivatives=()):
        """{name: Function}: the SX functions funs compiled to C (tacest.estimation.kernels;
        as given without a compiler).  The tag names the shape, effects and part, so that
        every structure's kernels are compiled once per machine and cached."""
        from tacest.estimation.kernels import compile_functions

        tag = f"tacest2d_{self.shape.name.replace(':', '')}_{'_'.join(self.effects) or 'plain'}_{part}"
        return compile_functions(funs, tag, derivatives=derivatives, echo=getattr(self, "echo", None))

    # ------------------------------------------------------------------------------
    # exact Lagrangian Hessian from small per-sample blocks (built in O(T))

    def _phys_function(self):
        """SX Function (theta, L, m0) -> scaled phys = [vec(V) / L (2K), mass / m0,
        inertia / (m0 L²), mu_g, mu_f]."""
        th = ca.SX.sym("theta", self.n_theta)
        L = ca.SX.sym("L")
        m0 = ca.SX.sym("m0")
        s = th[: self.n_shape]
        lm, lI, mu_g, mu_f = (th[self.n_shape + i] for i in range(4))
        V = self.shape.vertices(s, L)
        area, _, J = polygon_area_centroid_j(V)
        mass = m0 * ca.exp(lm)
        inertia = mass * (J / area) * ca.exp(lI)
        u = th[self.n_shape + len(PHYS_NAMES):]
        if "com_offset" in self.effects:
            # the body frame's origin is the COM: the vertices move by -(dx, dy); the
            # inertia about the COM stays the shape's about its centroid (as simulated)
            d = ca.horzcat(u[self.eff_index["com_offset.dx"]], u[self.eff_index["com_offset.dy"]]) * L
            V = V - ca.repmat(d, self.K, 1)
        return ca.Function("phys_of_theta", [th, L, m0],
                           [ca.vertcat(ca.vec(V) / L, mass / m0, inertia / (m0 * L * L), mu_g, mu_f, u)])

    def _prior_expression(self, theta, prior):
        s = theta[: self.n_shape]
        lm, lI, mu_g, mu_f = (theta[self.n_shape + i] for i in range(4))
        lm_sig, lI_sig, mu0, mu_sig, sh_sig = (prior[i] for i in range(5))
        s_ref = prior[6:]
        f = 0.5 * (lm / lm_sig) ** 2 + 0.5 * (lI / lI_sig) ** 2 \
            + 0.5 * ((mu_g - mu0) / mu_sig) ** 2 + 0.5 * ((mu_f - mu0) / mu_sig) ** 2 \
            + 0.5 * ca.sumsqr((s - s_ref) / sh_sig)
        for j, (_, _, centre, sigma, _, _) in enumerate(self.effect_params):
            f = f + 0.5 * ((theta[self.n_shape + len(PHYS_NAMES) + j] - centre) / sigma) ** 2
        return f

    def _stage_hessian_function(self, stage, mode):
        """SX Function: dense Hessian of one sample's Lagrangian contribution with respect
        to its local variables y = [q_prev, v_prev, q, v, lam_ground, lam_finger, phys,
        s_prev, s] (stage_local_variables; the order of _stage_indices)."""
        ins = stage.sx_in()
        w = ca.SX.sym("w", len(TERMS))
        lam_f = ca.SX.sym("lam_f")
        lk = ca.SX.sym("lam_kin", 3)
        out = dict(zip(stage.name_out(), stage(*ins)))
        H = self._local_hessian(out, stage_local_variables(ins), w, lam_f, mode, extra=ca.dot(lk, out["g_kin"]))
        return ca.Function("hess_stage", [*ins, w, lam_f, lk], [H])

    def _local_hessian(self, out, y, w, lam_f, mode, extra=0, names=None):
        """Dense local Hessian of lam_f · (weighted loss) + extra with respect to y.

        Gauss–Newton (mode "gauss-newton"): the squared
        terms contribute J_rᵀ J_r (positive semi-definite, the right model of a
        least-squares objective far from a zero-residual fit), the penalty terms and
        the constraints their exact second derivatives.  Mode "exact": everything exact.
        names maps loss terms to the output names holding them.
        """
        names = names or {t: t for t in TERMS}
        if mode == "exact":
            lag = 0
            for k, t in enumerate(TERMS):
                if t not in names:
                    continue
                o = out[names[t]]
                lag = lag + w[k] * (0.5 * ca.sumsqr(o) if t in SQUARED_TERMS else o)
            return ca.densify(ca.hessian(lam_f * lag + extra, y)[0])
        r = ca.vertcat(*[ca.sqrt(w[TERMS.index(t)]) * ca.vec(out[names[t]]) for t in SQUARED_TERMS if t in names])
        J = ca.jacobian(r, y)
        rest = extra
        for k, t in enumerate(TERMS):
            if t in PENALTY_TERMS and t in names:
                rest = rest + lam_f * w[k] * out[names[t]]
        H = lam_f * ca.mtimes(J.T, J)
        if not (isinstance(rest, (int, float)) and rest == 0):
            H = H + ca.hessian(rest, y)[0]
        return ca.densify(H)

    def _start_hessian_function(self, start, mode):
        ins = start.sx_in()
        w = ca.SX.sym("w", len(TERMS))
        lam_f = ca.SX.sym("lam_f")
        out = dict(zip(start.name_out(), start(*ins)))
        H = self._local_hessian(out, start_local_variables(ins), w, lam_f, mode, names=dict(START_TERM_OUTPUTS))
        return ca.Function("hess_start", [*ins, w, lam_f], [H])

    def _stage_indices(self, i):
        """(T-1, n_y) global z indices of each sample's local variables (see above)."""
        st, off, K = self.structures[i], self.offsets[i], self.K
        T, F = st.T, st.F
        t = np.arange(1, T)[:, None]
        q_prev = off["Q"][0] + 3 * (t - 1) + np.arange(3)
        v_prev = off["V"][0] + 3 * (t - 1) + np.arange(3)
        q = off["Q"][0] + 3 * t + np.arange(3)
        v = off["V"][0] + 3 * t + np.arange(3)
        lg = off["LG"][0] + 2 * K * (t - 1) + np.arange(2 * K)
        lf = off["LF"][0] + 2 * F * (t - 1) + np.arange(2 * F)
        ph = np.repeat(self.phys_offset + np.arange(self.n_phys)[None, :], T - 1, 0)
        s_prev = off["S"][0] + self.n_state * (t - 1) + np.arange(self.n_state)
        s = off["S"][0] + self.n_state * t + np.arange(self.n_state)
        return np.hstack([q_prev, v_prev, q, v, lg, lf, ph, s_prev, s])

    def _start_indices(self, i):
        off = self.offsets[i]
        return np.concatenate([off["Q"][0] + np.arange(3), off["V"][0] + np.arange(3),
                               self.phys_offset + np.arange(self.n_phys),
                               off["S"][0] + np.arange(self.n_state)])[None, :]

    def _assemble_hessian(self, blocks):
        """Sum the local dense blocks into the upper triangle of the global Hessian.

        blocks: list of (MX (n_y, n_y * N) local Hessians side by side, (N, n_y) global indices).
        The scatter-add is one constant sparse matrix times the stacked local entries.
        """
        import scipy.sparse as sp

        rows, cols, src = [], [], []
        base = 0
        vecs = []
        for H, idx in blocks:
            N, n_y = idx.shape
            gi = np.repeat(idx[:, :, None], n_y, 2)  # (N, i, j) -> row index of entry (i, j)
            gj = np.repeat(idx[:, None, :], n_y, 1)
            # vec() of (n_y, n_y*N) is column-major: entry (i, j) of block k sits at
            # base + (k n_y + j) n_y + i
            k = np.arange(N)[:, None, None]
            ii = np.arange(n_y)[None, :, None]
            jj = np.arange(n_y)[None, None, :]
            pos = base + (k * n_y + jj) * n_y + ii
            keep = gi <= gj
            rows.append(gi[keep])
            cols.append(gj[keep])
            src.append(pos[keep])
            base += n_y * n_y * N
            vecs.append(ca.vec(H))
        rows = np.concatenate(rows)
        cols = np.concatenate(cols)
        src = np.concatenate(src)
        n = self.n_z
        pattern = sp.csc_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
        pattern.sum_duplicates()
        pattern.sort_indices()
        # nonzero index of each (row, col) in CSC order
        lookup = sp.csc_matrix((np.arange(pattern.nnz) + 1.0, pattern.indices, pattern.indptr), shape=(n, n))
        nz_of = np.asarray(lookup[rows, cols]).reshape(-1).astype(np.int64) - 1
        A = sp.csc_matrix((np.ones(len(src)), (nz_of, src)), shape=(pattern.nnz, base))
        A_dm = ca.DM(ca.Sparsity(A.shape[0], A.shape[1], A.indptr.tolist(), A.indices.tolist()), A.data)
        h_nz = ca.mtimes(A_dm, ca.vertcat(*vecs))
        sparsity = ca.Sparsity(n, n, pattern.indptr.tolist(), pattern.indices.tolist())
        return ca.MX(sparsity, h_nz)

    # ------------------------------------------------------------------------------
    # per-sample functions (SX, mapped over samples)

    def _unpack_phys(self, phys, L, m0):
        """(V (K, 2) m, mass kg, inertia kg·m², mu_ground, mu_finger) from a scaled phys vector."""
        K = self.K
        V = ca.reshape(phys[: 2 * K], K, 2) * L
        return V, phys[2 * K] * m0, phys[2 * K + 1] * m0 * L * L, phys[2 * K + 2], phys[2 * K + 3]

    def _measured_force(self, force, ev, m0):
        """The force sensor's reading (2,) N of a model force (2,) N: gain × force + bias
        (force_scale, force_bias; the plain model reads the force itself)."""
        if "force_scale" in self.effects:
            force = ca.exp(ev["force_scale.log_gain"]) * force
        if "force_bias" in self.effects:
            force = force + ca.vertcat(ev["force_bias.fx"], ev["force_bias.fy"]) * m0 * 9.81
        return force

    def _face_friction_offset(self, q, V, n_g, ev):
        """Ground friction offset Σ_i w_i d_i of the face that faces the ground most:
        softmax weights w_i ∝ exp(-FACE_SHARPNESS · n_i·n_g), n_i the outward normal
        (world) of face i, from vertex i to i+1 of the CCW polygon V (K, 2) m."""
        K = self.K
        R = rot2(q[2])
        scores, d = [], []
        for i in range(K):
            e = V[(i + 1) % K, :] - V[i, :]
            n_body = ca.vertcat(e[1], -e[0]) / ca.sqrt(e[0] * e[0] + e[1] * e[1])
            scores.append(-FACE_SHARPNESS * ca.dot(n_g, R @ n_body))
            d.append(ev[f"face_friction.d{i}"])
        w = ca.exp(ca.vertcat(*scores))
        return ca.dot(w, ca.vertcat(*d)) / ca.sum1(w)

    def _plate_law(self, ev, g, s, s_prev, load):
        """soft_contact's plate over one sample: (sink m, its downward rate m/s, the
        law's whitened residual).  s, s_prev: the sample's and the previous sample's
        sinks (units of PLATE_UNIT·L), s_prev None for a plate at rest; load: the normal
        ground impulse over the sample in units of m0·g·dt; ev: _effect_values.

        The law k·s + c·ds/dt = W over the interval, exact for a load held constant
        across it: (s - a·s_prev)/(1 - a) = C·W with a = exp(-dt/tau) (a backward
        difference, s + tau·(s - s_prev)/dt, would put the fitted tau at exp(dt/tau) - 1
        = dt/tau_fit: 25 ms for 30 at dt = 10 ms); at rest s = C·W.  Whitened by the
        sink one process sigma of velocity makes in one sample: it holds as tightly as
        the momentum balance does."""
        L, dt = g[G["L"]], g[G["dt"]]
        unit = PLATE_UNIT * L  # m per unit of s
        sink = s * unit
        sink_static = ev["soft_contact.compliance"] * COMPLIANCE_UNIT * L * load  # m, W/k
        sig_sink = g[G["sig_proc"]] * 9.81 * dt * dt  # m
        if s_prev is None:
            return sink, 0.0, (sink - sink_static) / sig_sink
        before = s_prev * unit
        decay = ca.exp(-dt / (ev["soft_contact.tau"] * TAU_UNIT + TAU_FLOOR))
        return sink, (sink - before) / dt, ((sink - decay * before) / (1 - decay) - sink_static) / sig_sink

    def _restitution_laws(self, ev, g, q_start, v_prev, V, n_g, levers, phi_c, vn_c, s_prev, s, prev_sink=None):
        """restitution over one sample interval (t-1, t]: Newton's impact law with the
        impact inside an interval, for every vertex k.  Relaxes the contact laws' gaps
        ``phi_c`` and normal velocities ``vn_c`` (lists of K, m and m/s, relative to a
        soft ground's plate; modified in place) and returns (residuals whitened like the
        dynamics: the law of the interval after an impact, then the impact memory's
        definition; the levers (K of (2,), world, m) at which the ground impulses act;
        the impact memory's values (K,) m/s as its law sets them from the interval's
        motion).

        A vertex approaching at a (its normal velocity at t-1, from its lever then)
        from the gap phi_prev would end the interval p = a·dt - phi_prev below the
        ground: where p > -IMPACT_REACH (it reached the ground within the interval, to
        within the first-order path's error) it hit the ground, and its approach a is
        kept in the impact memory A_k(t) (a state: s rows n_plate..).  In the next
        interval it leaves with e·A_k(t), less what gravity takes in the interval since
        the impact on average (the law's residual, whitened by process·g·dt +
        RESTITUTION_SCATTER·A; without the gravity term a dropped box's e came out 0.16
        for 0.3).  In both intervals the contact laws do not count the vertex's rise off
        the ground against the impulse that makes it: its gap and its upward normal
        velocity (what it has of them) are taken off what complementarity sees, so the
        ground may push a vertex that it sends up (the impact's impulse stops the
        approach and sends it off at e·a; the end-of-interval velocities of a first-order
        scheme mix the two).  This relief does not depend on e: at e = 0 the model is
        looser than the plain one at impacts (a box turning onto its next corner lifts the
        first one, and clean toss recordings fit e 0.09 with held-out gains of 45-81; the
        diagnosis does not blame e below diagnose.MATERIAL_SIZE for that reason).  Impacts are gated by a²/(a² + BOUNCE_SPEED²)
        (slower landings are plastic), and the interval after an impact by the same
        gate on A, which turns the impact detection off there (its mixed velocity is
        no approach).

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
        K = self.K
        dt = g[G["dt"]]
        sig_v = g[G["sig_proc"]] * 9.81 * dt
        e_r = ev["restitution.e"]
        phi_prev, _, levers_prev = ground_contacts(q_start, v_prev, V, n_g, g[G["h"]])
        if prev_sink is not None:  # gaps relative to a soft ground's plate
            phi_prev = [p + prev_sink for p in phi_prev]
        A_prev, A_now = s_prev[self.n_plate:], s[self.n_plate:]
        r_after, r_memory, impulse_levers, targets = [], [], [], []
        for k in range(K):
            # the interval after an impact: the vertex leaves with e × its approach
            after = A_prev[k] ** 2 / (A_prev[k] ** 2 + BOUNCE_SPEED ** 2)
            # its normal velocity over the interval (the first-order scheme's v(t) is the
            # interval's mean): e·A less what gravity took since the impact, one interval
            # on average (from an impact at a uniform time in the previous interval to
            # this one's middle; a rebound slower than that is back on the ground).
            # Smoothed over REBOUND_SMOOTHING: with a sharp max(·, 0) the law was flat in
            # e below that speed, and a fit starting at e = 0 stayed there (e 0.03 for a
            # dropped box bouncing with 0.6)
            leave = smooth_pos(e_r * A_prev[k] - 9.81 * dt, REBOUND_SMOOTHING)
            r_after.append(after * (vn_c[k] - leave) / (sig_v + RESTITUTION_SCATTER * A_prev[k]))
            # an impact within this interval
            a = smooth_pos(-ca.dot(n_g, point_velocity(v_prev, levers_prev[k])), 1e-3)  # m/s, approach
            p = a * dt - phi_prev[k]  # m, how far the approach would carry it below the ground
            reach = smooth_pos(p + IMPACT_REACH, IMPACT_DEPTH_EPS)
            struck = (1 - after) * a ** 2 / (a ** 2 + BOUNCE_SPEED ** 2) * reach / (reach + IMPACT_DEPTH_EPS)
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
        return r_after + r_memory, impulse_levers, ca.vertcat(*targets)

    def _effect_values(self, phys):
        """{"effect.parameter": scaled value} of the effect block of a phys vector."""
        a = 2 * self.K + 4
        return {k: phys[a + j] for k, j in self.eff_index.items()}

    def _unpack_data(self, d, F):
        take = consecutive_slices(d)

        c_f = ca.reshape(take(2 * F), 2, F)
        v_f = ca.reshape(take(2 * F), 2, F)
        contact = take(F)
        n_meas = ca.reshape(take(2 * F), 2, F)
        F_meas = ca.reshape(take(2 * F), 2, F)
        w_force = take(F)
        w_tact = take(F)
        radius = take(F)
        c_f_start = ca.reshape(take(2 * F), 2, F)
        q_obs = take(3)
        w_pose = take(1)
        return c_f, v_f, contact, n_meas, F_meas, w_force, w_tact, radius, c_f_start, q_obs, w_pose

    def finger_geometry(self, q, V, c_f, radius, sd_fun):
        """Gap phi_f (m), outward object normal n (2, world) and lever r (2, world, from
        the COM to the contact point) of one finger centre c_f (2, world)."""
        R = rot2(q[2])
        x = q[0:2]
        sd, n_body = sd_fun(R.T @ (c_f - x), V)
        n_w = R @ n_body
        lever = c_f - x - sd * n_w
        return sd - radius, n_w, lever

    def _stage_function(self, F):
        K = self.K
        qp = ca.SX.sym("q_prev", 3)
        vp = ca.SX.sym("v_prev", 3)
        qs = ca.SX.sym("q", 3)
        vs = ca.SX.sym("v", 3)
        lg = ca.SX.sym("lam_ground", 2 * K)
        lf = ca.SX.sym("lam_finger", 2 * F)
        phys = ca.SX.sym("phys", self.n_phys)
        d = ca.SX.sym("d", self.n_data(F))
        g = ca.SX.sym("g", len(G_NAMES))
        sp = ca.SX.sym("s_prev", self.n_state)
        ss = ca.SX.sym("s", self.n_state)
        dt, L, Lam = g[G["dt"]], g[G["L"]], g[G["Lam"]]
        eps = g[G["eps"]]
        V, mass, inertia, mu_g, mu_f = self._unpack_phys(phys, L, g[G["m0"]])
        c_f, v_f, contact, n_meas, F_meas, w_force, w_tact, radius, c_f_start, q_obs, w_pose = \
            self._unpack_data(d, F)
        # unscale: q = [x/L, y/L, angle], v = [vx/L, vy/L, omega] per second
        unscale = ca.vertcat(L, L, 1)
        q, q_start = qs * unscale, qp * unscale
        v, v_prev = vs * unscale, vp * unscale
        n_g = ca.vertcat(g[G["nx"]], g[G["ny"]])
        t_g = perp(n_g)
        phi, slip, levers = ground_contacts(q, v, V, n_g, g[G["h"]])
        gen = ca.SX.zeros(3)
        comp = []
        pen = []
        cone, diss = [], []
        eps_slip = SLIP_EPS  # m/s, smoothing of |slip|
        ev = self._effect_values(phys)
        # force_scale: the physics residuals (dynamics, complementarity, cone,
        # dissipation, Occam) see the model's forces and mass in the sensor's units
        # (× gain), as the force residual does.  Then (mass, impulses, gain) and
        # (mass/c, impulses/c, gain·c) are the same model, as they are the same data:
        # without the factor a gain above 1 let the fit shrink every force and the mass,
        # and with them every physics residual, for free (a clean recording's gain went
        # to 5.9).  Only a mass known from elsewhere (a mass prior) splits gain and mass.
        gain = ca.exp(ev["force_scale.log_gain"]) if "force_scale" in self.effects else 1.0
        # gaps (m) seen by the ground contact laws (penetration, complementarity): the
        # geometric ones unless an effect relaxes them
        phi_c = list(phi)
        # normal velocities (m/s) of the vertices at the end of the interval, and the
        # separation speed the contact laws allow (0, or the rebound of restitution)
        vn_c = [ca.dot(n_g, point_velocity(v, levers[k])) for k in range(K)]
        sig_v = g[G["sig_proc"]] * 9.81 * dt  # m/s: process noise of a velocity change
        r_rest = []
        r_plate = []
        if "soft_contact" in self.effects:
            # a compliant ground: a massless plate on a spring k and damper c
            # (Kelvin–Voigt) under the sample's load W (the normal ground impulses over
            # dt): k·s + c·ds/dt = W.  Its sink s is a state of every sample (the S
            # block, in units of PLATE_UNIT·L), so the plate's velocity ds/dt = (s -
            # s_prev)/dt pays for itself: it follows from the loads of consecutive
            # samples, and a plate that moved within one sample to excuse a vertex's
            # jitter (as a per-sample velocity did: 16 of 20 clean benchmark recordings
            # were blamed on soft_contact) needs the loads to jump with it.  The law is
            # a residual of the dynamics term (_plate_law); its load is the ground's
            # normal impulse.  A vertex may penetrate the fixed ground by s, and the
            # contact laws see its normal velocity relative to the plate.
            s_now, rate, r = self._plate_law(ev, g, ss[0], sp[0], ca.sum1(lg[:K]))
            r_plate.append(r)
            phi_c = [p + s_now for p in phi_c]
            vn_c = [vn + rate for vn in vn_c]
        if "face_friction" in self.effects:
            mu_g = mu_g + self._face_friction_offset(q, V, n_g, ev)
        impulse_levers = levers  # where each vertex's ground impulse acts (the end pose's lever)
        memory_target = ca.SX.zeros(0)
        if "restitution" in self.effects:
            r_new, impulse_levers, memory_target = self._restitution_laws(
                ev, g, q_start, v_prev, V, n_g, levers, phi_c, vn_c, sp, ss,
                prev_sink=None if not r_plate else s_now - dt * rate)
            r_rest += r_new
        for k in range(K):
            ln, lt = lg[k], lg[K + k]
            gen += generalized_impulse(impulse_levers[k], Lam * (ln * n_g + lt * t_g))
            # eq. C2 (Coulomb cone) as a smooth penalty and eq. C3 (maximal dissipation:
            # friction opposes the slip with all the cone allows) as a whitened residual,
            # both in units of the reference weight m0·g·dt like the impulses: whitened
            # relative to the object's own weight instead, a heavy object would make
            # every friction violation cheap (and a heavy, slippery fit win).  A sticking
            # vertex (slip 0) may carry any friction inside the cone.
            cone += [one_sided(gain * (mu_g * ln - lt), CONE_TOLERANCE) * CONE_TOLERANCE,
                     one_sided(gain * (mu_g * ln + lt), CONE_TOLERANCE) * CONE_TOLERANCE]
            diss.append(gain * dissipation_shortfall(mu_g, ln, lt, slip[k] / L, eps_slip / L)
                        * g[G["sig_diss"]] / g[G["sig_diss_g"]])
            # smoothed gap in units of sig_gap, shifted by one: within about one sig_gap of
            # the ground a vertex counts as touching (see ground_gap_indicator)
            gap = ground_gap_indicator(phi_c[k], g[G["sig_gap"]], eps)
            # ... and a vertex that carries load does not separate from the ground
            # (velocity-level complementarity, inelastic contact): an indicator of its
            # normal velocity beyond one process sigma.  Without it, the position-level
            # tolerance lets loaded vertices hop within sig_gap, and the normal impulses
            # do positive work: heavy, slippery fits "vibrate" along the ground between
            # touches (a 25 kg box moved by a 0.9 N push)
            sep = ground_gap_indicator(vn_c[k], sig_v, eps)
            # saturating (bounded curvature far from the ground); in units of the
            # reference weight m0·g·dt, like every impulse (see the cone above).  With a
            # reach (noise.complementarity_reach > 0; the term is built only then) an impulse
            # at a vertex higher than the reach also costs its height over the reach in
            # reaches: no action at a distance (a saturating law alone prices a flying
            # vertex carrying sigma_comp of the weight at one sigma at any height)
            if self.reach_on:
                far = reach_excess(phi_c[k], g[G["reach"]])
                comp.append(gain * ln * ((gap + sep) / (1 + gap + sep) + far))
            else:  # the plain law, expression for expression (IPOPT's path unchanged)
                comp.append(gain * ln * (gap + sep) / (1 + gap + sep))
            pen.append(one_sided(phi_c[k], g[G["sig_pen"]]))
        sd_fun = polygon_sd_and_normal_function(K)
        r_force, r_normal, r_contact, imp_finger = [], [], [], []
        finger_rows = []  # (normal, lever) of each finger's contact frame, for the Occam term
        for f in range(F):
            # the gap at the interval's end (the contact flag, see contact_residual); the
            # contact frame n_w and lever of the impulse at its middle: the measured force
            # and normal are averages over the interval (SPEC), and a fingertip sliding
            # over a corner turns the normal within one interval (the end's frame put the
            # average force outside the friction cone there)
            phi_f, _, _ = self.finger_geometry(q, V, c_f[:, f], radius[f], sd_fun)
            _, n_w, lever = self.finger_geometry((q_start + q) / 2, V, (c_f_start[:, f] + c_f[:, f]) / 2,
                                                 radius[f], sd_fun)
            t_w = perp(n_w)
            finger_rows.append((n_w, lever))
            # finger impulse ON the object: a free world-frame vector, held in the friction
            # cone of the model's contact frame (eq. C2).  Fingertips often stick to the
            # object, and the measured fingertip velocity is noisy, so friction here is
            # not a closed-form law but a cone plus a maximal-dissipation penalty (eq. C3)
            imp_s = ca.vertcat(lf[2 * f], lf[2 * f + 1])
            imp = Lam * imp_s
            ln = -ca.dot(imp_s, n_w)
            lt = ca.dot(imp_s, t_w)
            slip_f = ca.dot(t_w, point_velocity(v, lever) - v_f[:, f]) / L  # object lengths per second
            diss.append(gain * dissipation_shortfall(mu_f, ln, lt, slip_f, eps_slip / L))
            # friction cone |lambda_t| <= mu lambda_n (and lambda_n >= 0) as a smooth penalty
            cone += [one_sided(gain * (mu_f * ln - lt), CONE_TOLERANCE) * CONE_TOLERANCE,
                     one_sided(gain * (mu_f * ln + lt), CONE_TOLERANCE) * CONE_TOLERANCE]
            imp_finger.append(imp)
            gen += generalized_impulse(lever, imp)
            r_force.append(w_force[f] * (self._measured_force(imp / dt, ev, g[G["m0"]]) - F_meas[:, f])
                           / g[G["sig_force"]])
            r_normal.append(w_tact[f] * contact[f] * (n_meas[:, f] - n_w) / g[G["sig_normal"]])
            r_contact.append(contact_residual(phi_f, contact[f], w_tact[f], g[G["sig_gap"]]))
        # eq. D1 divided by the mass matrix, whitened as process noise on the velocity
        # change: (v - v_prev) - dt g_vec - M⁻¹ J^T lambda, gravity along -n_g.  (Whitening
        # the impulse form by a fixed scale would let a light object move for free.)
        if "linear_drag" in self.effects:  # force -b·v on the COM over the interval (implicit)
            b = ev["linear_drag.b"] * g[G["m0"]]  # N·s/m
            gen += ca.vertcat(-b * v[0] * dt, -b * v[1] * dt, 0)
        if "angular_damping" in self.effects:  # torque -c·ω
            c_ang = ev["angular_damping.c"] * g[G["m0"]] * L * L  # N·m·s
            gen += ca.vertcat(0, 0, -c_ang * v[2] * dt)
        M = mass_matrix_diag(mass, inertia)
        M_ref = ca.vertcat(g[G["m_ref"]], g[G["m_ref"]], g[G["I_ref"]])
        grav = ca.vertcat(-9.81 * n_g * dt, 0)
        r_dyn_raw = gain * (M * ((v - v_prev) - grav) - gen) / M_ref
        r_dyn = ca.sqrt(g[G["dyn_mult"]]) * r_dyn_raw / ca.vertcat(sig_v, sig_v, sig_v / (L / 2))
        if r_rest:
            r_dyn = ca.vertcat(r_dyn, ca.sqrt(g[G["dyn_mult"]]) * ca.vertcat(*r_rest))
        if r_plate:
            r_dyn = ca.vertcat(r_dyn, ca.sqrt(g[G["dyn_mult"]]) * ca.vertcat(*r_plate))
        occam = ca.SX.zeros(1)
        if self.with_occam:
            # the Occam term of a pose-observed sample (pose_occam): tracking indices of the
            # translations and the rotation, from the process sd of each velocity change
            # (M floored far below any real mass: a trial step of the solver through a
            # degenerate shape may make the inertia <= 0, and the log NaN)
            M_pos = ca.fmax(gain * M, 1e-9 * M_ref)
            log_s = ca.log(sig_v * M_ref / M_pos / ca.vertcat(1, 1, L / 2)) - 0.5 * ca.log(g[G["dyn_mult"]])
            log_lam = log_s + ca.log(dt / ca.vertcat(g[G["sig_pos"]], g[G["sig_pos"]], g[G["sig_ang"]]))
            # priced only in the directions no contact holds (occam_free_weights: the
            # ground vertices by how close they are to the ground at the observed pose,
            # the fingers by their flag): there a contact impulse, not the mass, absorbs
            # a velocity change.  The observed pose, not the fitted one: with the fitted
            # gaps the term paid a light object to put its vertices on the ground (a
            # bouncing box's fit then oscillated between held and free and never
            # converged)
            phi_obs, _, _ = ground_contacts(q_obs, v, V, n_g, g[G["h"]])
            touch = [ca.exp(-OCCAM_TOUCH_SHARPNESS * ground_gap_indicator(phi_obs[k], g[G["sig_gap"]], eps))
                     for k in range(K)]
            free = occam_free_weights([(n_g, levers[k]) for k in range(K)] + finger_rows,
                                      touch + [contact[f] for f in range(F)], L / 2)
            occam = w_pose * sum(free[k] * pose_occam(log_lam[k]) for k in range(3))
        g_kin = (qs - qp) / dt - vs  # eq. D2, scaled (per second in units of L)
        r_pose = w_pose * (q - q_obs) / ca.vertcat(g[G["sig_pos"]], g[G["sig_pos"]], g[G["sig_ang"]])
        outs = {
            "force": ca.vertcat(*r_force) if F else ca.SX.zeros(0),
            "normal": ca.vertcat(*r_normal) if F else ca.SX.zeros(0),
            "contact": ca.vertcat(*r_contact) if F else ca.SX.zeros(0),
            "pose": r_pose,
            "dynamics": r_dyn,
            "penetration": ca.vertcat(*pen),
            "complementarity": ca.sqrt(g[G["comp_mult"]]) * ca.vertcat(*comp) / g[G["sig_comp"]],
            "dissipation": ca.vertcat(*diss) / g[G["sig_diss"]],
            "cone": ca.vertcat(*cone) / g[G["sig_comp"]],
            "occam": occam,
            "g_kin": g_kin,
            # diagnostics only (not in the loss): tangential ground impulses (scaled) and
            # finger impulses on the object (N·s, world); the ground contacts' geometric
            # gaps (m) and slip velocities (m/s), the ground friction coefficient and the
            # object's weight in units of the reference weight (for the active-set rows
            # of the information, tacest.information.observed)
            "lam_t_ground": lg[K:],
            "imp_finger": ca.vertcat(*imp_finger) if F else ca.SX.zeros(0),
            "phi_ground": ca.vertcat(*phi),
            "slip_ground": ca.vertcat(*slip),
            "mu_ground": mu_g,
            "weight": mass / g[G["m0"]],
            # restitution's impact memory as its law sets it (settle_impact_memory)
            "impact_target": memory_target,
        }
        names = list(outs)
        return ca.Function(f"stage_K{K}_F{F}", [qp, vp, qs, vs, lg, lf, phys, d, g, sp, ss],
                           [outs[n] for n in names],
                           ["q_prev", "v_prev", "q", "v", "lam_ground", "lam_finger", "phys", "d", "g", "s_prev", "s"],
                           names)

    def _start_function(self, F):
        """Terms at sample 0: rest (v ≈ 0, weighted by the run's w_rest: 0 for a run that
        starts pose-observed, data.starts_at_rest), penetration, pose observation,
        finger gap."""
        K = self.K
        qs = ca.SX.sym("q", 3)
        vs = ca.SX.sym("v", 3)
        phys = ca.SX.sym("phys", self.n_phys)
        d = ca.SX.sym("d", self.n_data(F))
        g = ca.SX.sym("g", len(G_NAMES))
        s0 = ca.SX.sym("s", self.n_state)
        L = g[G["L"]]
        V, *_ = self._unpack_phys(phys, L, g[G["m0"]])
        c_f, v_f, contact, n_meas, F_meas, w_force, w_tact, radius, c_f_start, q_obs, w_pose = \
            self._unpack_data(d, F)
        q = qs * ca.vertcat(L, L, 1)
        v = vs * ca.vertcat(L, L, 1)
        n_g = ca.vertcat(g[G["nx"]], g[G["ny"]])
        phi, _, _ = ground_contacts(q, v, V, n_g, g[G["h"]])
        w_rest = g[G["w_rest"]]
        rest = w_rest * v / ca.vertcat(g[G["sig_rest"]], g[G["sig_rest"]], g[G["sig_rest"]] / L * 2)
        if "soft_contact" in self.effects:
            # at rest on a compliant ground: the plate sunk by the object's weight (the
            # load m·g·dt is phys's mass / m0 in impulse units), whitened as the plate
            # law of every later sample; a free start (w_rest 0) leaves the plate free too
            sink, _, r = self._plate_law(self._effect_values(phys), g, s0[0], None, phys[2 * K])
            rest = ca.vertcat(rest, w_rest * r)
            phi = [p + sink for p in phi]
        if "restitution" in self.effects:
            # no impact before sample 0: the impact memory starts empty
            rest = ca.vertcat(rest, s0[self.n_plate:] / (g[G["sig_proc"]] * 9.81 * g[G["dt"]]))
        pen = ca.vertcat(*[one_sided(p, g[G["sig_pen"]]) for p in phi])
        r_pose = w_pose * (q - q_obs) / ca.vertcat(g[G["sig_pos"]], g[G["sig_pos"]], g[G["sig_ang"]])
        sd_fun = polygon_sd_and_normal_function(K)
        r_contact = []
        for f in range(F):
            phi_f, _, _ = self.finger_geometry(q, V, c_f[:, f], radius[f], sd_fun)
            r_contact.append(contact_residual(phi_f, contact[f], w_tact[f], g[G["sig_gap"]]))
        return ca.Function("start", [qs, vs, phys, d, g, s0],
                           [rest, pen, r_pose, ca.vertcat(*r_contact) if F else ca.SX.zeros(0)],
                           ["q", "v", "phys", "d", "g", "s"], ["rest", "penetration", "pose", "contact"])

    # ------------------------------------------------------------------------------
    # helpers to slice z

    def run_blocks(self, z, i):
        """Views (scaled values) of run i: Q (3, T), V (3, T), LG (2K, T-1) ground impulses
        [normal (K); tangential (K)], LF (2F, T-1)."""
        st = self.structures[i]
        off = self.offsets[i]
        z = np.asarray(z, float).reshape(-1)

        def blk(name, rows):
            a, n = off[name]
            return z[a: a + n].reshape(-1, rows).T

        LF = blk("LF", 2 * st.F) if st.F else np.zeros((0, st.T - 1))
        return blk("Q", 3), blk("V", 3), blk("LG", 2 * self.K), LF

    def state_block(self, z, i):
        """(n_state, T) the per-sample states of run i: soft_contact's plate sink (units
        of PLATE_UNIT·L), then restitution's impact memory (K rows, m/s); no rows
        without those effects."""
        a, n = self.offsets[i]["S"]
        return np.asarray(z, float).reshape(-1)[a: a + n].reshape(self.structures[i].T, self.n_state).T

    def stage_arguments(self, z, i, D, g):
        """The stage function's inputs for every interval of run i (mapped over T-1):
        from z (scaled decision vector), D (n_data, T) the run's data matrix and g its
        global vector."""
        Q, V, LG, LF = self.run_blocks(z, i)
        S = self.state_block(z, i)
        phys = np.asarray(z, float).reshape(-1)[self.phys_offset: self.phys_offset + self.n_phys]
        return (Q[:, :-1], V[:, :-1], Q[:, 1:], V[:, 1:], LG, LF, phys, D[:, 1:], g, S[:, :-1], S[:, 1:])

    def start_arguments(self, z, i, D, g):
        """The start function's inputs of run i (see stage_arguments)."""
        Q, V, _, _ = self.run_blocks(z, i)
        phys = np.asarray(z, float).reshape(-1)[self.phys_offset: self.phys_offset + self.n_phys]
        return (Q[:, 0], V[:, 0], phys, D[:, 0], g, self.state_block(z, i)[:, 0])

    def set_run_blocks(self, z, i, Q=None, V=None, LG=None, LF=None, S=None):
        """Write run i's blocks into z (scaled values, shapes as run_blocks and
        state_block give them).  New ground impulses LG without states S put the plate
        where it rests under them (s = compliance × load, the law without its damper;
        the object's weight at sample 0), with the compliance z holds, and the impact
        memory at 0 (no impact)."""
        off = self.offsets[i]
        if LG is not None and S is None and self.n_state:
            T = np.asarray(LG).shape[1] + 1
            S = np.zeros((self.n_state, T))
            if self.n_plate:
                u = np.asarray(z, float)[self.n_shape + len(PHYS_NAMES):self.n_theta]
                comp = u[self.eff_index["soft_contact.compliance"]]
                mass = float(np.exp(z[self.n_shape]))  # m / m0
                S[0] = comp * np.concatenate([[mass], np.asarray(LG, float)[: self.K].sum(axis=0)])
        for name, arr in (("Q", Q), ("V", V), ("LG", LG), ("LF", LF), ("S", S)):
            if arr is not None:
                a, n = off[name]
                z[a: a + n] = np.asarray(arr, float).T.reshape(-1)
        return z

    def settle_impact_memory(self, z, i, D, g):
        """z with run i's impact memory (restitution) set sample by sample to what its
        law gives along z's trajectory (D, g: the run's data matrix and global vector).
        Each sample's value depends on the previous one (the interval after an impact
        is no new impact), so a start with the memory at 0 leaves the impulse stage a
        nonconvex problem in it, and on a tumbling landing it settled on a leaked
        0.2 m/s that hid the real impact of the next sample.  Without restitution z is
        returned as it is."""
        if not self.n_impact:
            return z
        T = self.structures[i].T
        S = self.state_block(z, i).copy()
        S[self.n_plate:] = 0.0
        qp, vp, q, v, lg, lf, phys, d, g_, _, _ = self.stage_arguments(z, i, D, g)
        names = self.stage_funs[i].name_out()
        k_out = names.index("impact_target")
        for t in range(1, T):
            j = t - 1
            out = self.stage_funs[i](qp[:, j], vp[:, j], q[:, j], v[:, j], lg[:, j], lf[:, j], phys, d[:, j], g_,
                                     S[:, j], S[:, t])
            S[self.n_plate:, t] = np.asarray(out[k_out]).ravel()
        return self.set_run_blocks(z, i, S=S)
