"""Where each band's pixels sit: one fit frame φ shared by every band, and the way to θ and RA/Dec.

The fit frame φ (arcsec) runs along the first observation's pixel axes (φ1 with
its columns, φ2 with its rows), origin at its central pixel. Every band is a
`pixels.Grid` in φ — its own pixel scale and offset (NIRCam SW 0.031" and LW
0.063" together) — so the model renders each band on the data's own pixels.
A band whose pixel axes are turned against the first one's (another WCS
orientation, e.g. HST and JWST together) is a `pixels.RotatedGrid` in φ: the model
draws it on φ-aligned pixels and carries the light onto the data's own pixels by
their exact overlaps (model/detector.py), so no data are resampled. The WCS may be
rotated on the sky, and positions are turned into θ (DESIGN.md: θ1 West, θ2 North,
relative to the first observation's centre) and RA/Dec through it. Without a celestial
WCS the cutouts are taken to share their centre (turned against each other by their
matrices), and θ comes from a pixel-to-angle matrix where the data give one
(`pixel_matrix_arcsec`, or the header's PIX2A11..PIX2A22: a CD matrix in arcsec,
East and North per pixel x and y, as lenstronomy's `transform_pix2angle`), else
θ = φ (pixel x taken as West, y as North: say so when reporting). The model is
rendered on the data's pixels either way.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from ..errors import ConfigError
from ..pixels import Grid, RotatedGrid, rotation_matrix

# |M/s − R| allowed of a band's pixel axes against a rotation of the first one's (0.02 px
# over 100 px); a band turned by less than this is taken as aligned
ORIENTATION_TOL = 2e-4


def celestial_wcs(header):
    """The 2-D celestial WCS of a header, or None (no CTYPE RA/DEC pair)."""
    import warnings

    from astropy.wcs import FITSFixedWarning, WCS
    if not any(str(header.get(f"CTYPE{i}", "")).upper().startswith(("RA", "DEC")) for i in (1, 2)):
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        try:
            w = WCS(header).celestial
        except Exception:
            return None
    return w if w.has_celestial and w.naxis == 2 else None


def wcs_pixel_arcsec(wcs, where: str) -> float:
    """Pixel side of a celestial WCS (arcsec); ConfigError for non-square pixels."""
    from astropy.wcs.utils import proj_plane_pixel_scales
    sx, sy = (float(v) * 3600.0 for v in proj_plane_pixel_scales(wcs))
    if not (np.isfinite(sx) and sx > 0 and abs(sx - sy) <= 1e-3 * sx):
        raise ConfigError(f"{where} (WCS)", f"pixel scales {sx:.6g}\" x {sy:.6g}\"",
                          "square pixels (resample the image first)")
    return 0.5 * (sx + sy)


def check_pixel_matrix(m, pixel_arcsec, setting: str):
    """The 2 × 2 pixel-to-angle matrix `m` (arcsec: [[E/x, E/y], [N/x, N/y]]) as a tuple of
    tuples; ConfigError unless it has square, orthogonal pixels of side `pixel_arcsec` (when
    given) and the parity of the sky (det < 0: a mirror image is no sky image)."""
    a = np.asarray(m, float) if m is not None else None
    ok = a is not None and a.shape == (2, 2) and np.all(np.isfinite(a))
    if ok:
        c0, c1 = np.hypot(*a[:, 0]), np.hypot(*a[:, 1])
        s = 0.5 * (c0 + c1)
        ok = (s > 0 and abs(c0 - c1) <= 1e-3 * s and abs(a[:, 0] @ a[:, 1]) <= 1e-3 * s * s
              and np.linalg.det(a) < 0)
        if ok and pixel_arcsec is not None and abs(s - pixel_arcsec) > 1e-3 * pixel_arcsec:
            raise ConfigError(setting, np.round(a, 8).tolist(),
                              f"a matrix whose pixel side ({s:.6g}\") matches the pixel scale "
                              f"({pixel_arcsec:.6g}\")")
    if not ok:
        raise ConfigError(setting, m, "[[E/x, E/y], [N/x, N/y]] in arcsec per pixel (a CD matrix "
                          "× 3600): square orthogonal pixels, sky parity (det < 0)")
    return tuple(tuple(float(v) for v in row) for row in a)


def theta_rotation(frame) -> np.ndarray:
    """R [2, 2]: θ = R φ for a band without a celestial WCS (identity without a matrix)."""
    m = frame.pixel_matrix_arcsec
    if m is None:
        return np.eye(2)
    a = np.asarray(m, float)
    return np.diag([-1.0, 1.0]) @ a / np.sqrt(abs(np.linalg.det(a)))   # East → West = θ1


@dataclasses.dataclass(frozen=True)
class BandFrame:
    """One band's pixels: shape, pixel side (arcsec), celestial WCS (or None), and without a
    WCS the pixel-to-angle matrix (arcsec, CD convention; None: x West, y North)."""

    shape: tuple
    pixel_arcsec: float
    wcs: Optional[object] = dataclasses.field(default=None, compare=False)
    pixel_matrix_arcsec: Optional[tuple] = None


@dataclasses.dataclass(frozen=True)
class FitFrame:
    """The fit frame of a set of bands: their grids in φ and the way to θ / RA, Dec."""

    grids: tuple                       # pixels.Grid (or RotatedGrid) per band, in φ
    reference: BandFrame               # the first band
    names: tuple

    @property
    def _c0(self):
        ny, nx = self.reference.shape
        return np.array([(nx - 1) / 2.0, (ny - 1) / 2.0])

    def pixel_of(self, phi, band: int = 0):
        """0-based (x, y) pixel of φ [..., 2] in band `band`."""
        return self.grids[band].pixel_of(phi)

    def phi_of_pixel(self, xy, band: int = 0):
        return self.grids[band].position_of(xy)

    def radec(self, phi):
        """(RA, Dec) degrees of φ [..., 2], or None without a WCS."""
        w = self.reference.wcs
        if w is None:
            return None
        xy = self.pixel_of(phi, 0)
        ra, dec = w.wcs_pix2world(xy[..., 0], xy[..., 1], 0)
        return np.asarray(ra, float), np.asarray(dec, float)

    def center_radec(self):
        w = self.reference.wcs
        if w is None:
            return None
        ra, dec = w.wcs_pix2world(*self._c0, 0)
        return float(ra), float(dec)

    def theta(self, phi):
        """θ (arcsec, DESIGN.md frame) of φ [..., 2], relative to the first band's centre."""
        if self.reference.wcs is None:
            return np.asarray(phi, float) @ theta_rotation(self.reference).T
        from ..io import radec_to_theta
        ra, dec = self.radec(phi)
        t1, t2 = radec_to_theta(ra, dec, self.center_radec())
        return np.stack([np.asarray(t1, float), np.asarray(t2, float)], -1)

    def phi_of_radec(self, ra_deg, dec_deg):
        w = self.reference.wcs
        if w is None:
            raise ConfigError("clumps (catalogue)", "ra_deg/dec_deg",
                              "pixel or theta columns: the first observation has no celestial WCS")
        x, y = w.wcs_world2pix(np.asarray(ra_deg, float), np.asarray(dec_deg, float), 0)
        return self.phi_of_pixel(np.stack([x, y], -1), 0)

    def phi_of_theta(self, theta):
        theta = np.asarray(theta, float)
        if self.reference.wcs is None:
            return theta @ theta_rotation(self.reference)     # R is orthogonal: R⁻¹ = Rᵀ
        from ..io import theta_to_radec
        ra, dec = theta_to_radec(theta[..., 0], theta[..., 1], self.center_radec())
        return self.phi_of_radec(ra, dec)

    def pa_theta(self, phi, pa_phi_rad):
        """Position angles in θ (counter-clockwise from θ1) of ellipses at φ with angle pa_phi."""
        phi = np.atleast_2d(np.asarray(phi, float))
        pa = np.asarray(pa_phi_rad, float)
        eps = 1e-3
        d = np.stack([np.cos(pa), np.sin(pa)], -1) * eps
        t = self.theta(phi + d) - self.theta(phi - d)
        return np.arctan2(t[..., 1], t[..., 0])


