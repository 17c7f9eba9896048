"""Derived lensing quantities: κ, γ, μ, critical curves and caustics.

Two ways to get the Jacobian ∂α/∂θ:
- `lensing_quantities(lens, θ1, θ2)`: forward-mode derivatives (jax.jvp) of the
  lens's own deflection at any points. For analytic lenses this is exact; for a
  DeflectionGrid it is the derivative of the bilinear interpolant actually used in
  ray tracing (piecewise constant in one direction per cell).
- `grid_lensing_quantities(grid)`: finite differences of a DeflectionGrid at the
  centres of its cells, which equal the derivative of the bilinear interpolant
  there (the average of the two edge differences), and cost no tracing.

Conventions: A = I − ∂α/∂θ; κ = ½(∂α1/∂θ1 + ∂α2/∂θ2); γ1 = ½(∂α1/∂θ1 − ∂α2/∂θ2);
γ2 = ½(∂α1/∂θ2 + ∂α2/∂θ1) (symmetrised); λ_t = 1 − κ − |γ|, λ_r = 1 − κ + |γ|;
det A = λ_t λ_r; μ = 1/det A (signed: negative for saddle-point images).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from .analytic import safe_hypot
from .raytrace import trace


class LensingMaps(NamedTuple):
    """Lensing quantities at a set of points (arrays of the same shape)."""

    kappa: jnp.ndarray
    gamma1: jnp.ndarray
    gamma2: jnp.ndarray
    lambda_t: jnp.ndarray  # 1 − κ − |γ|: zero on tangential critical curves
    lambda_r: jnp.ndarray  # 1 − κ + |γ|: zero on radial critical curves
    det: jnp.ndarray       # det A = λ_t λ_r
    mu: jnp.ndarray        # 1/det A (signed); ±inf only exactly on a critical curve


def _from_derivatives(a11, a12, a21, a22):
    kappa = 0.5 * (a11 + a22)
    g1 = 0.5 * (a11 - a22)
    g2 = 0.5 * (a12 + a21)
    gamma = safe_hypot(g1, g2)
    lt = 1.0 - kappa - gamma
    lr = 1.0 - kappa + gamma
    det = (1.0 - a11) * (1.0 - a22) - a12 * a21
    return LensingMaps(kappa, g1, g2, lt, lr, det, 1.0 / det)


def deflection_jacobian(lens, theta1, theta2):
    """(∂α1/∂θ1, ∂α1/∂θ2, ∂α2/∂θ1, ∂α2/∂θ2) at θ (arrays), by forward-mode AD.

    Deflections are pointwise functions of θ, so one jvp with a unit tangent per
    axis gives the derivatives at every point at once.
    """
    theta1 = jnp.asarray(theta1)
    theta2 = jnp.asarray(theta2)
    one = jnp.ones_like(theta1)
    zero = jnp.zeros_like(theta1)
    f = lambda t1, t2: lens.deflection(t1, t2)  # noqa: E731
    _, (a11, a21) = jax.jvp(f, (theta1, theta2), (one, zero))
    _, (a12, a22) = jax.jvp(f, (theta1, theta2), (zero, one))
    return a11, a12, a21, a22


def lensing_quantities(lens, theta1, theta2) -> LensingMaps:
    """κ, γ, λ_t, λ_r, det A and μ at θ (arcsec arrays) from AD of `lens.deflection`."""
    return _from_derivatives(*deflection_jacobian(lens, theta1, theta2))


def magnification(lens, theta1, theta2):
    """Signed magnification μ = 1/det A at θ (arcsec)."""
    return lensing_quantities(lens, theta1, theta2).mu


def grid_lensing_quantities(grid):
    """Finite-difference lensing quantities of a DeflectionGrid at its cell centres.

    Returns (theta1, theta2, LensingMaps), arrays of shape (ny − 1, nx − 1): the
    cell centres lie half a pixel from the map's pixel centres. The values equal
    the derivatives of the bilinear interpolant at those points (including
    `grid.scale`).
    """
    a1 = grid.scale * jnp.asarray(grid.alpha1_arcsec)
    a2 = grid.scale * jnp.asarray(grid.alpha2_arcsec)
    p = grid.pixel_arcsec

    def d_dx(a):  # mean of the x-differences of the two rows bounding each cell
        dx = (a[:, 1:] - a[:, :-1]) / p
        return 0.5 * (dx[1:, :] + dx[:-1, :])

    def d_dy(a):
        dy = (a[1:, :] - a[:-1, :]) / p
        return 0.5 * (dy[:, 1:] + dy[:, :-1])

    maps = _from_derivatives(d_dx(a1), d_dy(a1), d_dx(a2), d_dy(a2))
    ny, nx = grid.shape
    t1 = grid.origin_arcsec[0] + p * (jnp.arange(nx - 1) + 0.5)
    t2 = grid.origin_arcsec[1] + p * (jnp.arange(ny - 1) + 0.5)
    T1, T2 = jnp.meshgrid(t1, t2)
    return T1, T2, maps


def _check_field(field):
    try:
        (x0, x1), (y0, y1) = field
        x0, x1, y0, y1 = float(x0), float(x1), float(y0), float(y1)
    except (TypeError, ValueError) as exc:
        raise ConfigError("field_arcsec", field, "((θ1_min, θ1_max), (θ2_min, θ2_max)) in arcsec") from exc
    if not (x1 > x0 and y1 > y0 and np.all(np.isfinite([x0, x1, y0, y1]))):
        raise ConfigError("field_arcsec", field, "finite ranges with max > min")
    return (x0, x1), (y0, y1)


def field_grid(field, pixel_arcsec, dtype=None):
    """Pixel-centre coordinates (θ1, θ2), shape (ny, nx), covering `field` at `pixel_arcsec`.

    field: ((θ1_min, θ1_max), (θ2_min, θ2_max)) in arcsec. The number of pixels
    is rounded up so that the grid covers the field; it is centred on it.
    """
    (x0, x1), (y0, y1) = _check_field(field)
    if not (np.isfinite(pixel_arcsec) and pixel_arcsec > 0):
        raise ConfigError("pixel_arcsec", pixel_arcsec, "a positive number")
    nx = max(2, int(np.ceil((x1 - x0) / pixel_arcsec - 1e-9)))
    ny = max(2, int(np.ceil((y1 - y0) / pixel_arcsec - 1e-9)))
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    t1 = cx + pixel_arcsec * (np.arange(nx) - 0.5 * (nx - 1))
    t2 = cy + pixel_arcsec * (np.arange(ny) - 0.5 * (ny - 1))
    T1, T2 = np.meshgrid(t1, t2)
    dtype = dtype or jnp.result_type(float)
    return jnp.asarray(T1, dtype), jnp.asarray(T2, dtype)


def lens_maps(lens, field, pixel_arcsec):
    """(θ1, θ2, LensingMaps) on a regular grid over `field` (arcsec)."""
    T1, T2 = field_grid(field, pixel_arcsec)
    return T1, T2, jax.jit(lensing_quantities)(lens, T1, T2)


def _contours(x, y, z, level=0.0):
    """Contour lines of z at `level` on the grid x, y (2-D arrays): a list of (N, 2) arrays."""
    import contourpy

    gen = contourpy.contour_generator(np.asarray(x), np.asarray(y), np.asarray(z, dtype=np.float64),
                                      line_type=contourpy.LineType.Separate)
    return [np.asarray(seg, dtype=np.float64) for seg in gen.lines(level) if len(seg) >= 2]


def critical_curves(lens, field, pixel_arcsec):
    """Tangential and radial critical curves in the lens plane.

    Returns {"tangential": [...], "radial": [...]}: lists of (N, 2) arrays of θ
    (arcsec), the zero contours of λ_t and λ_r on a grid of `pixel_arcsec` over
    `field` (linear interpolation between grid points, so the accuracy is a
    fraction of a pixel where λ is smooth).
    """
    T1, T2, m = lens_maps(lens, field, pixel_arcsec)
    return {"tangential": _contours(T1, T2, m.lambda_t), "radial": _contours(T1, T2, m.lambda_r)}


def caustics(lens, curves):
    """Map critical curves to the source plane with the lens equation.

    curves: the output of `critical_curves` (or any {name: [(N, 2) arrays]}).
    Returns the same structure with β (arcsec).
    """
    out = {}
    for name, segs in curves.items():
        mapped = []
        for seg in segs:
            b1, b2 = trace(lens, jnp.asarray(seg[:, 0]), jnp.asarray(seg[:, 1]))
            mapped.append(np.stack([np.asarray(b1), np.asarray(b2)], axis=1))
        out[name] = mapped
    return out


def rasterize(lens, field, pixel_arcsec):
    """Sample a lens's deflection on a regular grid over `field`: a DeflectionGrid.

    The grid's pixel centres are those of `field_grid(field, pixel_arcsec)`; the
    stored deflection already includes the lens's scaling (`scale = 1`). Useful to
    freeze an expensive analytic model, or to compare with a map.
    """
    from .grid import DeflectionGrid

    T1, T2 = field_grid(field, pixel_arcsec)
    a1, a2 = jax.jit(lambda l, x, y: l.deflection(x, y))(lens, T1, T2)
    origin = jnp.stack([T1[0, 0], T2[0, 0]])
    return DeflectionGrid(alpha1_arcsec=a1, alpha2_arcsec=a2, origin_arcsec=origin,
                          pixel_arcsec=float(pixel_arcsec), scale=1.0)
