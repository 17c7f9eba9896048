"""Local linearisation of the lens mapping for small sources (clumps).

A clump much smaller than the scale on which the lens Jacobian A = ∂β/∂θ
changes is imaged, near each image position θ_k, as the same Sérsic seen
through the linear map A_k: I(θ) = S(β_k + A_k (θ − θ_k)). That is again an
elliptical Sérsic — flux × |μ_k|, R_e and axis ratio from the eigenvalues of
(D R A_k)ᵀ(D R A_k) — which can be integrated over detector pixels directly,
with no rays at all. Near a caustic the approximation fails (the image is a
merging arc and |μ| varies across it); `build_model` keeps ray tracing there.

Build-time part (numpy, the lens is fixed): images of points on the traced
corner grid (the same bilinear ray mapping the ray tracer uses) and the
linearisation error of each clump image. Run-time part (JAX, differentiable
in the clump parameters): `lensed_clumps`.
"""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..pixels import Grid
from ..profiles import safe_atan2, safe_sqrt, sersic_radius_enclosing_np
from ..source import Clumps
from .tracing import map_points, point_images


class ClumpImages(eqx.Module):
    """Linearisation points of K clump images (fixed when the model is built).

    clump_index: [K] which clump each image belongs to.  theta0: [K, 2] image
    position (arcsec, lens plane) of the clump centre at build time.  beta0: [K, 2]
    that centre (arcsec, source plane).  jacobian: [K, 2, 2] A = ∂β/∂θ there.
    flux_scale: [K] |μ| averaged over the clump's light / |μ| at its centre, or None (1):
    the lens Jacobian varies across an image (the bilinear map's cells are ~ an image's
    size), and the image's flux follows the average, not the centre's value.
    """

    clump_index: jnp.ndarray
    theta0: jnp.ndarray
    beta0: jnp.ndarray
    jacobian: jnp.ndarray
    flux_scale: Optional[jnp.ndarray] = None

    @property
    def count(self):
        return self.clump_index.shape[0]


def image_magnifications(images: ClumpImages, dtype):
    """|μ| of each image as rendered: the centre's, times the light-averaged correction."""
    A = images.jacobian.astype(dtype)
    mu = 1.0 / jnp.abs(A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0])
    return mu if images.flux_scale is None else mu * images.flux_scale.astype(dtype)


def lensed_clumps(clumps: Clumps, images: ClumpImages) -> Clumps:
    """The K clump images as lens-plane Sérsics (a `Clumps` with θ centres, magnified flux).

    A clump centre moved from β0 to β images at θ0 + A⁻¹(β − β0) (first order, so
    fits can move clumps). The lensed profile is S(|D R A (θ − θ_k)|) with D =
    diag(1, 1/q), R the clump's rotation: its quadratic form Q = (DRA)ᵀ(DRA) has
    eigenvalues λ_min ≤ λ_max; R_e' = R_e/√λ_min along the eigenvector of λ_min,
    q' = √(λ_min/λ_max). Safe at circular images (finite gradients).
    """
    j = images.clump_index
    A = images.jacobian.astype(clumps.re_arcsec.dtype)
    det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    db = clumps.center_arcsec[j] - images.beta0
    # A⁻¹ db by Cramer's rule
    d1 = (A[:, 1, 1] * db[:, 0] - A[:, 0, 1] * db[:, 1]) / det
    d2 = (-A[:, 1, 0] * db[:, 0] + A[:, 0, 0] * db[:, 1]) / det
    center = images.theta0 + jnp.stack([d1, d2], axis=-1)

    q = clumps.q[j]
    c = jnp.cos(clumps.pa_rad[j])
    s = jnp.sin(clumps.pa_rad[j])
    # rows of D R A: u = c β1 + s β2 (major axis), v = (−s β1 + c β2) / q
    m00 = c * A[:, 0, 0] + s * A[:, 1, 0]
    m01 = c * A[:, 0, 1] + s * A[:, 1, 1]
    m10 = (-s * A[:, 0, 0] + c * A[:, 1, 0]) / q
    m11 = (-s * A[:, 0, 1] + c * A[:, 1, 1]) / q
    qa = m00 * m00 + m10 * m10
    qb = m00 * m01 + m10 * m11
    qc = m01 * m01 + m11 * m11
    lmax = 0.5 * (qa + qc) + safe_sqrt((0.5 * (qa - qc)) ** 2 + qb * qb)
    lmin = (det / q) ** 2 / lmax          # det Q / λ_max: no cancellation for thin images
    # Q = λ_min e eᵀ + λ_max e⊥ e⊥ᵀ with e = (cos φ, sin φ): Q00 − Q11 = (λ_min − λ_max) cos 2φ
    pa = 0.5 * safe_atan2(-2.0 * qb, qc - qa)
    mu = image_magnifications(images, det.dtype)
    return Clumps(center_arcsec=center,
                  flux=clumps.flux[j] * mu[:, None],
                  re_arcsec=clumps.re_arcsec[j] / jnp.sqrt(lmin),
                  n=clumps.n[j], q=jnp.sqrt(lmin / lmax), pa_rad=pa)


