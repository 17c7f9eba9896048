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
from scipy.spatial import cKDTree

from ..pixels import Grid
from ..profiles import safe_atan2, safe_sqrt
from ..source import Clumps


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


def bilinear_patch(corner, r, c, fx, fy, *, derivatives=True):
    """Value and (unless derivatives=False) derivatives per pixel along x and y of the
    bilinear interpolation of corner values [ny + 1, nx + 1] inside pixels (r, c) at
    fractions (fx, fy) ∈ [0, 1]."""
    v00 = corner[r, c]
    v01 = corner[r, c + 1]
    v10 = corner[r + 1, c]
    v11 = corner[r + 1, c + 1]
    val = v00 * (1 - fx) * (1 - fy) + v01 * fx * (1 - fy) + v10 * (1 - fx) * fy + v11 * fx * fy
    if not derivatives:
        return val
    dfx = (v01 - v00) * (1 - fy) + (v11 - v10) * fy
    dfy = (v10 - v00) * (1 - fx) + (v11 - v01) * fx
    return val, dfx, dfy


def map_points(corner_b1, corner_b2, grid: Grid, t1, t2):
    """β and A = ∂β/∂θ at lens-plane points (arcsec) from the corner grid's bilinear mapping.

    Returns (b1, b2, A [.., 2, 2], inside); points outside the grid are clamped and
    flagged False in `inside`.
    """
    h = grid.pixel_arcsec
    x = (np.asarray(t1, float) - (grid.x0_arcsec - 0.5 * h)) / h
    y = (np.asarray(t2, float) - (grid.y0_arcsec - 0.5 * h)) / h
    inside = (x >= 0) & (x <= grid.nx) & (y >= 0) & (y <= grid.ny)
    c = np.clip(np.floor(x).astype(int), 0, grid.nx - 1)
    r = np.clip(np.floor(y).astype(int), 0, grid.ny - 1)
    fx = np.clip(x - c, 0.0, 1.0)
    fy = np.clip(y - r, 0.0, 1.0)
    b1, d1x, d1y = bilinear_patch(corner_b1, r, c, fx, fy)
    b2, d2x, d2y = bilinear_patch(corner_b2, r, c, fx, fy)
    A = np.stack([np.stack([d1x, d1y], -1), np.stack([d2x, d2y], -1)], -2) / h
    return b1, b2, A, inside


def _pixel_corners(corner_b1, corner_b2, rows, cols):
    """β1, β2 at the corners 00, 01, 10, 11 of lens-plane pixels (rows, cols): [M, 4] each."""
    q = [(rows, cols), (rows, cols + 1), (rows + 1, cols), (rows + 1, cols + 1)]
    return (np.stack([corner_b1[a, b] for a, b in q], -1),
            np.stack([corner_b2[a, b] for a, b in q], -1))


def pixel_footprints(corner_b1, corner_b2, rows=None, cols=None):
    """Centre (mean of the corners' β) and reach (largest corner distance from it) of the
    source-plane footprints of lens-plane pixels (rows, cols): three [M] arrays; without
    rows and cols, of every pixel of the grid: three [ny, nx] arrays."""
    if rows is None:
        v1 = (corner_b1[:-1, :-1], corner_b1[:-1, 1:], corner_b1[1:, :-1], corner_b1[1:, 1:])
        v2 = (corner_b2[:-1, :-1], corner_b2[:-1, 1:], corner_b2[1:, :-1], corner_b2[1:, 1:])
    else:
        q = [(rows, cols), (rows, cols + 1), (rows + 1, cols), (rows + 1, cols + 1)]
        v1 = tuple(corner_b1[r, c] for r, c in q)
        v2 = tuple(corner_b2[r, c] for r, c in q)
    m1 = 0.25 * (v1[0] + v1[1] + v1[2] + v1[3])
    m2 = 0.25 * (v2[0] + v2[1] + v2[2] + v2[3])
    reach2 = np.zeros_like(m1)
    for a1, a2 in zip(v1, v2):
        np.maximum(reach2, (a1 - m1) ** 2 + (a2 - m2) ** 2, out=reach2)
    return m1, m2, np.sqrt(reach2)


class FootprintIndex:
    """Source-plane footprints (centres m1, m2 and reaches, [M] each, arcsec) of lens-plane
    pixels, with one KD tree per octave of reach, so that a few huge footprints (near a
    lens centre) do not widen every query. Built once, queried by `pixels_near`."""

    def __init__(self, m1, m2, reach):
        self.m1, self.m2, self.reach = m1, m2, reach
        level = np.floor(np.log2(np.maximum(reach, 1e-300))).astype(int)
        self.levels = []
        for lv in np.unique(level):
            members = np.nonzero(level == lv)[0]
            self.levels.append((members, cKDTree(np.stack([m1[members], m2[members]], -1)),
                                reach[members].max()))


