"""Helmholtz–Hodge decomposition (tacest.sensors.hhd): known-answer recovery and invariants."""

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.sensors.hhd import curl, divergence, gradient, hhd, rotated_gradient, solve_poisson_free_space

H, W = 64, 80
Y, X = np.mgrid[0:H, 0:W].astype(float)

#: Width of the test bumps in grid cells.  Central differences and the sampled Green's
#: function are second order, so the relative error is ~ c (h / sigma)^2; measured
#: 2.0 % (curl-free, sigma = 6) and 3.1 % (div-free, sigma = 4.8), and it falls 4x when
#: sigma doubles (checked in test_error_is_second_order).
SIGMA_PHI, SIGMA_PSI = 6.0, 4.8
#: Relative RMS tolerance: (h / sigma)^2 = 1/23 for the narrower bump, plus margin.
REL_TOL = 0.05


def _bump(cx, cy, s, a):
    """Gaussian a exp(-r^2 / 2 s^2) and its analytic gradient (d/dx, d/dy)."""
    g = a * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * s * s))
    return g, np.stack([-(X - cx) / s ** 2 * g, -(Y - cy) / s ** 2 * g], -1)


def _field(scale=1.0):
    # bumps well inside the grid (>= 4.5 sigma from every edge: their tails there are
    # < 1e-4 of the peak, so the free-space solution is the bump itself)
    _, grad_phi = _bump(32, 30, SIGMA_PHI * scale, 20.0 * scale)
    _, grad_psi = _bump(50, 34, SIGMA_PSI * scale, -15.0 * scale)
    rot_psi = np.stack([-grad_psi[..., 1], grad_psi[..., 0]], -1)
    const = np.array([0.7, -0.3])
    return grad_phi, rot_psi, const


def _rel(a, b):
    return np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b ** 2))


def test_recovers_gradient_rotated_gradient_and_constant():
    grad_phi, rot_psi, const = _field()
    r = hhd(grad_phi + rot_psi + const)
    assert _rel(r.curl_free, grad_phi) < REL_TOL
    assert _rel(r.div_free, rot_psi) < REL_TOL
    # the constant (a uniform translation: no div, no curl) lands in the harmonic part;
    # what else is there is the other parts' truncation error, bounded by the same
    # (h/sigma)^2 relative to their peak (~2 px): 0.2 px max over the grid
    assert np.max(np.abs(r.harmonic - const)) < 0.1 * np.max(np.abs(grad_phi))
    assert np.allclose(r.harmonic.mean(axis=(0, 1)), const, atol=0.02)


def test_error_is_second_order():
    """Twice as wide bumps (in cells) -> about 4x smaller error: the scheme is second order."""
    e1 = _rel(hhd(_field(1.0)[0]).curl_free, _field(1.0)[0])
    e2 = _rel(hhd(_field(1.5)[0]).curl_free, _field(1.5)[0])
    # (1.5)^2 = 2.25 expected; accept anything better than 1.8x (first order would give 1.5x)
    assert e1 / e2 > 1.8


def test_parts_are_nearly_orthogonal_and_div_curl_free():
    grad_phi, rot_psi, const = _field()
    r = hhd(grad_phi + rot_psi + const)

    def cos(a, b):
        return np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b))

    # exact orthogonality holds in the continuum only; the truncation error (~3 %, see
    # REL_TOL) leaks into the inner products, so allow 0.05
    assert abs(cos(r.curl_free, r.div_free)) < 0.05
    assert abs(cos(r.curl_free, r.harmonic)) < 0.05
    assert abs(cos(r.div_free, r.harmonic)) < 0.05
    # central differences commute, so div(J grad psi) and curl(grad phi) vanish to rounding
    assert np.max(np.abs(divergence(r.div_free))) < 1e-9 * np.max(np.abs(r.div))
    assert np.max(np.abs(curl(r.curl_free))) < 1e-9 * np.max(np.abs(r.curl))
    # and the potentials' Laplacians match the input's div and curl in the interior
    # (the wide central-difference Laplacian vs the sampled Green's function: 10 % of peak)
    inner = (slice(4, -4), slice(4, -4))
    lap_phi = divergence(gradient(r.phi))
    assert np.max(np.abs((lap_phi - r.div)[inner])) < 0.1 * np.max(np.abs(r.div))
    curl_d = curl(rotated_gradient(r.psi))
    assert np.max(np.abs((curl_d - r.curl)[inner])) < 0.1 * np.max(np.abs(r.curl))


def test_pure_translation_and_rotation():
    # a uniform field is all harmonic
    r = hhd(np.broadcast_to([1.5, -2.0], (20, 30, 2)).copy())
    assert np.allclose(r.curl_free, 0, atol=1e-12) and np.allclose(r.div_free, 0, atol=1e-12)
    # a rigid rotation about the centre has curl 2 and no divergence: no curl-free part
    y, x = np.mgrid[0:21, 0:21].astype(float) - 10
    r = hhd(np.stack([-y, x], -1) * 0.01)
    assert np.allclose(r.curl_free, 0, atol=1e-12)
    assert np.allclose(r.curl, 0.02)


def test_spacing_scales_potentials_not_fields():
    grad_phi, rot_psi, const = _field()
    f = grad_phi + rot_psi + const
    r1, r2 = hhd(f, spacing=1.0), hhd(f, spacing=8.0)
    # the field is given in the same units; with 8x the spacing, div and curl are 8x
    # smaller and the potentials 8x larger, the parts identical (up to rounding)
    assert np.allclose(r1.curl_free, r2.curl_free, atol=1e-9)
    assert np.allclose(r1.div * 1 / 8, r2.div)


def test_free_space_poisson_of_point_source_is_log():
    # lap u = delta (unit mass in one cell) -> u = ln(r) / 2 pi away from the source
    src = np.zeros((41, 41))
    src[20, 20] = 1.0
    u = solve_poisson_free_space(src)
    r = np.hypot(np.arange(41) - 20.0, 0)
    assert np.allclose(u[20, 25:], np.log(r[25:]) / (2 * np.pi))


def test_bad_input():
    with pytest.raises(TacestError, match="shape"):
        hhd(np.zeros((10, 10)))
    with pytest.raises(TacestError, match="at least 3"):
        hhd(np.zeros((2, 10, 2)))
    f = np.zeros((10, 10, 2))
    f[3, 3, 0] = np.nan
    with pytest.raises(TacestError, match="NaN"):
        hhd(f)


def test_mask_ignores_the_edge_of_the_data():
    """Flow only inside a disc (a dome image: no dots outside the rim).  Without a mask
    the disc's edge is a sheet of sources and vortices that claims the translation; with
    it, the translation inside is harmonic, as it should be."""
    rng = np.random.default_rng(0)
    r = np.hypot(X - 40, Y - 32)
    disc = r < 28
    f = np.where(disc[..., None], np.array([1.0, -0.5]), rng.normal(0, 0.3, (H, W, 2)))
    _, grad_phi = _bump(38, 30, SIGMA_PHI, 20.0)
    f = f + np.where(disc[..., None], grad_phi, 0.0)
    res = hhd(f, mask=disc)
    inner = r < 24
    assert np.allclose(res.harmonic[inner].mean(axis=0), [1.0, -0.5], atol=0.02)
    assert _rel(res.curl_free[inner], grad_phi[inner]) < REL_TOL
    unmasked = hhd(f)
    assert not np.allclose(unmasked.harmonic[inner].mean(axis=0), [1.0, -0.5], atol=0.2)
