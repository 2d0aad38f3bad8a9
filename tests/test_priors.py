"""The friction prior (tacest.model.priors): log-normal by default, normal on request, one
definition for the 2-D and 3-D problems, the shooting method and planning."""

from __future__ import annotations

import dataclasses
import math

import casadi as ca
import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.estimation.config import EstimatorConfig, load_config
from tacest.information.expected import prior_information
from tacest.model.priors import (FRICTION, FRICTION_LOG_SIGMA, PRIOR_HEAD, friction_information, friction_residual,
                                 prior_head)
from tests.test_estimator import _problem_point


def _prior(**changes):
    base = EstimatorConfig().prior
    return dataclasses.replace(base, **changes)


def _residual(mu, prior):
    return float(ca.DM(friction_residual(mu, ca.DM(prior_head(prior)))))


def test_the_default_friction_prior_is_log_normal_around_its_median():
    prior = _prior()
    assert prior.friction_log_sigma > 0
    assert _residual(prior.friction, prior) == pytest.approx(0.0, abs=1e-15)
    # one sigma is a factor exp(sigma_log) either way: symmetric in log mu
    up = _residual(prior.friction * math.exp(prior.friction_log_sigma), prior)
    down = _residual(prior.friction / math.exp(prior.friction_log_sigma), prior)
    assert up == pytest.approx(1.0, rel=1e-12) and down == pytest.approx(-1.0, rel=1e-12)


def test_a_frictionless_ground_costs_what_the_log_normal_prior_says():
    """The point of the log-normal prior: mu at the estimators' bound (0.01) is
    ln(0.01 / 0.5) / 0.7 = 5.6 sigma (15.6 objective units), where the normal prior of
    sigma 1 charged 0.12."""
    lognormal, normal = _prior(), _prior(friction_log_sigma=0.0)
    assert 0.5 * _residual(0.01, lognormal) ** 2 == pytest.approx(0.5 * (math.log(0.02) / 0.7) ** 2, rel=1e-12)
    assert 0.5 * _residual(0.01, lognormal) ** 2 > 15.0
    assert 0.5 * _residual(0.01, normal) ** 2 == pytest.approx(0.5 * 0.49 ** 2, rel=1e-12)


def test_friction_log_sigma_zero_is_the_normal_prior():
    prior = _prior(friction_log_sigma=0.0, friction_sigma=0.25)
    assert _residual(0.75, prior) == pytest.approx(1.0, rel=1e-12)
    assert friction_information(0.75, prior) == pytest.approx(16.0, rel=1e-12)


@pytest.mark.parametrize("mu", [0.05, 0.5, 1.9])
def test_friction_information_is_the_squared_derivative_of_the_residual(mu):
    """Central differences of the residual (step 1e-6 μ: truncation ~1e-12 relative)."""
    prior = _prior()
    h = 1e-6 * mu
    d = (_residual(mu + h, prior) - _residual(mu - h, prior)) / (2 * h)
    assert friction_information(mu, prior) == pytest.approx(d * d, rel=1e-7)


def test_prior_head_order_is_the_stage_models():
    head = prior_head(_prior(friction=0.4, friction_log_sigma=0.6))
    assert len(head) == len(PRIOR_HEAD)
    assert head[FRICTION] == 0.4 and head[FRICTION_LOG_SIGMA] == 0.6 and head[PRIOR_HEAD.index("on")] == 1.0


@pytest.mark.parametrize("friction_log_sigma", [0.7, 0.0])
def test_the_2d_prior_hessian_is_jtj_of_the_prior_residuals(friction_log_sigma):
    """problem.prior_hessian (the priors' information in the observed information) is the
    Gauss–Newton JᵀJ of the prior residuals, checked against central differences of
    the residuals (step 1e-6: truncation ~1e-12, rounding ~1e-10 relative), at a
    friction of 1.8 where the log-normal prior's exact Hessian is negative."""
    est, pr, z, p = _problem_point("box")
    if friction_log_sigma == 0.0:
        config = dataclasses.replace(est.config, prior=_prior(friction_log_sigma=0.0))
        from tacest.estimation.data import parameter_vector

        p = parameter_vector(pr, est.runs, est.scales, config, 0.5, 2.0, est.s0, ridge=0.0)
    theta = np.asarray(z[: pr.n_theta], float).copy()
    theta[pr.n_shape + 2] = 1.8  # ground friction
    pv = pr.prior_values(p)
    th = ca.SX.sym("th", pr.n_theta)
    res = ca.Function("r", [th], [pr.prior_residual(th, ca.DM(pv))])
    h = 1e-6
    J = np.column_stack([(np.asarray(res(theta + h * e)).ravel() - np.asarray(res(theta - h * e)).ravel()) / (2 * h)
                         for e in np.eye(pr.n_theta)])
    H = pr.prior_hessian(theta, p)
    np.testing.assert_allclose(H, J.T @ J, rtol=1e-6, atol=1e-9)
    k = pr.n_shape + 2
    assert H[k, k] > 0
    expected = friction_information(1.8, est.config.prior if friction_log_sigma else _prior(friction_log_sigma=0.0))
    assert H[k, k] == pytest.approx(expected, rel=1e-6)


def test_planning_prior_information_uses_the_same_friction_prior():
    from types import SimpleNamespace

    model = SimpleNamespace(mass=0.3, friction_ground=0.2, friction_finger=0.9)
    config = EstimatorConfig()
    info = prior_information(["friction_ground", "friction_finger"], model, config, 0.1)
    np.testing.assert_allclose(np.diag(info), [friction_information(0.2, config.prior),
                                               friction_information(0.9, config.prior)], rtol=1e-12)


def test_a_log_normal_prior_needs_a_positive_median(tmp_path):
    with pytest.raises(TacestError, match="prior.friction"):
        load_config(None, {"prior": {"friction": 0.0}})
    # the normal prior may be centred at zero
    assert load_config(None, {"prior": {"friction": 0.0, "friction_log_sigma": 0.0}}).prior.friction == 0.0
    with pytest.raises(TacestError, match="friction_log_sigma"):
        load_config(None, {"prior": {"friction_log_sigma": -1.0}})