def pixels_near(corner_b1, corner_b2, rows, cols, centers, radii, index=None):
    """Pairs (disc index [L], pixel index [L]) of source-plane discs (centers [P, 2], radii [P],
    arcsec) and lens-plane pixels (rows, cols) whose footprint comes within the disc.
    index: the pixels' `FootprintIndex`, when already made."""
    if index is None:
        index = FootprintIndex(*pixel_footprints(corner_b1, corner_b2, np.asarray(rows),
                                                 np.asarray(cols)))
    m1, m2, reach = index.m1, index.m2, index.reach
    centers = np.asarray(centers, float).reshape(-1, 2)
    radii = np.asarray(radii, float)
    none = (np.zeros(0, int), np.zeros(0, int))
    if m1.size == 0 or centers.shape[0] == 0:
        return none
    pis, mis = [], []
    for members, tree, widest in index.levels:
        cand = tree.query_ball_point(centers, r=radii + 1.01 * widest + 1e-12)
        pi = np.repeat(np.arange(centers.shape[0]), [len(c) for c in cand])
        if pi.size:
            pis.append(pi)
            mis.append(members[np.concatenate([np.asarray(c, int) for c in cand])])
    if not pis:
        return none
    pi, mi = np.concatenate(pis), np.concatenate(mis)
    near = (np.hypot(centers[pi, 0] - m1[mi], centers[pi, 1] - m2[mi])
            <= radii[pi] + 1.01 * reach[mi] + 1e-12)
    return pi[near], mi[near]


def point_images(corner_b1, corner_b2, grid: Grid, rows, cols, points, *, merge_pixels=0.5,
                 index=None):
    """Every image of each source-plane point inside the given lens-plane pixels.

    corner_b1/2: β at the grid's pixel corners ([ny + 1, nx + 1]); rows, cols: the pixels
    searched; points: [P, 2] β (arcsec). Each pixel is split into two triangles whose
    images in the source plane are tested for each point (triangle mapping), and the
    hit is then solved exactly on the pixel's bilinear mapping (Newton, which the
    ray tracer's rays follow too). Returns numpy (point_index [K], theta [K, 2],
    A [K, 2, 2]); images of a point closer than `merge_pixels` are merged.
    """
    points = np.asarray(points, float).reshape(-1, 2)
    h = grid.pixel_arcsec
    rows = np.asarray(rows)
    cols = np.asarray(cols)
    pi, mi = pixels_near(corner_b1, corner_b2, rows, cols, points, np.zeros(points.shape[0]),
                         index)
    if pi.size == 0:
        return np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 2, 2))
    # corners of the candidate pixels only, indexed like them
    cand, at = np.unique(mi, return_inverse=True)
    v1, v2 = _pixel_corners(corner_b1, corner_b2, rows[cand], cols[cand])
    v1, v2 = v1[at], v2[at]
    # the two triangles (00, 01, 11) and (00, 11, 10) in pixel units (fx, fy)
    found_p, found_m, found_f = [], [], []
    for tri, pts in (((0, 1, 3), ((0, 0), (1, 0), (1, 1))), ((0, 3, 2), ((0, 0), (1, 1), (0, 1)))):
        a, b, c = tri
        e1 = np.stack([v1[:, b] - v1[:, a], v2[:, b] - v2[:, a]], -1)
        e2 = np.stack([v1[:, c] - v1[:, a], v2[:, c] - v2[:, a]], -1)
        d = np.stack([points[pi, 0] - v1[:, a], points[pi, 1] - v2[:, a]], -1)
        det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        ok = np.abs(det) > 1e-30
        det = np.where(ok, det, 1.0)
        l1 = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / det
        l2 = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / det
        tol = -1e-9
        hit = ok & (l1 >= tol) & (l2 >= tol) & (l1 + l2 <= 1 - tol)
        p0, p1, p2 = (np.asarray(p, float) for p in pts)
        f = p0[None] + l1[:, None] * (p1 - p0)[None] + l2[:, None] * (p2 - p0)[None]
        found_p.append(pi[hit])
        found_m.append(mi[hit])
        found_f.append(f[hit])
    pidx = np.concatenate(found_p)
    midx = np.concatenate(found_m)
    f = np.concatenate(found_f)
    r, c = rows[midx], cols[midx]
    fx, fy = f[:, 0].copy(), f[:, 1].copy()
    # Newton on the bilinear patch (the triangle solution is the first guess)
    for _ in range(8):
        b1, d1x, d1y = bilinear_patch(corner_b1, r, c, fx, fy)
        b2, d2x, d2y = bilinear_patch(corner_b2, r, c, fx, fy)
        r1 = points[pidx, 0] - b1
        r2 = points[pidx, 1] - b2
        det = d1x * d2y - d1y * d2x
        det = np.where(np.abs(det) > 1e-300, det, 1e-300)
        fx = np.clip(fx + (d2y * r1 - d1y * r2) / det, 0.0, 1.0)
        fy = np.clip(fy + (-d2x * r1 + d1x * r2) / det, 0.0, 1.0)
    theta = np.stack([grid.x0_arcsec + (c + fx - 0.5) * h,
                      grid.y0_arcsec + (r + fy - 0.5) * h], -1)
    _, _, A, _ = map_points(corner_b1, corner_b2, grid, theta[:, 0], theta[:, 1])
    # merge duplicates (a point on a shared edge is found in both neighbours)
    order = np.lexsort((theta[:, 1], theta[:, 0], pidx))
    pidx, theta, A = pidx[order], theta[order], A[order]
    keep = np.ones(pidx.size, bool)
    first = np.searchsorted(pidx, pidx)       # sorted by point: its images are contiguous
    for k in np.nonzero(first < np.arange(pidx.size))[0]:
        prev = slice(first[k], k)
        if np.any(keep[prev] & (np.hypot(*(theta[prev] - theta[k]).T) < merge_pixels * h)):
            keep[k] = False
    return pidx[keep], theta[keep], A[keep]


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