def _affine_to_reference(frame: BandFrame, ref: BandFrame):
    """(q0, M): band pixels p map to reference pixels q0 + M p (from the two WCSs)."""
    ny, nx = frame.shape
    pts = np.array([[0.0, 0.0], [nx - 1.0, 0.0], [0.0, ny - 1.0]])
    ra, dec = frame.wcs.wcs_pix2world(pts[:, 0], pts[:, 1], 0)
    qx, qy = ref.wcs.wcs_world2pix(ra, dec, 0)
    q = np.stack([qx, qy], -1)
    M = np.stack([(q[1] - q[0]) / max(nx - 1, 1), (q[2] - q[0]) / max(ny - 1, 1)], -1)
    return q[0], M


def _overlap(a: Grid, b: Grid) -> bool:
    return (min(a.x_range[1], b.x_range[1]) > max(a.x_range[0], b.x_range[0])
            and min(a.y_range[1], b.y_range[1]) > max(a.y_range[0], b.y_range[0]))


def fit_frame(frames, names, files=None) -> FitFrame:
    """The FitFrame of bands (BandFrame each, names for messages, files for messages)."""
    files = files or names
    ref = frames[0]
    with_wcs = [f.wcs is not None for f in frames]
    if any(with_wcs) and not all(with_wcs):
        k = with_wcs.index(not with_wcs[0])
        raise ConfigError(f"observations[{names[k]}] ({files[k]})",
                          "a celestial WCS" if with_wcs[k] else "no celestial WCS",
                          "every observation with a celestial WCS, or none (bands are placed "
                          "on the sky by their WCS, or taken as concentric without one)")
    c0 = np.array([(ref.shape[1] - 1) / 2.0, (ref.shape[0] - 1) / 2.0])
    p0 = ref.pixel_arcsec
    grids = []
    for k, f in enumerate(frames):
        ny, nx = f.shape
        if k == 0:
            x0 = -(nx - 1) / 2.0 * f.pixel_arcsec
            y0 = -(ny - 1) / 2.0 * f.pixel_arcsec
            grids.append(Grid(x0, y0, f.pixel_arcsec, nx, ny))
            continue
        if f.wcs is None:   # concentric; turned by the two pixel matrices' rotations
            M = f.pixel_arcsec / p0 * theta_rotation(ref).T @ theta_rotation(f)
            q0 = c0 + M @ np.array([-(nx - 1) / 2.0, -(ny - 1) / 2.0])
        else:
            q0, M = _affine_to_reference(f, ref)
        s = float(np.sqrt(abs(np.linalg.det(M))))
        angle = float(np.arctan2(M[1, 0], M[0, 0]))
        turn = rotation_matrix(angle)
        if not (s > 0 and np.linalg.det(M) > 0 and np.max(np.abs(M / s - turn)) < ORIENTATION_TOL):
            raise ConfigError(f"observations[{names[k]}] ({files[k]})",
                              "pixel axes flipped or sheared against "
                              f"observations[{names[0]}]",
                              "square pixels of the sky's parity (bands may be rotated and "
                              "of other pixel scales, not mirrored)")
        x0, y0 = (q0[0] - c0[0]) * p0, (q0[1] - c0[1]) * p0
        if np.max(np.abs(M / s - np.eye(2))) < ORIENTATION_TOL:
            grids.append(Grid(x0, y0, s * p0, nx, ny))
        else:
            grids.append(RotatedGrid(x0, y0, s * p0, nx, ny, angle))
    for k in range(1, len(grids)):
        if not _overlap(grids[0], grids[k]):
            raise ConfigError(f"observations[{names[k]}] ({files[k]})", "no overlap on the sky",
                              f"a band whose WCS overlaps observations[{names[0]}]")
    return FitFrame(tuple(grids), ref, tuple(names))
