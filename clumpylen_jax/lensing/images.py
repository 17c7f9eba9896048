"""Multiple images of a point source, and the lens-plane region a source lands in.

`find_images` (pure JAX, jit- and grad-safe): tile the field with a grid of
vertices, trace them, split each cell into two triangles and keep the triangles
whose source-plane image contains β (barycentric test, which also catches
parity-flipped triangles); the barycentric point in the lens plane is the first
guess, refined by Newton's method on θ − α(θ) − β = 0 (optimistix). The number
of images is static (`max_images`) with a validity mask. Derivatives with
respect to β (and to lens parameters) come from implicit differentiation of the
root (see `refine_images`); the triangle search itself is not differentiated
(the guesses are wrapped in stop_gradient).

Limits: images closer together than ~half a grid pixel are merged; images in
cells whose triangles fold over β more than the grid resolves (very close to a
critical curve, with a source within ~pixel² of the caustic) may be missed.
Choose `pixel_arcsec` well below the separation of the images you need.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from .derived import _check_field, deflection_jacobian, field_grid, lensing_quantities
from .raytrace import trace


class Images(NamedTuple):
    """Images of a point source; arrays of length `max_images`, valid ones first.

    theta1, theta2: image positions, arcsec. magnification: signed μ = 1/det A.
    parity: +1 (minimum/maximum) or −1 (saddle). valid: which entries are images.
    residual_arcsec: |θ − α(θ) − β| after refinement.
    """

    theta1: jnp.ndarray
    theta2: jnp.ndarray
    magnification: jnp.ndarray
    parity: jnp.ndarray
    valid: jnp.ndarray
    residual_arcsec: jnp.ndarray


def _triangle_hits(a, b, c, beta):
    """Barycentric coordinates (l1, l2) of β in source-plane triangles (a, b, c) and an inside mask."""
    e1 = (b[0] - a[0], b[1] - a[1])
    e2 = (c[0] - a[0], c[1] - a[1])
    p = (beta[0] - a[0], beta[1] - a[1])
    d = e1[0] * e2[1] - e2[0] * e1[1]
    ok = d != 0
    dd = jnp.where(ok, d, 1.0)
    l1 = (p[0] * e2[1] - e2[0] * p[1]) / dd
    l2 = (e1[0] * p[1] - p[0] * e1[1]) / dd
    inside = ok & (l1 >= 0) & (l2 >= 0) & (l1 + l2 <= 1)
    return l1, l2, inside


def image_candidates(lens, beta1, beta2, T1, T2, n_candidates):
    """Lens-plane first guesses of the images of β from the triangle test on the vertex grid T1, T2.

    Returns (theta1, theta2, found), each of length `n_candidates` (static).
    """
    B1, B2 = trace(lens, T1, T2)
    beta = (beta1, beta2)
    corners = {
        "00": (slice(None, -1), slice(None, -1)), "01": (slice(None, -1), slice(1, None)),
        "10": (slice(1, None), slice(None, -1)), "11": (slice(1, None), slice(1, None)),
    }
    th = {k: (T1[s], T2[s]) for k, s in corners.items()}
    bs = {k: (B1[s], B2[s]) for k, s in corners.items()}
    guesses1, guesses2, masks = [], [], []
    for tri in (("00", "01", "11"), ("00", "11", "10")):  # two triangles per cell
        a, b, c = (bs[k] for k in tri)
        l1, l2, inside = _triangle_hits(a, b, c, beta)
        ta, tb, tc = (th[k] for k in tri)
        guesses1.append((ta[0] + l1 * (tb[0] - ta[0]) + l2 * (tc[0] - ta[0])).ravel())
        guesses2.append((ta[1] + l1 * (tb[1] - ta[1]) + l2 * (tc[1] - ta[1])).ravel())
        masks.append(inside.ravel())
    g1 = jnp.concatenate(guesses1)
    g2 = jnp.concatenate(guesses2)
    mask = jnp.concatenate(masks)
    (idx,) = jnp.nonzero(mask, size=n_candidates, fill_value=0)
    found = jnp.arange(n_candidates) < jnp.sum(mask)
    return g1[idx], g2[idx], found


def _lens_equation(theta, args):
    lens, beta = args
    b1, b2 = trace(lens, theta[0], theta[1])
    return jnp.stack([b1 - beta[0], b2 - beta[1]])


def refine_images(lens, beta1, beta2, theta1_guess, theta2_guess, *, rtol=1e-10, atol=1e-10, max_steps=40):
    """Newton refinement of image positions (vectorised over the guesses).

    The forward solve is optimistix's Newton root finder on θ − α(θ) − β = 0. Its
    derivatives are those of the implicit function theorem, dθ = A⁻¹ (dβ + ∂α/∂p dp),
    attached by one extra Newton step from the (stop-gradient) root, with A⁻¹
    also held constant: this equals optimistix.ImplicitAdjoint's first
    derivatives, but stays finite where A is singular (a source exactly on a
    caustic gets a zero derivative instead of an error: ImplicitAdjoint's linear
    solve raises there, and it cannot be transposed under vmap).
    Returns (theta1, theta2, residual_arcsec, converged).
    """
    beta = jnp.stack([jnp.asarray(beta1), jnp.asarray(beta2)])
    dtype = jnp.result_type(theta1_guess, beta)
    beta = beta.astype(dtype)
    if dtype == jnp.float32:  # tolerances a float32 solve can meet
        rtol, atol = max(rtol, 1e-6), max(atol, 1e-5)
    import optimistix as optx   # here, not at the top: `simulate` never refines images (~0.5 s)

    solver = optx.Newton(rtol=rtol, atol=atol)
    lens_c = jax.lax.stop_gradient(lens)
    beta_c = jax.lax.stop_gradient(beta)

    def forward(t1, t2):
        y0 = jnp.stack([t1, t2]).astype(dtype)
        sol = optx.root_find(_lens_equation, solver, y0, args=(lens_c, beta_c),
                             max_steps=max_steps, throw=False)
        th = jnp.where(jnp.all(jnp.isfinite(sol.value)), sol.value, y0)
        return th, sol.result == optx.RESULTS.successful

    th, conv = jax.vmap(forward)(jax.lax.stop_gradient(jnp.ravel(theta1_guess)),
                                 jax.lax.stop_gradient(jnp.ravel(theta2_guess)))
    th = jax.lax.stop_gradient(th)
    t1, t2 = th[:, 0], th[:, 1]
    # One implicit-differentiation Newton step (value change ~ residual ≈ 0).
    a11, a12, a21, a22 = deflection_jacobian(lens_c, t1, t2)
    m11, m12, m21, m22 = 1.0 - a11, -a12, -a21, 1.0 - a22
    det = m11 * m22 - m12 * m21
    ok = jnp.abs(det) > 1e3 * jnp.finfo(dtype).eps
    inv_det = jnp.where(ok, 1.0 / jnp.where(ok, det, 1.0), 0.0)
    f1, f2 = trace(lens, t1, t2)
    f1, f2 = f1 - beta[0], f2 - beta[1]
    theta1 = t1 - inv_det * (m22 * f1 - m12 * f2)
    theta2 = t2 - inv_det * (-m21 * f1 + m11 * f2)
    res = jnp.hypot(jax.lax.stop_gradient(f1), jax.lax.stop_gradient(f2))
    return theta1, theta2, res, conv


def find_images(lens, beta1, beta2, *, field, pixel_arcsec, max_images=8, tol_arcsec=None,
                merge_arcsec=None) -> Images:
    """Images of the point β (arcsec) inside `field` ((θ1_min, θ1_max), (θ2_min, θ2_max)).

    pixel_arcsec: spacing of the search grid; max_images: static size of the
    output; tol_arcsec: largest accepted |β(θ) − β| (default: 1e-6 pixel in
    float64, 1e-3 pixel in float32); merge_arcsec: images closer than this are
    one image (default half a pixel). jit-able with field, pixel_arcsec and
    max_images static.
    """
    (x0, x1), (y0, y1) = _check_field(field)
    if not (isinstance(max_images, int) and max_images >= 1):
        raise ConfigError("max_images", max_images, "a positive integer")
    if not (np.isfinite(pixel_arcsec) and pixel_arcsec > 0):
        raise ConfigError("pixel_arcsec", pixel_arcsec, "a positive number")
    beta1 = jnp.asarray(beta1)
    beta2 = jnp.asarray(beta2)
    return _find_images(lens, beta1, beta2, ((x0, x1), (y0, y1)), float(pixel_arcsec), max_images,
                        None if tol_arcsec is None else float(tol_arcsec),
                        None if merge_arcsec is None else float(merge_arcsec))


@partial(jax.jit, static_argnums=(3, 4, 5, 6, 7))
def _find_images(lens, beta1, beta2, field, pixel_arcsec, max_images, tol_arcsec, merge_arcsec):
    dtype = jnp.result_type(beta1, beta2)
    T1, T2 = field_grid(field, pixel_arcsec, dtype=dtype)
    n_cand = 4 * max_images  # adjacent triangles can share an image
    g1, g2, found = image_candidates(lens, jax.lax.stop_gradient(beta1), jax.lax.stop_gradient(beta2),
                                     T1, T2, n_cand)
    t1, t2, res, conv = refine_images(lens, beta1, beta2, g1, g2)
    if tol_arcsec is None:
        tol_arcsec = pixel_arcsec * (1e-3 if dtype == jnp.float32 else 1e-6)
    if merge_arcsec is None:
        merge_arcsec = 0.5 * pixel_arcsec
    ok = found & jnp.isfinite(t1) & jnp.isfinite(t2) & (res < tol_arcsec)
    # Keep the first of each group of candidates that converged to the same image.
    d = jnp.hypot(t1[:, None] - t1[None, :], t2[:, None] - t2[None, :])
    earlier = jnp.tril(jnp.ones((n_cand, n_cand), bool), k=-1)
    dup = jnp.any(earlier & ok[None, :] & (d < merge_arcsec), axis=1)
    valid = ok & ~dup
    order = jnp.argsort(jnp.where(valid, 0, 1), stable=True)[:max_images]
    t1, t2, valid, res = t1[order], t2[order], valid[order], res[order]
    m = lensing_quantities(lens, t1, t2)
    parity = jnp.where(m.det >= 0, 1, -1)
    return Images(t1, t2, m.mu, parity, valid, res)


def lens_plane_region(lens, center_beta, radius_arcsec, *, search_field, pixel_arcsec,
                      margin_arcsec=0.0, component=None):
    """Bounding box ((θ1_min, θ1_max), (θ2_min, θ2_max)) of the lens plane that maps within
    `radius_arcsec` of `center_beta` in the source plane.

    A coarse grid (`pixel_arcsec`) over `search_field` is traced; the pixels that
    land within the radius (plus those whose triangles contain the centre, so
    that a source smaller than a coarse pixel is not lost) are kept, and the box
    is padded by one coarse pixel and `margin_arcsec`. component: None for all
    images, or a θ (θ1, θ2) to keep only the connected patch nearest to it (the
    paper simulates only the main arc). Raises ConfigError when nothing lands there.
    Not differentiable (it chooses static shapes).
    """
    from scipy import ndimage

    if not (np.isfinite(radius_arcsec) and radius_arcsec > 0):
        raise ConfigError("source radius_arcsec", radius_arcsec, "a positive number")
    c1, c2 = (float(v) for v in center_beta)
    T1, T2 = field_grid(search_field, pixel_arcsec)
    B1, B2 = jax.jit(trace)(lens, T1, T2)
    hit = np.array(jnp.hypot(B1 - c1, B2 - c2) <= radius_arcsec)
    # Cells whose triangles contain the centre: mark their four corners.
    for tri in (((0, 0), (0, 1), (1, 1)), ((0, 0), (1, 1), (1, 0))):
        sl = [(slice(j, j + B1.shape[0] - 1), slice(i, i + B1.shape[1] - 1)) for j, i in tri]
        _, _, inside = _triangle_hits(*[(B1[s], B2[s]) for s in sl], (c1, c2))
        inside = np.asarray(inside)
        for s in ((slice(0, -1), slice(0, -1)), (slice(0, -1), slice(1, None)),
                  (slice(1, None), slice(0, -1)), (slice(1, None), slice(1, None))):
            hit[s] |= inside
    if not hit.any():
        raise ConfigError("source position", (c1, c2),
                          f"a source whose light lands inside the search field {search_field}")
    T1n, T2n = np.asarray(T1), np.asarray(T2)
    if component is not None:
        labels, n = ndimage.label(hit, structure=np.ones((3, 3)))
        d = np.hypot(T1n - float(component[0]), T2n - float(component[1]))
        best = min(range(1, n + 1), key=lambda k: d[labels == k].min())
        hit = labels == best
    pad = pixel_arcsec + margin_arcsec
    return ((float(T1n[hit].min() - pad), float(T1n[hit].max() + pad)),
            (float(T2n[hit].min() - pad), float(T2n[hit].max() + pad)))
