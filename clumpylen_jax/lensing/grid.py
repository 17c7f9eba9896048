"""Deflection fields sampled on a regular grid, and every bilinear interpolation of the lens
plane: deflection maps and the tiled source-plane grid (`bilinear_neighbours` holds the
clamping rule, `bilinear_gather` the weights), and the traced corners inside a lens-plane
pixel (`bilinear_patch`, `bilinear_quad`, read by `tracing.py`). Change the lens
interpolation here.

Rays outside the map (the rule, documented once here): the deflection is that of
the nearest map pixel centre on the edge ("edge clamping"), so every ray gets a
finite, continuous deflection; its derivative across the edge is zero. Scenes
are expected to keep the region they trace inside the map; the lens-model layer
warns when they do not.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError, require


def bilinear_interpolate(image, x_pix, y_pix):
    """Bilinear interpolation of a 2-D ``image[y, x]`` at fractional pixel indices.

    x_pix, y_pix: positions in pixel units, (0, 0) being the centre of
    ``image[0, 0]``. Positions outside the array are clamped to the edge.
    Differentiable in ``image`` and in the positions (piecewise linear).
    """
    return bilinear_interpolate_channels(image[:, :, None], x_pix, y_pix)[..., 0]


def bilinear_neighbours(x_pix, y_pix, ny: int, nx: int, xp=jnp):
    """Clamped positions and the four neighbours of bilinear interpolation on [ny, nx].

    Returns (x, y, i0, j0, i1, j1): positions clamped to the edge (the rule for rays
    outside a map) and the column/row indices of the neighbours. `xp` is jax.numpy or
    numpy (build-time bookkeeping uses the same rule as the interpolation).
    """
    x = xp.clip(x_pix, 0.0, nx - 1.0)
    y = xp.clip(y_pix, 0.0, ny - 1.0)
    i0 = xp.clip(xp.floor(x).astype(np.int32), 0, max(nx - 2, 0))
    j0 = xp.clip(xp.floor(y).astype(np.int32), 0, max(ny - 2, 0))
    return x, y, i0, j0, xp.minimum(i0 + 1, nx - 1), xp.minimum(j0 + 1, ny - 1)


def bilinear_gather(get, x_pix, y_pix, ny: int, nx: int):
    """Bilinear interpolation [..., C] of a channels-last field of shape [ny, nx, C] that
    `get(rows, cols)` reads (a dense array or any other storage)."""
    x, y, i0, j0, i1, j1 = bilinear_neighbours(x_pix, y_pix, ny, nx)
    fx = (x - i0)[..., None]
    fy = (y - j0)[..., None]
    return (get(j0, i0) * (1 - fx) * (1 - fy) + get(j0, i1) * fx * (1 - fy)
            + get(j1, i0) * (1 - fx) * fy + get(j1, i1) * fx * fy)


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


def bilinear_quad(ll, lr, ur, ul, fx, fy):
    """Bilinear interpolation between four corner values (lower left, lower right, upper
    right, upper left) at fractions (fx, fy) ∈ [0, 1] (the sub-pixel corners of a host core,
    `tracing.host_core_footprints`; its own order of terms, kept for bit-identical sums)."""
    return ll * (1 - fx) * (1 - fy) + lr * fx * (1 - fy) + ur * fx * fy + ul * (1 - fx) * fy


def bilinear_interpolate_channels(image, x_pix, y_pix):
    """Bilinear interpolation of a channels-last image [ny, nx, C] at fractional pixel indices.

    Returns [..., C]; (0, 0) is the centre of ``image[0, 0]``, positions outside
    are clamped to the edge (the rule for rays outside a map). Each of the four
    neighbours is read once for all channels.
    """
    get = lambda j, i: image.at[j, i].get(mode="promise_in_bounds")  # noqa: E731 (clipped)
    return bilinear_gather(get, x_pix, y_pix, *image.shape[:2])


class DeflectionGrid(eqx.Module):
    """A deflection field on a regular grid, in the θ frame of DESIGN.md.

    alpha1_arcsec, alpha2_arcsec: [ny, nx] deflection along +θ1 (West) and +θ2
        (North), arcsec, for D_ls/D_s = 1 unless `scale` says otherwise.
    origin_arcsec: (θ1, θ2) of the centre of pixel [0, 0], arcsec.
    pixel_arcsec: grid spacing, arcsec (the same along both axes).
    scale: the factor applied to the stored deflection, D_ls/D_s for the
        scene's source when the map is normalised to D_ls/D_s = 1.
    """

    alpha1_arcsec: jnp.ndarray
    alpha2_arcsec: jnp.ndarray
    origin_arcsec: jnp.ndarray
    pixel_arcsec: float = eqx.field(static=True)
    scale: float = 1.0

    def __check_init__(self):
        a1 = np.shape(self.alpha1_arcsec)
        a2 = np.shape(self.alpha2_arcsec)
        if a1 != a2 or len(a1) != 2:
            raise ConfigError("deflection maps (shape)", f"{a1} and {a2}",
                              "two 2-D arrays of the same shape")
        if min(a1) < 2:
            raise ConfigError("deflection maps (shape)", a1, "at least 2 x 2 pixels")
        require(np.isfinite(self.pixel_arcsec) and self.pixel_arcsec > 0,
                "deflection pixel_arcsec", self.pixel_arcsec, "a positive number")

    @property
    def shape(self):
        return self.alpha1_arcsec.shape

    def deflection(self, theta1, theta2):
        """(α1, α2) in arcsec at θ (arcsec), scaled by `scale`; edge-clamped outside."""
        x = (theta1 - self.origin_arcsec[0]) / self.pixel_arcsec
        y = (theta2 - self.origin_arcsec[1]) / self.pixel_arcsec
        a1 = bilinear_interpolate(self.alpha1_arcsec, x, y)
        a2 = bilinear_interpolate(self.alpha2_arcsec, x, y)
        return self.scale * a1, self.scale * a2

    def contains(self, theta1, theta2):
        """True where θ lies inside the map (between the outermost pixel centres)."""
        ny, nx = self.shape
        x = (theta1 - self.origin_arcsec[0]) / self.pixel_arcsec
        y = (theta2 - self.origin_arcsec[1]) / self.pixel_arcsec
        return (x >= 0) & (x <= nx - 1) & (y >= 0) & (y <= ny - 1)
