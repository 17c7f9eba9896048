"""Starting points from the pixels alone: a smooth host from image moments, clump candidates
from the residual, and (through a lens) candidates merged into source-plane clumps.

Nothing here knows the truth: every number comes from the data, their variances, the
detector grids of the scene model and, for lensed scenes, the lens's deflection.

- `host_from_moments`: one Sérsic per scene (flux per band, centre, R_e, q, PA) from the
  flux-weighted moments of the pixels above 3σ in the reference band; through a lens the
  moments are taken in the source plane (each pixel's β = θ − α(θ), weighted by its
  surface brightness × its source-plane area pixel²/|μ|, so that surface brightness is
  conserved).
- `find_candidates`: peaks of the matched-filtered S/N of the residual (photutils
  `find_peaks`) in the stack of the bands with the finest pixel, each with an aperture
  flux per band and a size and shape from its second moments minus the PSF's.
- `merge_images`: candidates whose β agree within a tolerance (the source-plane size of
  `merge_pixels` detector pixels at each) are images of one clump; their fluxes are
  de-magnified and combined.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from ..pixels import Grid, rotation_matrix

GAUSS_RE_PER_SIGMA = 1.1774   # R_e / σ of a Gaussian (n = 0.5) profile: √(2 ln 2)
APERTURE_PIXELS = 2.5         # radius of the candidates' aperture (photometry and moments)
MIN_RE_PIXELS = 0.3           # smallest R_e start of a candidate, image pixels


@dataclasses.dataclass
class Candidates:
    """Clump candidates (source-plane, one per merged clump); arrays [K, ...] by decreasing S/N.

    beta_arcsec [K, 2], flux [K, B] (intrinsic counts/s), re_arcsec, q, pa_rad [K] (q and
    PA through a lens: the image's shape mapped by the local lens Jacobian, `source_shape`),
    snr [K] (peak of the matched-filtered residual), n_images [K] (candidates merged),
    theta_pix [K, 2] (row, col of the brightest image in the reference band).
    """

    beta_arcsec: np.ndarray
    flux: np.ndarray
    re_arcsec: np.ndarray
    q: np.ndarray
    pa_rad: np.ndarray
    snr: np.ndarray
    n_images: np.ndarray
    theta_pix: np.ndarray

    def __len__(self):
        return int(self.snr.size)


def reference_bands(scene_model) -> list:
    """Indices of the bands with the finest detector pixel (they are stacked for detection):
    the finest of those on the first band's pixel grid's axes (a band whose pixels are
    turned against the frame, a `RotatedGrid`, is stacked only with its own kind)."""
    grids = [lay.grid for lay in scene_model.layouts]
    aligned = [k for k, g in enumerate(grids) if isinstance(g, Grid)] or [0]
    pix = np.array([grids[k].pixel_arcsec for k in aligned])
    ref = [k for k, p in zip(aligned, pix) if np.isclose(p, pix.min(), rtol=1e-6)]
    return [k for k in ref if grids[k] == grids[ref[0]]]


def snr_stack(residuals, variances, masks, bands):
    """Inverse-variance stack of residual images: (stack, its S/N map)."""
    num = sum(np.asarray(residuals[k]) * masks[k] / variances[k] for k in bands)
    den = sum(masks[k] / variances[k] for k in bands)
    ok = den > 0
    stack = np.where(ok, num / np.where(ok, den, 1.0), 0.0)
    return stack, np.where(ok, num / np.sqrt(np.where(ok, den, 1.0)), 0.0)


def _moments(weights, x, y):
    """(centre x, y, σ_major, σ_minor, pa) of positive weights at positions x, y."""
    w = np.clip(weights, 0.0, None)
    tot = w.sum()
    if not tot > 0:
        return None
    mx, my = (w * x).sum() / tot, (w * y).sum() / tot
    cxx = (w * (x - mx) ** 2).sum() / tot
    cyy = (w * (y - my) ** 2).sum() / tot
    cxy = (w * (x - mx) * (y - my)).sum() / tot
    ev, vec = np.linalg.eigh(np.array([[cxx, cxy], [cxy, cyy]]))
    ev = np.clip(ev, 0.0, None)
    pa = float(np.arctan2(vec[1, 1], vec[0, 1]))
    return mx, my, float(np.sqrt(ev[1])), float(np.sqrt(ev[0])), pa


def pixel_jacobians(scene_model, k: int, lens):
    """β1, β2 (arcsec) of band k's detector pixel centres and the lens Jacobian
    A = ∂β/∂θ there ([ny, nx, 2, 2], finite differences over the pixels; identity unlensed)."""
    g = scene_model.layouts[k].grid
    x, y = g.centers()
    # along the pixel axes: the frame's (a Grid), or turned by their angle (a RotatedGrid)
    turn = np.eye(2) if isinstance(g, Grid) else rotation_matrix(g.angle_rad)
    if lens is None:
        return x, y, np.broadcast_to(np.eye(2), x.shape + (2, 2))
    a1, a2 = lens.deflection(jnp.asarray(x), jnp.asarray(y))
    b1, b2 = x - np.asarray(a1), y - np.asarray(a2)
    p = g.pixel_arcsec
    jac = np.stack([np.stack([np.gradient(b1, p, axis=1), np.gradient(b1, p, axis=0)], -1),
                    np.stack([np.gradient(b2, p, axis=1), np.gradient(b2, p, axis=0)], -1)], -2)
    return b1, b2, jac @ turn.T     # ∂β/∂(pixel axes) → ∂β/∂θ


def _abs_det(A):
    """|det A| of Jacobians [..., 2, 2] (1/|μ|)."""
    return np.abs(A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0])


def pixel_betas(scene_model, k: int, lens):
    """β1, β2 (arcsec) of band k's detector pixel centres and |det A| there (1 unlensed)."""
    b1, b2, A = pixel_jacobians(scene_model, k, lens)
    return b1, b2, _abs_det(A)


def source_shape(q_img: float, pa_img: float, jacobian):
    """(q, PA) of the source-plane ellipse that the linear lens map θ ↦ β = A θ (`jacobian`
    [2, 2]) takes the image-plane one (q, PA: major axis from +θ1) to: its second moments
    are A Σ_θ Aᵀ. The seed of a lensed clump's shape (an image's elongation is mostly the
    lens's, not the clump's)."""
    c, s = np.cos(pa_img), np.sin(pa_img)
    rot = np.array([[c, -s], [s, c]])
    cov = jacobian @ rot @ np.diag([1.0, q_img**2]) @ rot.T @ jacobian.T
    ev, vec = np.linalg.eigh(0.5 * (cov + cov.T))
    q = float(np.sqrt(max(ev[0], 0.0) / ev[1])) if ev[1] > 0 else 1.0
    return float(np.clip(q, 0.2, 1.0)), float(np.arctan2(vec[1, 1], vec[0, 1]))


def sky_levels(data, masks):
    """Per band, the median of the outer ring of pixels (the border 10 %): the sky start."""
    out = []
    for d, m in zip(data, masks):
        ny, nx = d.shape
        e = max(1, int(0.1 * min(ny, nx)))
        ring = np.ones(d.shape, bool)
        ring[e:-e, e:-e] = False
        v = d[ring & (m > 0)]
        out.append(float(np.median(v)) if v.size else 0.0)
    return np.asarray(out)


def host_from_moments(scene_model, data, variances, masks, lens=None):
    """A smooth Sérsic start (dict of Sersic fields, fluxes per band) from the data's moments."""
    bands = reference_bands(scene_model)
    sky = sky_levels(data, masks)
    k0 = bands[0]
    d = np.asarray(data[k0]) - sky[k0]
    bright = (d > 3 * np.sqrt(variances[k0])) & (masks[k0] > 0)
    if bright.sum() < 5:
        bright = masks[k0] > 0
    b1, b2, det = pixel_betas(scene_model, k0, lens)
    w = np.where(bright, d, 0.0) * det          # surface brightness × source-plane area
    mom = _moments(w, b1, b2)
    p = scene_model.layouts[k0].grid.pixel_arcsec
    if mom is None:
        mom = (float(b1.mean()), float(b2.mean()), 5 * p, 5 * p, 0.0)
    mx, my, s_maj, s_min, pa = mom
    s_maj = max(s_maj, p)
    s_min = max(s_min, 0.3 * s_maj)
    flux = []
    for k in range(len(data)):
        dk = np.asarray(data[k]) - sky[k]
        _, _, det_k = pixel_betas(scene_model, k, lens)
        flux.append(max(float(np.sum(np.where(masks[k] > 0, dk, 0.0) * det_k)), 1e-6))
    return dict(flux=np.asarray(flux), re_arcsec=GAUSS_RE_PER_SIGMA * s_maj, n=1.0,
                q=float(np.clip(s_min / s_maj, 0.2, 1.0)), pa_rad=pa,
                center_arcsec=np.array([mx, my])), sky


def matched_filter(snr_map, sigma_pix=1.0):
    """S/N map smoothed by a unit-norm Gaussian (a point source's matched filter, roughly)."""
    from scipy.ndimage import gaussian_filter
    sm = gaussian_filter(np.asarray(snr_map, float), sigma_pix, mode="constant")
    r = np.arange(-4, 5)
    kern = np.exp(-0.5 * (r[:, None] ** 2 + r[None, :] ** 2) / sigma_pix**2)
    return sm * kern.sum() / np.sqrt((kern ** 2).sum())


def find_peaks_snr(snr_map, threshold: float, max_peaks: int, box_pix: int = 3):
    """Peaks (row, col, value) of a S/N map above threshold, brightest first (photutils)."""
    import warnings

    from photutils.detection import find_peaks
    from photutils.utils.exceptions import NoDetectionsWarning
    with warnings.catch_warnings():   # no peak is an answer here (the counting stops), not news
        warnings.simplefilter("ignore", NoDetectionsWarning)
        tab = find_peaks(np.asarray(snr_map, float), threshold, box_size=box_pix,
                         n_peaks=max_peaks, border_width=1)
    if tab is None or len(tab) == 0:
        return np.zeros((0, 3))
    out = np.c_[np.asarray(tab["y_peak"]), np.asarray(tab["x_peak"]), np.asarray(tab["peak_value"])]
    return out[np.argsort(-out[:, 2])]


def _aperture(shape, row, col, radius):
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    return (yy - row) ** 2 + (xx - col) ** 2 <= radius**2, yy - row, xx - col


def measure_candidate(residual, row, col, psf_sigma_pix, pixel_arcsec):
    """R_e (arcsec, image plane), q and PA of a residual peak at (row, col) of `residual`
    (the reference band's image: the sizes come from its own pixels, whatever the other
    bands' grids; their fluxes are measured on each band's grid by `find_candidates`)."""
    ap, dy, dx = _aperture(residual.shape, row, col, APERTURE_PIXELS)
    mom = _moments(np.where(ap, residual, 0.0), dx, dy)
    if mom is None:
        return MIN_RE_PIXELS * pixel_arcsec, 1.0, 0.0
    _, _, s_maj, s_min, pa = mom
    intr_maj = np.sqrt(max(s_maj**2 - psf_sigma_pix**2, 0.0))
    intr_min = np.sqrt(max(s_min**2 - psf_sigma_pix**2, 0.0))
    q = float(np.clip(intr_min / intr_maj, 0.2, 1.0)) if intr_maj > 0 else 1.0
    # an unresolved peak starts at a third of a pixel: a much smaller start can fall
    # between the sample points of a coarse renderer, with no gradient to grow back
    re = max(GAUSS_RE_PER_SIGMA * intr_maj, MIN_RE_PIXELS) * pixel_arcsec
    return re, q, pa


def merge_images(beta, det, snr, merge_pixels: float, pixel_arcsec: float):
    """Groups (lists of indices into the candidates, brightest first) of candidates that are
    images of one source clump: their β within the source-plane size of `merge_pixels`
    detector pixels (pixel × √|det A| at the brighter one, |det A| = 1/|μ|)."""
    order = np.argsort(-snr)
    used = np.zeros(snr.size, bool)
    groups = []
    for i in order:
        if used[i]:
            continue
        tol = merge_pixels * pixel_arcsec * np.sqrt(max(det[i], 1e-6))
        near = (~used) & (np.hypot(*(beta - beta[i]).T) <= tol)
        near[i] = True
        idx = [i] + [j for j in order if near[j] and j != i]
        used[idx] = True
        groups.append(idx)
    return groups


def _band_pixel(scene_model, k, x_arcsec, y_arcsec):
    x, y = scene_model.layouts[k].grid.pixel_of(np.array([x_arcsec, y_arcsec]))
    return y, x


def find_candidates(scene_model, residuals, variances, masks, *, lens=None, psf_sigma_pix,
                    threshold_snr: float, max_candidates: int, merge_pixels: float = 2.0):
    """Clump candidates in residual images (list over bands, counts/s): see `Candidates`.

    psf_sigma_pix: [B] Gaussian σ of each band's PSF in its own pixels (from the model).
    threshold_snr: peaks of the matched-filtered S/N stack below it are ignored.
    """
    bands = reference_bands(scene_model)
    ref = bands[0]
    g = scene_model.layouts[ref].grid
    _, snr = snr_stack(residuals, variances, masks, bands)
    sm = matched_filter(snr, max(float(psf_sigma_pix[ref]), 0.7))
    peaks = find_peaks_snr(sm, threshold_snr, 4 * max_candidates)
    b1, b2, jac = pixel_jacobians(scene_model, ref, lens)
    det = _abs_det(jac)
    rows = []
    for r, c, v in peaks:
        r, c = int(r), int(c)
        x, y = g.position_of(np.array([c, r], float))
        flux = np.zeros(len(residuals))
        for k in range(len(residuals)):
            rk, ck = (r, c) if k in bands else _band_pixel(scene_model, k, x, y)
            scale = g.pixel_arcsec / scene_model.layouts[k].grid.pixel_arcsec
            ap, _, _ = _aperture(residuals[k].shape, rk, ck, max(APERTURE_PIXELS * scale, 1.5))
            flux[k] = float(np.sum(np.where(ap & (masks[k] > 0), residuals[k], 0.0)))
        re_img, q, pa = measure_candidate(np.asarray(residuals[ref]), r, c,
                                          float(psf_sigma_pix[ref]), g.pixel_arcsec)
        if lens is not None:
            q, pa = source_shape(q, pa, jac[r, c])
        rows.append((b1[r, c], b2[r, c], det[r, c], flux, re_img, q, pa, v, r, c))
    if not rows:
        z = np.zeros(0)
        return Candidates(np.zeros((0, 2)), np.zeros((0, len(residuals))), z, z, z, z,
                          np.zeros(0, int), np.zeros((0, 2), int))
    beta = np.array([[t[0], t[1]] for t in rows])
    dets = np.array([t[2] for t in rows])
    snr_v = np.array([t[7] for t in rows])
    groups = merge_images(beta, dets, snr_v, merge_pixels, g.pixel_arcsec)[:max_candidates]
    out = dict(beta=[], flux=[], re=[], q=[], pa=[], snr=[], n=[], pix=[])
    for idx in groups:
        i = idx[0]
        mu = np.array([1.0 / max(dets[j], 1e-6) for j in idx])
        out["beta"].append(beta[i])
        out["flux"].append(np.clip(sum(rows[j][3] for j in idx) / mu.sum(), 1e-12, None))
        out["re"].append(rows[i][4] * np.sqrt(dets[i]))
        out["q"].append(rows[i][5])
        out["pa"].append(rows[i][6])
        out["snr"].append(np.sqrt(np.sum(snr_v[idx] ** 2)))
        out["n"].append(len(idx))
        out["pix"].append((rows[i][8], rows[i][9]))
    a = {k: np.asarray(v) for k, v in out.items()}
    return Candidates(a["beta"], a["flux"], a["re"], a["q"], a["pa"], a["snr"], a["n"], a["pix"])
