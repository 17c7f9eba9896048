"""The traced lens plane: β at the corners of a fine lens-plane grid, and what is read from it.

Build time only (numpy; the lens is fixed in a model). `trace_corners` traces β = θ − α(θ)
at every corner of the high-resolution lens-plane grid once; every other lens-plane
quantity the model needs comes from those corners by bilinear interpolation inside a
pixel (`grid.bilinear_patch`: the lens mapping is smooth on the scale of a lens-plane pixel):

- which pixels can receive light from the source (`traced_pixels`, source-plane
  footprints and their `FootprintIndex`);
- the rays at sub-pixel offsets (`rays_in_pixels`);
- images of source-plane points and the Jacobian there (`point_images`, `map_points`);
- the sub-pixel footprints of pixels near a host centre, integrated exactly
  (`host_core_footprints`).

The interpolation formulas themselves are all in `grid.py`.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from ..pixels import Grid
from .grid import bilinear_patch, bilinear_quad


# ------------------------------------------------------------------ tracing the corners


def trace_in_chunks(lens, theta1, theta2, chunk=1 << 20):
    """β of rays θ (numpy, flat), computed with the lens in float64 by chunks."""
    out1 = np.empty_like(theta1)
    out2 = np.empty_like(theta2)
    f = jax.jit(lambda a, b: lens.deflection(a, b))
    # chunks of one size (the last one padded with its own last ray): one compilation
    n = theta1.size
    n_chunks = max(1, math.ceil(n / chunk))
    chunk = max(1, math.ceil(n / n_chunks))
    for s in range(0, n, chunk):
        t1, t2 = theta1[s:s + chunk], theta2[s:s + chunk]
        if t1.size < chunk:
            t1, t2 = (np.pad(t, (0, chunk - t.size), mode="edge") for t in (t1, t2))
        a1, a2 = f(jnp.asarray(t1), jnp.asarray(t2))
        m = min(chunk, n - s)
        out1[s:s + m] = theta1[s:s + m] - np.asarray(a1)[:m]
        out2[s:s + m] = theta2[s:s + m] - np.asarray(a2)[:m]
    bad = ~(np.isfinite(out1) & np.isfinite(out2))
    if np.any(bad):
        k = int(np.argmax(bad))
        raise ConfigError("lens", f"non-finite deflection at θ = ({theta1[k]:.4f}, {theta2[k]:.4f})\" "
                          f"({int(bad.sum())} rays)",
                          "a lens with finite deflections over the traced field (NaN in the "
                          "deflection maps there?)")
    return out1, out2



def trace_corners(lens, hr_grid: Grid):
    """β (two [ny + 1, nx + 1] arrays) at the corners of every lens-plane pixel."""
    xc, yc = np.meshgrid(hr_grid.x_edges(), hr_grid.y_edges())
    b1, b2 = trace_in_chunks(lens, xc.ravel(), yc.ravel())
    return b1.reshape(xc.shape), b2.reshape(xc.shape)



# ------------------------------------------------------------------ interpolating the corners


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
        from scipy.spatial import cKDTree   # build time only: not imported by a warm run

        self.m1, self.m2, self.reach = m1, m2, reach
        level = np.floor(np.log2(np.maximum(reach, 1e-300))).astype(int)
        self.levels = []
        for lv in np.unique(level):
            members = np.nonzero(level == lv)[0]
            # unbalanced, uncompacted: built in 1.2 s instead of 2.8 s for 4M footprints;
            # the queries return the same (sorted) members
            tree = cKDTree(np.stack([m1[members], m2[members]], -1), balanced_tree=False,
                           compact_nodes=False)
            self.levels.append((members, tree, reach[members].max()))


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


# ~70 lines: one search in four steps (candidate pixels, triangle test, Newton on the
# bilinear patch, merging duplicates) whose arrays are shared from step to step
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


def traced_pixels(corner_b1, corner_b2, center, radius):
    """Rows and columns of lens-plane pixels whose light can come from the source disc,
    and the `FootprintIndex` of their source-plane footprints.

    A pixel is traced when the disc (center, radius) comes within its
    source-plane footprint: the distance from the mean of its corners' β to the
    centre is below radius + the largest corner distance from that mean, so
    that thin, highly magnified images are not missed.
    """
    m1, m2, reach = pixel_footprints(corner_b1, corner_b2)
    keep = np.hypot(m1 - center[0], m2 - center[1]) < radius + 1.01 * reach
    rows, cols = np.nonzero(keep)
    return rows, cols, FootprintIndex(m1[keep], m2[keep], reach[keep])


def rays_in_pixels(corner_b1, corner_b2, rows, cols, offsets):
    """β of rays at sub-pixel offsets (in (−½, ½) pixel) of the given pixels: [M, R] each.

    Bilinear interpolation of the corners' β: the lens mapping is smooth on the
    scale of a lens-plane pixel, and each pixel needs one deflection per corner
    instead of one per ray.
    """
    ox, oy = offsets
    fx = (ox + 0.5)[None, :]
    fy = (oy + 0.5)[None, :]
    return [bilinear_patch(b, rows[:, None], cols[:, None], fx, fy, derivatives=False)
            for b in (corner_b1, corner_b2)]



# ------------------------------------------------------------------ host cores


_HOST_CORE_REACHES = 4     # × exact_core: footprint reaches from a host centre integrated exactly
_HOST_CORE_SPLIT = 2       # each such pixel as 2 × 2 sub-pixels, each with its own footprint
_HOST_CORE_DET_CHANGE = 0.01   # largest relative change of |μ| across a sub-pixel integrated exactly


def host_core_footprints(centers, corner_b1, corner_b2, rows, cols, footprint_index,
                         exact_core: int):
    """The traced pixels whose host light is integrated exactly, and their sub-pixels'
    source-plane footprints: (index into the traced pixels [K], corners β1, β2 [K, S, 4],
    areas [K, S]) or None.

    centers: [(β1, β2)] of the host components.  rows, cols, footprint_index: the traced
    pixels (`traced_pixels`).  exact_core: the accuracy knob (0: none integrated exactly).

    Those whose source-plane footprint lies within 4·exact_core of its own reaches from a
    host component's centre, where a sample is off by % near a cusp (the residual total
    flux error of an n = 4 host of R_e 4 lens pixels behind a mass sheet: 5e-4 with
    2·exact_core, 2e-4 with 4, 1.5e-4 with 6, +3 % with none), and where the lens map is
    linear enough. Each is split into 2 × 2 sub-pixels whose footprints (corners by
    bilinear interpolation of the pixel's traced corners) are integrated exactly and
    divided by their areas: the mean |dθ/dβ| of a sub-pixel stands for the local one.
    That holds where |μ| changes by < 1 % across each sub-pixel; near a critical curve it
    changes by tens of % across a pixel, and a sample at the pixel's centre is the better
    estimate there (an n = 1 host by an SIS caustic lost 3e-4 of its flux otherwise).
    The 4 × 4 split changed a compact host behind an SIS by 1e-4 and cost 4× more.
    """
    if not centers or exact_core == 0:
        return None
    m1, m2, reach = footprint_index.m1, footprint_index.m2, footprint_index.reach
    near = np.zeros(m1.shape, bool)
    for c1, c2 in centers:
        near |= (np.hypot(m1 - c1, m2 - c2) < _HOST_CORE_REACHES * exact_core * reach)
    idx = np.nonzero(near)[0]
    if idx.size == 0:
        return None
    r, k = rows[idx], cols[idx]
    # the pixel's corners (lower left, lower right, upper right, upper left), then the
    # sub-pixels' corners by bilinear interpolation: [K, split², 4]
    ll, lr, ur, ul = ((r, k), (r, k + 1), (r + 1, k + 1), (r + 1, k))
    f = np.arange(_HOST_CORE_SPLIT + 1) / _HOST_CORE_SPLIT
    fy, fx = np.meshgrid(f, f, indexing="ij")

    def sub_corners(cb):
        g = bilinear_quad(*(cb[p][:, None, None] for p in (ll, lr, ur, ul)), fx, fy)
        return np.stack([g[:, :-1, :-1], g[:, :-1, 1:], g[:, 1:, 1:], g[:, 1:, :-1]],
                        -1).reshape(idx.size, -1, 4)

    v1, v2 = sub_corners(corner_b1), sub_corners(corner_b2)
    e1, e2 = np.roll(v1, -1, -1) - v1, np.roll(v2, -1, -1) - v2
    turn = e1 * np.roll(e2, -1, -1) - e2 * np.roll(e1, -1, -1)
    convex = np.all(turn > 0, -1) | np.all(turn < 0, -1)
    area = 0.5 * np.abs(np.sum(v1 * np.roll(v2, -1, -1) - np.roll(v1, -1, -1) * v2, -1))
    # |det| changes across a bilinear footprint by |w × e| along each edge e, with w its
    # twist v0 − v1 + v2 − v3: relative to the mean (the area), at most |w| Σ|e| / area
    twist = np.hypot(v1[..., 0] - v1[..., 1] + v1[..., 2] - v1[..., 3],
                     v2[..., 0] - v2[..., 1] + v2[..., 2] - v2[..., 3])
    edges = np.hypot(e1[..., 0], e2[..., 0]) + np.hypot(e1[..., 1], e2[..., 1])
    ok = convex & (area > 0) & (twist * edges < _HOST_CORE_DET_CHANGE * np.maximum(area, 1e-300))
    keep = np.all(ok, -1)
    if not np.any(keep):
        return None
    return idx[keep], v1[keep], v2[keep], area[keep]
