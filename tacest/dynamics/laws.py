"""Contact and friction laws as smooth, whitened CasADi residuals, shared by the 2-D and
3-D models (tacest.model.stage2d, tacest.model.stage3d) and their effects.

Every law here is written so that a Gauss–Newton model of its square stays valid across
contact-mode changes: one-sided limits are softplus penalties shifted into the violated
side (:func:`one_sided`), indicators have exponential tails (:func:`ground_gap_indicator`),
and friction is a cone plus a maximal-dissipation residual (:func:`dissipation_shortfall`,
the violation-implicit form of ContactNets).
"""

from __future__ import annotations

import casadi as ca

#: m/s: smoothing of |slip| in the maximal-dissipation residual (see
#: dissipation_shortfall); well below poke speeds of several cm/s
SLIP_EPS = 3e-3

#: scaled impulse (units of m0·g·dt): tolerance of the fingertip friction cone penalty
#: (1 % of the reference weight's impulse; finger impulses are ~5-50 % of it)
CONE_TOLERANCE = 0.01

#: m: smoothing width of the complementarity's reach term max(phi - reach, 0), a
#: softplus with an exponential tail (as ground_gap_indicator): at a vertex on the
#: ground (phi = 0, reach 1 cm) it adds 5e-6 of the saturated psi, so a resting vertex
#: under load costs nothing.  The algebraic tail of smooth_pos (eps²/4r, 0.25 % there)
#: priced the weight itself and pulled the mass of pushed boxes away (bench_estimate,
#: median mass error 21 % -> 30 % on seeds 0-5)
REACH_SMOOTHING = 1e-3


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


#: smoothing of the smaller of a fingertip's two gaps at an interval's ends, in units of
#: sigma_gap (:func:`interval_gap`): equal gaps give their value exactly; gaps far apart
#: give the smaller one plus this (0.1 sigma_gap = 50 um at the default 0.5 mm)
INTERVAL_GAP_SMOOTHING = 0.1


def interval_gap(phi_start, phi_end, eps):
    """Smoothed smaller of a fingertip's gaps (m) at an interval's two ends: how close it
    came to the object over the interval (the gap between two 10 ms samples is close to
    monotone).  (a + b)/2 - sqrt(((a - b)/2)² + eps²) + eps: exactly a where a = b (no
    bias along a sustained touch), min(a, b) + eps where |a - b| >> eps, smooth."""
    half = 0.5 * (phi_start - phi_end)
    return 0.5 * (phi_start + phi_end) - ca.sqrt(half * half + eps * eps) + eps


def contact_residual(phi_f, contact, weight, sigma_gap, phi_start=None, ends=None):
    """Whitened contact-flag residual of one fingertip: where the flag is 1, its gap phi_f
    (m) at the interval's end, or, at the last sample of a touch (``ends`` 1, with
    ``phi_start`` its gap at the interval's start), the smaller of the gaps at the two
    ends (:func:`interval_gap`); where the flag is 0, its (smoothed) penetration at the end.

    The flag covers the interval (t[k-1], t[k]] (SPEC).  Within a touch the fingertip
    is on the surface at the interval's end (the touch goes on past it); at its last
    sample it let go inside the interval (or, for a touch of one sample, struck and
    bounced).  A fingertip that withdraws at 0.5 m/s is 5 mm (10 sigma_gap) away at the
    end of a 10 ms interval: the end's gap charged that 50 units, and fits of fast pokes
    bent the shape to avoid it (docs/estimation.md, "The interval of a tactile
    sample")."""
    touched = phi_f
    if phi_start is not None:
        touched = ends * interval_gap(phi_start, phi_f, INTERVAL_GAP_SMOOTHING * sigma_gap) + (1 - ends) * phi_f
    return weight * (contact * touched / sigma_gap + (1 - contact) * one_sided(phi_f, sigma_gap))


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
