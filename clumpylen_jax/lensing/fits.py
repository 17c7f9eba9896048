"""Deflection maps from FITS files (HFF convention) placed in the θ frame.

HFF convention (Hubble Frontier Fields lens-model deliverables): two files, the
deflection along +x pixel and along +y pixel, in arcsec, for D_ls/D_s = 1, on a
TAN-projected grid with a celestial WCS. We support grids whose pixel axes are
aligned with the sky (north up; east left or right, south up or down: a flip is
exact and cheap). A rotated grid raises ConfigError: resampling a deflection map
would silently smooth it and change its derived κ, so we ask the user to supply
an aligned map instead.

Placement: the θ frame is the gnomonic (TAN) projection about the scene's lens
centre (RA0, Dec0), θ1 = −ξ (West positive), θ2 = η, which agrees with DESIGN.md's
θ1 = −ΔRA·cos(Dec0)·3600, θ2 = ΔDec·3600 to first order. We compute θ of the
centres of pixel [0, 0] and of its neighbours from the WCS; the map's own tangent
point usually differs from the lens centre (e.g. by ~20″ for the HFF MACS J0416
maps), which shifts the grid and rotates it by ~1e-5 rad (negligible; checked and
reported as an error when above a tolerance).
"""

from __future__ import annotations

import os
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from ..constants import ARCSEC_PER_RAD
from ..errors import ConfigError
from ._distances import dls_ds
from .grid import DeflectionGrid

# Largest tolerated misalignment between the map's pixel grid and the θ frame,
# as the displacement (in pixels) it would cause at the far edge of the map.
_ALIGN_TOL_PIX = 0.05


def tan_project_arcsec(ra_deg, dec_deg, ra0_deg, dec0_deg):
    """θ (arcsec) of sky positions in the gnomonic projection about (ra0, dec0).

    Standard coordinates (ξ, η) of the TAN projection; θ1 = −ξ (towards the West),
    θ2 = η. Numpy, float64.
    """
    ra = np.deg2rad(np.asarray(ra_deg, float))
    dec = np.deg2rad(np.asarray(dec_deg, float))
    ra0 = np.deg2rad(float(ra0_deg))
    dec0 = np.deg2rad(float(dec0_deg))
    dra = ra - ra0
    cosc = np.sin(dec0) * np.sin(dec) + np.cos(dec0) * np.cos(dec) * np.cos(dra)
    xi = np.cos(dec) * np.sin(dra) / cosc
    eta = (np.cos(dec0) * np.sin(dec) - np.sin(dec0) * np.cos(dec) * np.cos(dra)) / cosc
    return -xi * ARCSEC_PER_RAD, eta * ARCSEC_PER_RAD


def _read_image(path, what):
    from astropy.io import fits

    path = Path(os.fspath(path))
    if not path.is_file():
        raise ConfigError(f"deflection map ({what})", str(path), "an existing FITS file")
    try:
        with fits.open(path, memmap=False) as hdul:
            hdu = next((h for h in hdul if h.data is not None and np.ndim(h.data) >= 2), None)
            if hdu is None:
                raise ConfigError(f"deflection map ({what})", str(path), "a FITS file with a 2-D image")
            # FITS is big-endian; convert to native float64 once, here.
            data = np.asarray(hdu.data, dtype=np.float64)
            header = hdu.header.copy()
    except OSError as exc:
        raise ConfigError(f"deflection map ({what})", str(path), f"a readable FITS file ({exc})") from exc
    data = np.squeeze(data)
    if data.ndim != 2:
        raise ConfigError(f"deflection map ({what})", f"{path} with shape {hdu.data.shape}", "a 2-D image")
    return data, header


def _celestial_wcs(header, path, what):
    import warnings

    from astropy.wcs import WCS

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            wcs = WCS(header, naxis=2)
    except Exception as exc:  # astropy raises several types for broken headers
        raise ConfigError(f"deflection map WCS ({what})", str(path), f"a valid celestial WCS ({exc})") from exc
    if not wcs.has_celestial or wcs.celestial.naxis != 2:
        raise ConfigError(f"deflection map WCS ({what})", str(path),
                          "a celestial WCS (CTYPE1/2 = RA---TAN/DEC--TAN, CRVAL, CRPIX, CD or CDELT)")
    wcs = wcs.celestial
    if wcs.wcs.lng != 0:
        raise ConfigError(f"deflection map WCS ({what})", str(path), "RA along the first (x) axis")
    return wcs