# ---------------------------------------------------------------- build time (numpy)


def _det_inverse(A):
    """(det [K], inverse [K, 2, 2]) of 2 × 2 matrices A [K, 2, 2] (numpy)."""
    det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    inv = np.stack([np.stack([A[:, 1, 1], -A[:, 0, 1]], -1),
                    np.stack([-A[:, 1, 0], A[:, 0, 0]], -1)], -2) / det[:, None, None]
    return det, inv


def light_averaged_flux_scale(corner_b1, corner_b2, grid: Grid, theta, A, beta0, samples,
                              weights, iterations: int = 12):
    """|μ| of each of K clump images averaged over its clump's light, over |μ| at the
    image of its centre (`ClumpImages.flux_scale`): [K].

    theta [K, 2], A [K, 2, 2], beta0 [K, 2]: the image of each clump centre, the Jacobian
    there and the centre (arcsec); samples [K, S, 2] β and weights [K, S] (summing to 1):
    a quadrature of the clump's light. Each sample's image near θ is solved by Newton on
    the corner grid's bilinear mapping (the one the ray tracer follows), starting from
    the linear map's guess; 1 (the centre's μ) where a solve does not converge or leaves
    the grid.
    """
    if theta.shape[0] == 0:
        return np.zeros(0)
    det, inv = _det_inverse(A)
    t = theta[:, None, :] + np.einsum("kab,ksb->ksa", inv, samples - beta0[:, None, :])
    for step in range(iterations + 1):
        b1, b2, J, inside = map_points(corner_b1, corner_b2, grid, t[..., 0], t[..., 1])
        r = np.stack([samples[..., 0] - b1, samples[..., 1] - b2], -1)
        if step == iterations or np.max(np.abs(r)) < 1e-12 * grid.pixel_arcsec:
            break
        d = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
        d = np.where(np.abs(d) > 1e-300, d, 1e-300)
        t = t + np.stack([J[..., 1, 1] * r[..., 0] - J[..., 0, 1] * r[..., 1],
                          -J[..., 1, 0] * r[..., 0] + J[..., 0, 0] * r[..., 1]], -1) / d[..., None]
    mu = 1.0 / np.abs(J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0])
    ok = (inside & (np.hypot(r[..., 0], r[..., 1]) < 1e-9 * grid.pixel_arcsec)).all(axis=1)
    return np.where(ok, np.sum(weights * mu, axis=1) * np.abs(det), 1.0)


def linearisation_error(corner_b1, corner_b2, grid: Grid, theta, A, beta0, radius_arcsec,
                        n_angles: int = 16):
    """How far (arcsec, lens plane) the linearised image misplaces a clump's rim.

    For points β on the circle of `radius_arcsec` ([K]) around the clump centre β0,
    the linear map puts their image at θ_lin = θ_k + A⁻¹(β − β0); the ray mapping
    sends θ_lin to β(θ_lin), and the image of β is off by ≈ |A⁻¹(β(θ_lin) − β)|.
    Returns the largest such distance per image ([K]); +inf where the rim's image
    leaves the grid (not linearisable).
    """
    K = theta.shape[0]
    if K == 0:
        return np.zeros(0)
    ang = np.linspace(0, 2 * np.pi, n_angles, endpoint=False)
    circle = np.stack([np.cos(ang), np.sin(ang)], -1)                 # [S, 2]
    _, Ainv = _det_inverse(A)
    dbeta = radius_arcsec[:, None, None] * circle[None]               # [K, S, 2]
    t = theta[:, None, :] + np.einsum("kab,ksb->ksa", Ainv, dbeta)
    b1, b2, _, inside = map_points(corner_b1, corner_b2, grid, t[..., 0], t[..., 1])
    miss = np.stack([b1 - beta0[:, None, 0] - dbeta[..., 0],
                     b2 - beta0[:, None, 1] - dbeta[..., 1]], -1)
    out = np.linalg.norm(np.einsum("kab,ksb->ksa", Ainv, miss), axis=-1).max(-1)
    return np.where(inside.all(-1) & np.isfinite(out), out, np.inf)


