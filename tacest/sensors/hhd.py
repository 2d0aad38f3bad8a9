"""Helmholtz–Hodge decomposition (HHD) of a 2-D vector field on a regular grid.

A flow field ``f`` (H, W, 2) is split into three parts::

    f = grad(phi) + J grad(psi) + h
        curl-free     div-free     harmonic remainder

with ``J grad(psi) = (-d psi/dy, d psi/dx)`` (grad rotated by +90 degrees), so that
``div grad(phi) = lap(phi) = div f`` and ``curl J grad(psi) = lap(psi) = curl f``.
Component 0 of a field is along x (image columns, to the right), component 1 along y
(image rows, downwards); ``curl f = d f_y/dx - d f_x/dy``.

Boundary handling: the *natural* HHD (Bhatia, Pascucci, Bremer, "The Natural
Helmholtz-Hodge Decomposition for Open-Boundary Flow Analysis", IEEE TVCG 2014).
The image is a window onto a larger membrane, not a walled box, so no boundary
condition is imposed: the potentials are the free-space solutions of Poisson's equation
driven only by the divergence and curl *inside* the window,

    phi = G * div f,   psi = G * curl f,   G(r) = ln(r) / (2 pi),

and everything that the interior sources cannot explain -- a uniform translation (shear
of the gel, camera shake), influences from outside the window -- is left in the harmonic
remainder ``h`` (div h = curl h = 0 up to discretisation).  The convolutions are linear,
not circular: both operands are zero-padded to at least (2H-1, 2W-1) before the FFT, so
there are no periodic artefacts (the usual pitfall of an FFT Poisson solve).  A
DCT-based Neumann solve (scipy.fft.dctn) was the alternative; it forces
``grad(phi) . n = 0`` on the image border, which pushes a contact near the border into
the harmonic part and ties the split to where the image happens to be cropped.

Discretisation: divergence and curl by second-order central differences (one-sided at
the edges, ``np.gradient`` with ``edge_order=2``), the Green's function sampled at the
cell offsets with its cell average at r = 0, gradients of the potentials by the same
central differences.  Everything is second order in h / (length scale of the field).

Cost: two FFTs of a complex (2H, 2W) array per call (div and curl are transformed
together as ``div + i curl``); on the coarse grid used for tactile flow (about 60 x 80)
this is well under a millisecond.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.fft

from tacest.errors import TacestError

#: Mean of ln(r) over a unit square centred on r = 0: (ln 2)/2 - 3/2 + pi/4 - ln 2.
#: (Exact: integrate ln r in polar coordinates over the 8 triangles of the square.)
_MEAN_LOG_UNIT_CELL = -0.5 * np.log(2.0) - 1.5 + np.pi / 4.0


@dataclass
class HHDResult:
    """The three parts of a field and their potentials (all on the input grid).

    curl_free, div_free, harmonic : (H, W, 2) float, same units as the input field
    phi, psi : (H, W) float, potential and stream function (field units x spacing)
    div, curl : (H, W) float, divergence and curl of the input field (field units / spacing)
    """

    curl_free: np.ndarray
    div_free: np.ndarray
    harmonic: np.ndarray
    phi: np.ndarray
    psi: np.ndarray
    div: np.ndarray
    curl: np.ndarray


def divergence(field: np.ndarray, spacing: float = 1.0) -> np.ndarray:
    """div f = d f_x/dx + d f_y/dy of ``field`` (H, W, 2) -> (H, W), central differences."""
    fx, fy = field[..., 0], field[..., 1]
    return _ddx(fx, spacing) + _ddy(fy, spacing)


def curl(field: np.ndarray, spacing: float = 1.0) -> np.ndarray:
    """Scalar curl d f_y/dx - d f_x/dy of ``field`` (H, W, 2) -> (H, W)."""
    fx, fy = field[..., 0], field[..., 1]
    return _ddx(fy, spacing) - _ddy(fx, spacing)


def gradient(scalar: np.ndarray, spacing: float = 1.0) -> np.ndarray:
    """grad s of ``scalar`` (H, W) -> (H, W, 2) as (d/dx, d/dy)."""
    return np.stack([_ddx(scalar, spacing), _ddy(scalar, spacing)], axis=-1)


def rotated_gradient(scalar: np.ndarray, spacing: float = 1.0) -> np.ndarray:
    """J grad s = (-d s/dy, d s/dx) of ``scalar`` (H, W) -> (H, W, 2); divergence-free."""
    return np.stack([-_ddy(scalar, spacing), _ddx(scalar, spacing)], axis=-1)


def _ddx(a, h):
    if a.shape[1] < 3:
        raise TacestError(f"HHD needs a grid of at least 3 x 3 cells, got {a.shape}")
    return np.gradient(a, h, axis=1, edge_order=2)


def _ddy(a, h):
    if a.shape[0] < 3:
        raise TacestError(f"HHD needs a grid of at least 3 x 3 cells, got {a.shape}")
    return np.gradient(a, h, axis=0, edge_order=2)


@lru_cache(maxsize=16)
def _green_fft(H: int, W: int, spacing: float):
    """FFT of the free-space Green's function G(r) = ln(r)/(2 pi) times the cell area,
    laid out for a linear convolution of an (H, W) array; returns (fft, (Hp, Wp))."""
    Hp = scipy.fft.next_fast_len(2 * H - 1)
    Wp = scipy.fft.next_fast_len(2 * W - 1)
    iy = np.arange(Hp)
    ix = np.arange(Wp)
    # wrap-around offsets: 0..H-1 then negative offsets at the end of the padded axis
    oy = np.where(iy < H, iy, iy - Hp).astype(float)
    ox = np.where(ix < W, ix, ix - Wp).astype(float)
    r = np.hypot(oy[:, None], ox[None, :]) * spacing
    with np.errstate(divide="ignore"):
        g = np.log(r)
    g[0, 0] = np.log(spacing) + _MEAN_LOG_UNIT_CELL  # cell average of ln r at r = 0
    # offsets that no pair of cells can have (|oy| >= H or |ox| >= W) are padding
    g[(np.abs(oy) >= H)[:, None] | (np.abs(ox) >= W)[None, :]] = 0.0
    g *= spacing * spacing / (2.0 * np.pi)
    return scipy.fft.fft2(g), (Hp, Wp)


def solve_poisson_free_space(source: np.ndarray, spacing: float = 1.0) -> np.ndarray:
    """Free-space solution u = G * source of lap(u) = source, ``source`` (H, W) real or
    complex, zero outside the grid.  Returns (H, W), same dtype kind as ``source``."""
    H, W = source.shape
    G, (Hp, Wp) = _green_fft(H, W, float(spacing))
    out = scipy.fft.ifft2(scipy.fft.fft2(source, s=(Hp, Wp)) * G)[:H, :W]
    return out if np.iscomplexobj(source) else out.real


def hhd(field: np.ndarray, spacing: float = 1.0, mask: np.ndarray | None = None) -> HHDResult:
    """Natural Helmholtz–Hodge decomposition of ``field``.

    Parameters
    ----------
    field : (H, W, 2) float, e.g. optical flow in px; component 0 along x (columns),
        component 1 along y (rows).  H, W >= 3.
    spacing : float, grid spacing in the units of x and y (e.g. px per grid cell).
    mask : optional (H, W) bool, the domain where the field is data (e.g. the dome's
        disc in a tactile image).  Divergence and curl count as sources only where the
        cell and its four neighbours are in the domain (the central differences then use
        data only); outside it the field is ignored, so the edge of the data (a rim with
        flow inside and none outside) is not mistaken for a sheet of sources and
        vortices.  The parts are returned on the whole grid; they mean something inside.

    Returns
    -------
    HHDResult with ``curl_free = grad(phi)``, ``div_free = J grad(psi)`` and
    ``harmonic = field - curl_free - div_free``.
    """
    f = np.asarray(field, dtype=float)
    if f.ndim != 3 or f.shape[2] != 2:
        raise TacestError(f"HHD needs a field of shape (H, W, 2), got {f.shape}")
    if not np.all(np.isfinite(f)):
        raise TacestError("HHD input contains NaN or inf")
    d = divergence(f, spacing)
    c = curl(f, spacing)
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.shape != f.shape[:2]:
            raise TacestError(f"HHD mask has shape {m.shape}, the field {f.shape[:2]}")
        inner = m.copy()
        inner[1:, :] &= m[:-1, :]
        inner[:-1, :] &= m[1:, :]
        inner[:, 1:] &= m[:, :-1]
        inner[:, :-1] &= m[:, 1:]
        d = np.where(inner, d, 0.0)
        c = np.where(inner, c, 0.0)
    pot = solve_poisson_free_space(d + 1j * c, spacing)
    phi, psi = pot.real, pot.imag
    cf = gradient(phi, spacing)
    dfree = rotated_gradient(psi, spacing)
    return HHDResult(curl_free=cf, div_free=dfree, harmonic=f - cf - dfree, phi=phi, psi=psi, div=d, curl=c)