def place_map(wcs, shape, ra0_deg, dec0_deg, *, name="deflection map"):
    """Where a map's pixels lie in the θ frame of a lens centre.

    Returns (origin_arcsec, pixel_arcsec, flip_x, flip_y): θ of the centre of
    pixel [0, 0] *after* the flips, the pixel size, and whether the array must be
    reversed along x (east to the right) or y (south up) so that +x is West and
    +y North. Raises ConfigError for a rotated or non-square-pixel grid.
    """
    ny, nx = shape
    # θ of pixel centres at three corners of the array (0-based pixel coordinates).
    px = np.array([0.0, nx - 1.0, 0.0])
    py = np.array([0.0, 0.0, ny - 1.0])
    ra, dec = wcs.all_pix2world(px, py, 0)
    t1, t2 = tan_project_arcsec(ra, dec, ra0_deg, dec0_deg)
    ex = np.array([t1[1] - t1[0], t2[1] - t2[0]]) / (nx - 1)  # θ step per +x pixel
    ey = np.array([t1[2] - t1[0], t2[2] - t2[0]]) / (ny - 1)  # θ step per +y pixel
    sx, sy = np.hypot(*ex), np.hypot(*ey)
    if not (sx > 0 and sy > 0):
        raise ConfigError(f"{name} WCS", "zero pixel scale", "a non-degenerate celestial WCS")
    # Off-axis components measure rotation; their effect at the far edge must be tiny.
    off = max(abs(ex[1]) * (nx - 1) / sx, abs(ey[0]) * (ny - 1) / sy)
    if off > _ALIGN_TOL_PIX or abs(sx - sy) * max(nx, ny) > _ALIGN_TOL_PIX * sx:
        raise ConfigError(
            f"{name} WCS",
            f"pixel axes rotated or non-square (off-axis drift {off:.3g} px, scales {sx:.6g}″ × {sy:.6g}″)",
            "a grid aligned with north/east (CD1_2 = CD2_1 = 0) and square pixels; resample the map first")
    flip_x = ex[0] < 0  # +x pixel points East: reverse columns and negate α_x
    flip_y = ey[1] < 0  # +y pixel points South
    pixel = 0.5 * (sx + sy)
    origin = np.array([t1[0], t2[0]])
    if flip_x:
        origin[0] = t1[1]
    if flip_y:
        origin[1] = t2[2]
    return origin, float(pixel), bool(flip_x), bool(flip_y)


def _normalization_scale(normalization, z_lens, z_source, cosmology):
    num = dls_ds(z_lens, z_source, cosmology)
    if normalization == "dls_ds":
        return num
    if isinstance(normalization, dict) and set(normalization) == {"z_source"}:
        zn = float(normalization["z_source"])
        if not zn > z_lens:
            raise ConfigError("deflection normalization z_source", zn, f"a redshift above z_lens = {z_lens}")
        return num / dls_ds(z_lens, zn, cosmology)
    raise ConfigError("deflection normalization", normalization,
                      '"dls_ds" (maps for D_ls/D_s = 1) or {"z_source": z_n} (maps for a source at z_n)')