# ---------------------------------------------------------------- which clumps (build time)


def linearise_clumps(clumps, corner_b1, corner_b2, hr: Grid, rows, cols, footprint_index,
                     stamp_flux_fraction: float, tolerance_arcsec: float, dtype):
    """Which clumps the local linear lens map renders well, and their images.

    A clump is linearised when every image of its centre has a linearisation error
    (`linearisation_error` on its 99 %-light circle) below `tolerance_arcsec` and 8 points
    on the rim of its stamp have as many images as the centre (no caustic crosses it).
    Returns (mask [N], ClumpImages of the linearised clumps).
    """
    cc = np.asarray(clumps.center_arcsec, float)
    re = np.asarray(clumps.re_arcsec, float)
    n = np.asarray(clumps.n, float)
    N = re.size
    r99 = sersic_radius_enclosing_np(0.99, re, n)
    r_stamp = sersic_radius_enclosing_np(stamp_flux_fraction, re, n)
    ang = np.linspace(0.0, 2 * np.pi, 8, endpoint=False)
    rim = cc[:, None, :] + r_stamp[:, None, None] * np.stack([np.cos(ang), np.sin(ang)], -1)
    pidx, theta, A = point_images(corner_b1, corner_b2, hr, rows, cols,
                                  np.concatenate([cc, rim.reshape(-1, 2)]),
                                  index=footprint_index)
    counts = np.bincount(pidx, minlength=9 * N)
    ok = np.all(counts[N:].reshape(N, 8) == counts[:N, None], axis=1)
    centre = pidx < N
    ci, theta, A = pidx[centre], theta[centre], A[centre]
    err = linearisation_error(corner_b1, corner_b2, hr, theta, A, cc[ci], r99[ci])
    bad = np.zeros(N, bool)
    np.logical_or.at(bad, ci, ~(err < tolerance_arcsec))
    ok &= ~bad
    keep = ok[ci]
    ci, theta, A = ci[keep], theta[keep], A[keep]
    samples, weights = _light_samples(cc, re, n, np.asarray(clumps.q, float),
                                      np.asarray(clumps.pa_rad, float), r_stamp)
    scale = light_averaged_flux_scale(corner_b1, corner_b2, hr, theta, A, cc[ci],
                                      samples[ci], weights[ci])
    images = ClumpImages(clump_index=jnp.asarray(ci), theta0=jnp.asarray(theta, dtype),
                         beta0=jnp.asarray(cc[ci], dtype), jacobian=jnp.asarray(A, dtype),
                         flux_scale=jnp.asarray(scale, dtype))
    return ok, images


def _light_samples(center, re, n, q, pa, r_max, radial: int = 10, angular: int = 16):
    """Points β ([N, radial·angular, 2], arcsec) and weights ([N, radial·angular], summing
    to 1) that integrate a smooth function over each clump's light.

    Radially Gauss–Laguerre in x = b (r/R_e)^{1/n}, where the light is x^{2n−1} e^{−x} dx
    (generalised Laguerre weight), points beyond r_max [N] (the stamp's radius) pulled in
    to it; in the elliptical angle (light is uniform in it) equal steps.
    """
    from scipy.special import gammaincinv, roots_genlaguerre
    N = re.size
    r = np.empty((N, radial))
    w = np.empty((N, radial))
    for nv in np.unique(n):
        at = n == nv
        x, wx = roots_genlaguerre(radial, 2 * nv - 1)
        b = gammaincinv(2 * nv, 0.5)
        r[at] = np.minimum(re[at, None] * (x / b) ** nv, r_max[at, None])
        w[at] = wx / wx.sum()
    phi = (np.arange(angular) + 0.5) * (2 * np.pi / angular)
    u = r[:, :, None] * np.cos(phi)
    v = (q[:, None, None] * r[:, :, None]) * np.sin(phi)
    c, s = np.cos(pa)[:, None, None], np.sin(pa)[:, None, None]
    x = center[:, 0, None, None] + c * u - s * v
    y = center[:, 1, None, None] + s * u + c * v
    weights = np.broadcast_to(w[:, :, None] / angular, u.shape).reshape(N, -1)
    return np.stack([x, y], -1).reshape(N, -1, 2), weights
