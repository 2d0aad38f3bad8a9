"""Model augmentations inside the 2-D estimator's NLP (effects=) and fixed-parameter fits
(fixed=): derivatives, structure, "no effect" equals the plain model, bad names."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.data import choose_scales, parameter_vector
from tacest.dims import estimate_runs
from tacest.estimation.estimator import ImplicitEstimator
from tacest.estimation.initial import initial_guess
from tacest.estimation.problem2d import Problem2D, RunStructure
from tacest.model.registry import model_effect_names
from tacest.model.stage2d import PHYS_NAMES, TERMS

NLP_EFFECTS = model_effect_names(2)
from tacest.geometry.shapes import make_shape
from tests.nlp_checks import FD_RTOL, FD_STEP, assert_derivatives_match_finite_differences
from tests.test_estimator import pushed_box_run

ALL = tuple(NLP_EFFECTS)


def _point(shape, effects, seed=0):
    """A generic point (z, p) of the NLP with effects, near the start; effect parameters
    set away from "no effect" (0.1 scaled, inside every bound)."""
    run = pushed_box_run()
    est = ImplicitEstimator([run], shape, effects=effects)
    pr = est.problem
    rng = np.random.default_rng(seed)
    z = initial_guess(pr, [run], est.scales, est.s0)
    a = pr.n_shape + len(PHYS_NAMES)
    z[a: a + pr.n_eff] = 0.1
    z[pr.phys_offset: pr.phys_offset + pr.n_phys] = np.asarray(
        pr.phys_sx(z[: pr.n_theta], est.scales.L, est.scales.m0)).reshape(-1)
    # perturbation 0.02 (scaled): inside every smooth region, away from symmetric values
    z = z + rng.normal(size=pr.n_z) * 0.02
    p = parameter_vector(pr, [run], est.scales, est.config, 0.5, 2.0, est.s0, ridge=0.0)
    return est, pr, z, p


@pytest.mark.parametrize("shape", ["box", "polygon:5"])
def test_gradient_and_jacobian_with_every_effect_match_finite_differences(shape):
    est, pr, z, p = _point(shape, ALL)
    z = _with_impacts(est, pr, z)
    # the objective is large here (the effects move the generic point far from the data):
    # its own rounding, eps·|f| / h, with a factor 10 of margin joins the tolerance.
    # Every coordinate of the per-sample states (the plate's sinks, the impact memory)
    # is checked too
    a, n = pr.offsets[0]["S"]
    assert n == (1 + pr.K) * pr.structures[0].T
    assert_derivatives_match_finite_differences(pr, z, p, f_rounding_margin=10.0, extra=range(a, a + n))


def _with_impacts(est, pr, z, seed=7):
    """z with the object's velocities stirred (±0.5 m/s, ±5 rad/s: vertices approach
    the ground at up to ~1 m/s) and restitution's impact memory at 0-1 m/s, so that the
    impact law and the interval after an impact are both active where derivatives are
    checked (at the start's slow push their gates are ~0)."""
    rng = np.random.default_rng(seed)
    z = z.copy()
    Q, V, _, _ = pr.run_blocks(z, 0)
    V = V + rng.normal(size=V.shape) * np.array([[0.5 / est.scales.L], [0.5 / est.scales.L], [5.0]])
    pr.set_run_blocks(z, 0, V=V)
    S = pr.state_block(z, 0)
    memory = pr.state_slices["restitution"]
    S[memory] = rng.uniform(0.0, 1.0, size=S[memory].shape)
    pr.set_run_blocks(z, 0, S=S)
    return z


def test_information_jacobian_with_every_effect_matches_finite_differences():
    """The residual Jacobian the information is built from (problem2d.ResidualJacobian2D,
    assembled from per-sample blocks) matches central differences of its own residuals in
    every parameter, every plate sink and 40 other coordinates, with every effect in the NLP."""
    est, pr, z, p = _point("box", ALL)
    z = _with_impacts(est, pr, z)
    rj = pr.residual_jacobian
    r0, J = rj(z, p)
    J = np.asarray(ca.DM(J))
    a, n = pr.offsets[0]["S"]
    idx = list(range(pr.n_theta + pr.n_phys)) + list(range(a, a + n)) \
        + np.random.default_rng(4).choice(pr.n_z, 40, replace=False).tolist()
    h = FD_STEP
    for i in idx:
        e = np.zeros(pr.n_z)
        e[i] = h
        fd = (np.asarray(rj(z + e, p)[0]).ravel() - np.asarray(rj(z - e, p)[0]).ravel()) / (2 * h)
        # FD_RTOL as the objective's check (nlp_checks), relative to the column's size
        np.testing.assert_allclose(fd, J[:, i], rtol=FD_RTOL, atol=FD_RTOL * max(1.0, np.abs(J[:, i]).max()),
                                   err_msg=str(i))


def test_exact_hessian_blocks_with_every_effect_match_casadi():
    """The per-sample block Hessian stays exact with the effect parameters in phys."""
    est, pr, z, p = _point("box", ALL)
    z = _with_impacts(est, pr, z)
    lam_g = np.random.default_rng(2).normal(size=pr.g.shape[0])
    mine = np.asarray(ca.DM(pr.hess_lag["exact"](z, p, 0.7, lam_g)))
    lag = 0.7 * pr.f_reference + ca.dot(ca.DM(lam_g), pr.g)
    ref = np.asarray(ca.DM(ca.Function("h", [pr.z_sym, pr.p_sym],
                                       [ca.triu(ca.hessian(lag, pr.z_sym)[0])])(z, p)))
    # both exact symbolic derivatives: they differ by rounding only
    np.testing.assert_allclose(mine, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


def test_no_effects_leaves_the_nlp_as_it_is():
    shape = make_shape("box", dim=2)
    st = [RunStructure(T=24, F=1)]
    plain = Problem2D(shape, st, EstimatorConfig())
    none = Problem2D(shape, st, EstimatorConfig(), effects=())
    assert (none.n_z, none.g.shape[0], none.n_p_total, none.n_theta) == \
        (plain.n_z, plain.g.shape[0], plain.n_p_total, plain.n_theta)
    # the size the plain layout has: theta (2 + 4), phys (2K + 4), per sample q, v (6),
    # per interval ground (2K) and finger (2F) impulses
    K, T, F = 4, 24, 1
    assert plain.n_z == 6 + (2 * K + 4) + 6 * T + (2 * K + 2 * F) * (T - 1)
    with_drag = Problem2D(shape, st, EstimatorConfig(), effects=("linear_drag", "force_bias"))
    assert with_drag.n_z == plain.n_z + 2 * 3  # 3 parameters, in theta and in phys
    assert with_drag.g.shape[0] == plain.g.shape[0] + 3  # their lifting constraints


@pytest.mark.parametrize("effect", [e for e in ALL if e != "restitution"])
def test_an_effect_at_no_effect_reproduces_the_plain_objective(effect):
    """Each augmentation at its "no effect" value (every effect parameter 0: gain 1, no
    bias, no drag, a rigid ground, equal face frictions, COM at the centroid) gives the
    plain model's objective at the same trajectories (restitution adds an impact residual
    that is not 0 at e = 0: a plastic impact, the plain model's implicit assumption)."""
    run = pushed_box_run()
    cfg = EstimatorConfig()
    plain = ImplicitEstimator([run], "box", cfg)
    aug = ImplicitEstimator([run], "box", cfg, effects=(effect,))
    pp, pa = plain.problem, aug.problem
    z_p = initial_guess(pp, [run], plain.scales, plain.s0) + np.random.default_rng(3).normal(size=pp.n_z) * 0.02
    z_p[pp.phys_offset: pp.phys_offset + pp.n_phys] = np.asarray(
        pp.phys_sx(z_p[: pp.n_theta], plain.scales.L, plain.scales.m0)).reshape(-1)
    n_eff = pa.n_eff
    # the augmented z: theta + zeros, phys + zeros, the same run blocks (then, with
    # soft_contact, the plate's sinks: 0, the rigid ground's; one run, so they come last)
    z_a = np.concatenate([z_p[: pp.n_theta], np.zeros(n_eff), z_p[pp.n_theta: pp.n_theta + pp.n_phys],
                          np.zeros(n_eff), z_p[pp.n_theta + pp.n_phys:], np.zeros(pa.n_state * run.n_samples)])
    assert z_a.size == pa.n_z
    p_p = parameter_vector(pp, [run], plain.scales, cfg, 0.5, 2.0, plain.s0)
    p_a = parameter_vector(pa, [run], aug.scales, cfg, 0.5, 2.0, aug.s0)
    f_p = float(ca.Function("f", [pp.z_sym, pp.p_sym], [pp.f])(z_p, p_p))
    f_a = float(ca.Function("f", [pa.z_sym, pa.p_sym], [pa.f])(z_a, p_a))
    # the same arithmetic up to the order of operations: rounding only
    assert f_a == pytest.approx(f_p, rel=1e-10)
    assert f_p > 1.0  # a generic point: the comparison is not between two zeros


def test_force_scale_is_the_same_model_as_a_scaled_mass():
    """A sensor gain g is the same data as a mass g times as large: with force_scale, the
    point (mass/c, impulses/c, gain·c) has every loss term of (mass, impulses, gain), the
    physics residuals included (they see forces in the sensor's units), so only a mass
    prior can split gain and mass; without that factor a gain above 1 shrank every
    physics residual."""
    c = 1.7

    def lifted(est, pr, z):  # z with its phys block recomputed from its theta
        z[pr.phys_offset: pr.phys_offset + pr.n_phys] = np.asarray(
            pr.phys_sx(z[: pr.n_theta], est.scales.L, est.scales.m0)).reshape(-1)
        return z

    def scaled(est, pr, z, gain_too):  # mass and impulses / c (and the gain × c)
        z2 = z.copy()
        a = pr.n_shape
        z2[a + PHYS_NAMES.index("log_mass")] -= np.log(c)
        if gain_too:
            z2[a + len(PHYS_NAMES) + pr.eff_index["force_scale.log_gain"]] += np.log(c)
        z2 = lifted(est, pr, z2)
        _, _, LG, LF = pr.run_blocks(z2, 0)
        return pr.set_run_blocks(z2, 0, LG=LG / c, LF=LF / c)

    def terms(pr, z, p):
        return np.asarray(pr.term_fun(z, p)[0]).ravel()

    est, pr, z, p = _point("box", ("force_scale",))
    z = lifted(est, pr, z)
    t1, t2 = terms(pr, z, p), terms(pr, scaled(est, pr, z, True), p)
    # the same arithmetic up to the order of operations (c and 1/c): rounding only
    np.testing.assert_allclose(t2, t1, rtol=1e-9)
    # compared away from zero: the force term and the physics terms are not 0 here
    # (this run has no pose observations, so no pose or Occam term)
    for term in ("force", "dynamics", "complementarity", "cone", "dissipation"):
        assert t1[TERMS.index(term)] > 1.0, term
    # the plain model has no such symmetry: its physics residuals change with the mass
    est0, pr0, zp, pp = _point("box", ())
    assert not np.allclose(terms(pr0, scaled(est0, pr0, zp, False), pp), terms(pr0, zp, pp), rtol=1e-3)


def test_unknown_or_transform_effect_is_one_clear_error():
    run = pushed_box_run()
    with pytest.raises(TacestError) as exc:
        estimate_runs([run], "box", effects=("bouncyness",))
    msg = str(exc.value)
    assert "bouncyness" in msg and "\n" not in msg and "restitution" in msg
    with pytest.raises(TacestError) as exc:
        estimate_runs([run], "box", effects=("latency",))
    assert "data transform" in str(exc.value) and "\n" not in str(exc.value)


def test_fixed_holds_every_parameter_and_fits_the_trajectories():
    """A fit with an effect, then the same data with everything of it held fixed: the
    parameters come back unchanged (to the pinning interval, 1e-9 scaled) and the fit
    is at least as good as the free one's (its trajectories start the solve)."""
    run = pushed_box_run()
    free = estimate_runs([run], "box", effects=("linear_drag",))
    assert free.success, free.solver_status
    assert "linear_drag.b" in free.params and "linear_drag.b" in free.info_names
    assert free.model == ["linear_drag"]
    held = estimate_runs([run], "box", effects=("linear_drag",), fixed=free)
    assert held.success, held.solver_status
    sc = choose_scales([run], EstimatorConfig())
    for k in ("mass", "inertia", "friction_ground", "friction_finger", "linear_drag.b"):
        # 1e-9 scaled half-width; b's unit is m0 (kg/s), mass is exp(scaled): relative 1e-8 is ample
        assert held.params[k] == pytest.approx(free.params[k], rel=1e-8, abs=1e-8 * sc.m0), k
    np.testing.assert_allclose(held.vertices, free.vertices, atol=1e-8 * sc.L)
    # the objective includes the priors, which are equal; IPOPT's acceptable tolerance
    # allows the objective to change by 1e-3 of itself (solver.py)
    assert held.objective <= free.objective * (1 + 1e-3) + 1e-6
    # refit_shape: everything but the shape held; the shape may move from the fixed one
    refit = estimate_runs([run], "box", effects=("linear_drag",), fixed=free, refit_shape=True)
    assert refit.success, refit.solver_status
    for k in ("mass", "friction_ground", "linear_drag.b"):
        assert refit.params[k] == pytest.approx(free.params[k], rel=1e-8, abs=1e-8 * sc.m0), k


@pytest.mark.parametrize("shape", ["box", "polygon:5"])
def test_effect_parameters_round_trip_through_physical_units(shape):
    """Every effect's report (scaled theta -> an estimate's /params, physical units) and
    scaled (back) are inverses, for every effect at once: the fixed= fits and the
    diagnosis' bound check read effect parameters through them (estimator.theta_of).
    Tolerance 1e-12 relative: a product and a quotient by the same unit (or exp and log)
    in double precision."""
    from tacest.estimation.estimator import theta_of
    from tacest.io.estimate import Estimate

    est, pr, z, _ = _point(shape, ALL)
    est.p_final = parameter_vector(pr, est.runs, est.scales, est.config, 0.3, 1.0, est.s0)
    V, mass, inertia, mu_g, mu_f = est.physical(z)
    params = dict(est.effect_params(z), mass=mass, inertia=inertia, friction_ground=mu_g, friction_finger=mu_f)
    fake = Estimate(dim=2, shape=shape, vertices=V, params=params, runs=[])
    theta = z[: pr.n_theta]
    a = pr.n_shape + len(PHYS_NAMES)
    np.testing.assert_allclose(theta_of(est, fake)[a:], theta[a: a + pr.n_eff], rtol=1e-12, atol=1e-14)
    with pytest.raises(TacestError, match="linear_drag.b"):
        theta_of(est, Estimate(dim=2, shape=shape, vertices=V, runs=[],
                               params={k: v for k, v in params.items() if k != "linear_drag.b"}))