def load_deflection_maps(x_path, y_path, *, lens_center_radec_deg, z_lens, z_source,
                         normalization="dls_ds", cosmology=None) -> DeflectionGrid:
    """Read HFF-style x/y deflection maps into a DeflectionGrid in the θ frame.

    x_path, y_path: FITS images of the deflection (arcsec) along +x and +y pixel.
    lens_center_radec_deg: (RA0, Dec0) in degrees, the origin of θ.
    z_lens, z_source: redshifts; the map is scaled by D_ls/D_s(z_l, z_s)/D_ls/D_s(z_l, z_n).
    normalization: "dls_ds" (maps for D_ls/D_s = 1, HFF) or {"z_source": z_n}.
    cosmology: None (flat ΛCDM, H0 = 70, Ωm = 0.3), an astropy cosmology or {"H0", "Om0"}.

    NaNs are allowed in the files (they only matter where rays are traced):
    check them with `check_finite`. Returns a float64 DeflectionGrid whose
    `scale` holds the redshift scaling.
    """
    try:
        ra0, dec0 = (float(v) for v in lens_center_radec_deg)
    except (TypeError, ValueError) as exc:
        raise ConfigError("lens center_radec_deg", lens_center_radec_deg, "[RA, Dec] in degrees") from exc
    ax, hx = _read_image(x_path, "x")
    ay, hy = _read_image(y_path, "y")
    if ax.shape != ay.shape:
        raise ConfigError("deflection maps (shape)", f"x {ax.shape} vs y {ay.shape}", "the same shape")
    wx = _celestial_wcs(hx, x_path, "x")
    wy = _celestial_wcs(hy, y_path, "y")
    # Both files must describe the same grid: compare where their corners fall.
    ny, nx = ax.shape
    corners = (np.array([0, nx - 1, 0, nx - 1.0]), np.array([0, 0, ny - 1, ny - 1.0]))
    rx, dx = wx.all_pix2world(*corners, 0)
    ry, dy = wy.all_pix2world(*corners, 0)
    pix_deg = np.sqrt(abs(np.linalg.det(wx.pixel_scale_matrix)))
    mismatch = np.max(np.hypot((rx - ry) * np.cos(np.deg2rad(dx)), dx - dy)) / pix_deg
    if not mismatch < 1e-3:
        raise ConfigError("deflection maps (WCS)", f"x and y grids differ by {mismatch:.3g} pixels",
                          "x and y maps on the same WCS grid")
    origin, pixel, flip_x, flip_y = place_map(wx, ax.shape, ra0, dec0)
    if flip_x:  # columns run East→West after reversal; the x component flips sign
        ax, ay = -ax[:, ::-1], ay[:, ::-1]
    if flip_y:
        ax, ay = ax[::-1, :], -ay[::-1, :]
    scale = _normalization_scale(normalization, float(z_lens), float(z_source), cosmology)
    return DeflectionGrid(alpha1_arcsec=jnp.asarray(np.ascontiguousarray(ax)),
                          alpha2_arcsec=jnp.asarray(np.ascontiguousarray(ay)),
                          origin_arcsec=jnp.asarray(origin), pixel_arcsec=pixel, scale=scale)


def check_finite(grid: DeflectionGrid, theta1_range, theta2_range, *, name="deflection map"):
    """Raise ConfigError if the map has a non-finite value where rays in the box are traced.

    theta1_range, theta2_range: (min, max) in arcsec of the lens-plane region.
    The bilinear stencil of the box (one pixel beyond each side, clamped at the
    edges) is checked; the message gives the first bad pixel and its θ.
    """
    (x0, x1), (y0, y1) = theta1_range, theta2_range
    ny, nx = grid.shape
    o1, o2 = (float(v) for v in np.asarray(grid.origin_arcsec))
    p = grid.pixel_arcsec
    i0 = int(np.clip(np.floor((min(x0, x1) - o1) / p), 0, nx - 1))
    i1 = int(np.clip(np.ceil((max(x0, x1) - o1) / p), 0, nx - 1))
    j0 = int(np.clip(np.floor((min(y0, y1) - o2) / p), 0, ny - 1))
    j1 = int(np.clip(np.ceil((max(y0, y1) - o2) / p), 0, ny - 1))
    for comp, arr in (("x", grid.alpha1_arcsec), ("y", grid.alpha2_arcsec)):
        sub = np.asarray(arr)[j0:j1 + 1, i0:i1 + 1]
        bad = ~np.isfinite(sub)
        if bad.any():
            jj, ii = np.argwhere(bad)[0]
            j, i = j0 + jj, i0 + ii
            raise ConfigError(
                f"{name} ({comp} component)",
                f"{int(bad.sum())} non-finite pixels in the traced region, first at pixel "
                f"[y={j}, x={i}] (θ = ({o1 + i * p:.2f}″, {o2 + j * p:.2f}″))",
                "finite deflections wherever rays are traced")
