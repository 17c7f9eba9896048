"""Injection–recovery completeness of clumps versus flux and size, with blending.

For each cell (flux, R_e) of a grid and each of `n_trials` positions, one
clump is added to a base source, the scene is rendered and observed with
photon noise (a key per trial), and sources are detected by photutils
segmentation: pixels above `nsigma` × the expected noise σ = √((model + sky)/t)
(sky subtracted), at least `npixels` connected pixels, no deblending. The
injected clump counts as recovered when a segment contains its image's peak
pixel and that segment's flux-weighted centroid lies within
`match_radius_pix` of the peak (for a lensed clump, any of its images).

Blending: for every detection the number of true clumps (base and injected)
whose image peaks fall in its segment; a segment holding the injected clump and
others is blended (its centroid then usually misses the match radius).

The Fisher-forecast S/N of the injected clump's flux and size (detect.py) is
computed for each cell at the same positions, for comparison with the
empirical completeness (commonly, 50 % completeness near S/N_flux ≈ 5–10).

One scene model serves the whole grid: it is built with a clump at every trial
position at the largest size (so the traced region and clump stamps cover all
of them), then any source with the same components is rendered.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import require
from ..source import Clumps, Source


@dataclasses.dataclass
class CompletenessResult:
    """Completeness grid. Arrays are [n_flux, n_size] unless said.

    fluxes_counts_per_s [n_flux] (band `band`, intrinsic), sizes_arcsec [n_size].
    completeness: fraction recovered (matched).  detected_fraction: fraction whose peak
    lies in any segment (matched or blended).  blended_fraction: fraction whose segment
    holds other true clumps too.  fisher_snr_flux, fisher_snr_re: mean forecast S/N.
    segment_multiplicity: histogram (index = number of true clumps in a segment, over
    every detection of every trial).  positions_arcsec [n_trials, 2].
    """

    fluxes_counts_per_s: np.ndarray
    sizes_arcsec: np.ndarray
    completeness: np.ndarray
    detected_fraction: np.ndarray
    blended_fraction: np.ndarray
    fisher_snr_flux: np.ndarray
    fisher_snr_re: np.ndarray
    segment_multiplicity: np.ndarray
    positions_arcsec: np.ndarray
    band: str

    def to_table(self):
        """One row per cell (flux, size)."""
        from astropy.table import Table
        f, s = np.meshgrid(self.fluxes_counts_per_s, self.sizes_arcsec, indexing="ij")
        return Table({"flux_counts_per_s": f.ravel(), "re_arcsec": s.ravel(),
                      "completeness": self.completeness.ravel(),
                      "detected_fraction": self.detected_fraction.ravel(),
                      "blended_fraction": self.blended_fraction.ravel(),
                      "fisher_snr_flux": self.fisher_snr_flux.ravel(),
                      "fisher_snr_re": self.fisher_snr_re.ravel()})


def _with_clump(base: Source, center, flux_b, re, n_sersic, q, pa):
    """base + one clump (appended last); flux_b: [B]."""
    new = Clumps(center[None], flux_b[None], re[None], n_sersic[None], q[None], pa[None])
    if base.clumps is None or base.clumps.count == 0:
        cl = new
    else:
        cl = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b.astype(a.dtype)]), base.clumps, new)
    return Source(bulge=base.bulge, disk=base.disk, clumps=cl)


def image_peaks(image, rel: float = 0.2):
    """(row, col) of local maxima above rel × max: the images of one clump (one unless lensed)."""
    from scipy.ndimage import maximum_filter
    img = np.asarray(image)
    top = img.max()
    if not top > 0:
        return np.zeros((0, 2), int)
    peaks = (img == maximum_filter(img, size=3)) & (img >= rel * top)
    return np.argwhere(peaks)


def detect(image_minus_sky, sigma, *, nsigma=3.0, npixels=5, deblend=False):
    """Segmentation map (int array, 0 = background) of pixels above nsigma·σ (photutils);
    with `deblend`, each segment split by photutils' multi-threshold deblending (32 levels,
    contrast 0.001: SExtractor's defaults), so that a clump on a host is a segment of its own
    where its peak stands out."""
    from photutils.segmentation import deblend_sources, detect_sources
    img = np.asarray(image_minus_sky)
    seg = detect_sources(img, nsigma * np.asarray(sigma), int(npixels))
    if seg is None:
        return np.zeros(np.shape(image_minus_sky), int)
    if deblend:
        seg = deblend_sources(img, seg, int(npixels), progress_bar=False)
    return np.asarray(seg.data)


def _centroids(image, seg):
    from scipy.ndimage import center_of_mass
    labels = np.unique(seg[seg > 0])
    w = np.clip(np.asarray(image), 0.0, None)
    return dict(zip(labels.tolist(), center_of_mass(w, seg, labels)))


def completeness_grid(base_source: Source, bands, fluxes_counts_per_s, sizes_arcsec, key, *,
                      deblend=False, **kwargs) -> CompletenessResult:
    """Injection–recovery completeness over (flux, size): `completeness_grids` with one
    detection setting (deblend: split the segments by photutils' deblending, `detect`)."""
    return completeness_grids(base_source, bands, fluxes_counts_per_s, sizes_arcsec, key,
                              deblend=(deblend,), **kwargs)[0]


def completeness_grids(base_source: Source, bands, fluxes_counts_per_s, sizes_arcsec, key, *,
                       lens=None, field_arcsec=None, positions_arcsec=None, n_trials=8,
                       region_arcsec=None, band=0, nsigma=3.0, npixels=5, match_radius_pix=2.0,
                       clump_n=0.5, clump_q=1.0, flux_ratios=None, accuracy=None,
                       fisher=True, deblend=(False, True)) -> tuple:
    """Injection–recovery completeness over (flux, size) in band index `band`, one
    `CompletenessResult` per detection setting of `deblend`, all from the same injections
    (each trial rendered once, with its own noise, and scored by each setting).

    base_source: the scene without the injected clump (host and/or clumps, may be empty of
        clumps; needs at least one component — use a faint host for a blank field).
    bands: `model.Band`s.  lens, field_arcsec: as for `model.build_model`.
    fluxes_counts_per_s: injected fluxes in band `band` (other bands scaled by
        `flux_ratios` [B], default 1).  sizes_arcsec: injected R_e values.
    positions_arcsec: [n_trials, 2] source-plane positions, or None: uniform in a disc of
        radius `region_arcsec` (default 0.3") around the base source's centre.
    nsigma, npixels: photutils detection settings.  match_radius_pix: matching radius.
    fisher: also compute the Fisher-forecast S/N of each injected clump.
    deblend: per setting, whether the segments are split by photutils' deblending (`detect`).
    """
    from ..model import Accuracy

    fluxes = np.atleast_1d(np.asarray(fluxes_counts_per_s, float))
    sizes = np.atleast_1d(np.asarray(sizes_arcsec, float))
    require(np.all(fluxes >= 0) and np.all(sizes > 0), "completeness grid", (fluxes, sizes),
            "fluxes ≥ 0 and sizes > 0")
    accuracy = accuracy or Accuracy()
    ratios = np.ones(len(bands)) if flux_ratios is None else np.asarray(flux_ratios, float)
    k_pos, k_noise = jax.random.split(key)
    if positions_arcsec is None:
        positions_arcsec = _random_positions(base_source, accuracy, k_pos, n_trials, region_arcsec)
    pos = np.asarray(positions_arcsec, float).reshape(-1, 2)
    n_trials = pos.shape[0]
    model = _grid_model(base_source, bands, pos, sizes.max(), clump_n, clump_q, lens=lens,
                        field_arcsec=field_arcsec, accuracy=accuracy)
    sky = model.layouts[band].sky_counts_per_s
    base = base_source.astype(jnp.float64)
    n_base = 0 if base.clumps is None else base.clumps.count

    render_b, iso = _injectors(model, base, ratios, clump_n, clump_q, band)
    base_peaks = [image_peaks(np.asarray(_isolated_base_image(model, base, k, band)))
                  for k in range(n_base)]
    deblend = tuple(bool(d) for d in deblend)
    mults = [np.zeros(n_base + 2, int) for _ in deblend]
    scores = _injection_grid(render_b, iso, pos, fluxes, sizes, k_noise, sky, base_peaks, mults,
                             nsigma=nsigma, npixels=npixels, match_radius_pix=match_radius_pix,
                             deblend=deblend)
    shape = (fluxes.size, sizes.size)
    snr_f = np.full(shape, np.nan)
    snr_r = np.full(shape, np.nan)
    if fisher:
        snr_f, snr_r = _fisher_grid(model, base, pos, fluxes, sizes, ratios, clump_n, clump_q, band)
    return tuple(CompletenessResult(fluxes, sizes, comp, det, blend, snr_f, snr_r, mult, pos,
                                    model.band_names[band])
                 for (comp, det, blend), mult in zip(scores, mults))


def _injectors(model, base, ratios, clump_n, clump_q, band):
    """Two compiled functions, vmapped over trials, of (centre [arcsec], flux [counts/s in
    `band`], R_e [arcsec]): render_b(…, key) → (noisy, variance) of base + the clump in
    `band`; iso(…) → the clump's image alone (where its peaks are)."""
    def render(center, flux, re, nkey):
        src = _with_clump(base, center, flux * jnp.asarray(ratios), re, jnp.asarray(float(clump_n)),
                          jnp.asarray(float(clump_q)), jnp.asarray(0.0))
        noisy, _, var = model.observe(src, nkey)
        return noisy[band], var[band]

    render_b = eqx.filter_jit(jax.vmap(render))
    iso = eqx.filter_jit(jax.vmap(lambda center, flux, re: _isolated_image(
        model, base, center, flux * jnp.asarray(ratios), re, clump_n, clump_q, band)))
    return render_b, iso


def _injection_grid(render_b, iso, pos, fluxes, sizes, k_noise, sky, base_peaks, mults, *,
                    nsigma, npixels, match_radius_pix, deblend=(False,)):
    """Per setting of `deblend` (its `mults` histogram incremented): (completeness, detected,
    blended fractions) [n_flux, n_size]; every trial position of every cell injected and
    observed once, with its own noise key, then detected and scored by each setting."""
    n_trials = pos.shape[0]
    shape = (len(deblend), fluxes.size, sizes.size)
    comp = np.zeros(shape)
    det = np.zeros(shape)
    blend = np.zeros(shape)
    for i, f in enumerate(fluxes):
        for j, s in enumerate(sizes):
            keys = jax.random.split(jax.random.fold_in(k_noise, i * sizes.size + j), n_trials)
            fl = jnp.full(n_trials, f)
            re = jnp.full(n_trials, s)
            noisy, var = render_b(jnp.asarray(pos), fl, re, keys)
            alone = np.asarray(iso(jnp.asarray(pos), fl, jnp.full(n_trials, max(s, 1e-9))))
            noisy, var = np.asarray(noisy), np.asarray(var)
            for t in range(n_trials):
                peaks = image_peaks(alone[t]) if f > 0 else np.zeros((0, 2), int)
                for d, (split, mult) in enumerate(zip(deblend, mults)):
                    hit, matched, blended = _score_trial(
                        noisy[t] - sky, np.sqrt(var[t]), peaks, base_peaks, mult, nsigma=nsigma,
                        npixels=npixels, match_radius_pix=match_radius_pix, deblend=split)
                    det[d, i, j] += hit
                    comp[d, i, j] += matched
                    blend[d, i, j] += blended
    return [(comp[d] / n_trials, det[d] / n_trials, blend[d] / n_trials)
            for d in range(len(deblend))]


def _random_positions(base_source, accuracy, key, n_trials, region_arcsec):
    """n_trials source-plane positions [arcsec] uniform in a disc of radius region_arcsec
    (default 0.3") about the base source's centre."""
    from ..model import source_extent
    center, _ = source_extent(base_source, accuracy.source_flux_fraction,
                              accuracy.stamp_flux_fraction)
    r = (region_arcsec or 0.3) * np.sqrt(np.asarray(jax.random.uniform(key, (n_trials,))))
    phi = 2 * np.pi * np.asarray(jax.random.uniform(jax.random.fold_in(key, 1), (n_trials,)))
    return center[None, :] + np.c_[r * np.cos(phi), r * np.sin(phi)]


def _grid_model(base_source, bands, pos, re_max_arcsec, clump_n, clump_q, **build_kw):
    """One scene model for the whole grid: its extent and stamps set by the base source plus
    a clump at every trial position `pos` [n, 2] arcsec at the largest size re_max_arcsec."""
    from ..model import build_model
    n_trials, nb = pos.shape[0], len(bands)
    cover = Clumps(jnp.asarray(pos), jnp.ones((n_trials, nb)), jnp.full(n_trials, re_max_arcsec),
                   jnp.full(n_trials, float(clump_n)), jnp.full(n_trials, float(clump_q)),
                   jnp.zeros(n_trials))
    if base_source.clumps is not None and base_source.clumps.count > 0:
        cover = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([jnp.asarray(a, float), b]),
                                       base_source.clumps, cover)
    return build_model(Source(base_source.bulge, base_source.disk, cover), bands, **build_kw)


def _score_trial(image_minus_sky, sigma, peaks, base_peaks, mult, *, nsigma, npixels,
                 match_radius_pix, deblend=False):
    """Detect one trial's image and score the injected clump: (hit, matched, blended).

    peaks: (row, col) of the injected clump's images; base_peaks: those of each base clump.
    mult (histogram of true clumps per segment) is incremented in place for every segment.
    """
    seg = detect(image_minus_sky, sigma, nsigma=nsigma, npixels=npixels, deblend=deblend)
    cents = _centroids(image_minus_sky, seg)
    owners = {}
    for pk_list in base_peaks + [peaks]:
        for lab in {int(seg[r, c]) for r, c in pk_list if seg[r, c] > 0}:
            owners[lab] = owners.get(lab, 0) + 1
    for lab in cents:
        mult[min(owners.get(lab, 0), mult.size - 1)] += 1
    hit = matched = blended = False
    for r, c in peaks:
        lab = int(seg[r, c])
        if lab == 0:
            continue
        hit = True
        blended |= owners.get(lab, 0) > 1
        cy, cx = cents[lab]
        matched |= np.hypot(cy - r, cx - c) <= match_radius_pix
    return hit, matched, blended


def _isolated_image(model, base, center, flux_b, re, clump_n, clump_q, band):
    """Noiseless image of the injected clump alone (base components at zero flux)."""
    zero = jax.tree_util.tree_map(lambda a: a, base)
    if zero.bulge is not None:
        zero = eqx.tree_at(lambda s: s.bulge.flux, zero, jnp.zeros_like(zero.bulge.flux))
    if zero.disk is not None:
        zero = eqx.tree_at(lambda s: s.disk.sersic.flux, zero, jnp.zeros_like(zero.disk.sersic.flux))
    if zero.clumps is not None and zero.clumps.count > 0:
        zero = eqx.tree_at(lambda s: s.clumps.flux, zero, jnp.zeros_like(zero.clumps.flux))
    src = _with_clump(zero, center, flux_b, re, jnp.asarray(float(clump_n)),
                      jnp.asarray(float(clump_q)), jnp.asarray(0.0))
    return model.band_images(src)[band]


def _isolated_base_image(model, base, k, band):
    """Noiseless image of base clump k alone (for blending counts)."""
    cl = base.clumps
    flux = jnp.zeros_like(cl.flux).at[k].set(cl.flux[k])
    src = Source(clumps=eqx.tree_at(lambda c: c.flux, cl, flux))
    return model.band_images(src)[band]


def _fisher_grid(model, base, pos, fluxes, sizes, ratios, clump_n, clump_q, band):
    """Mean over positions of the forecast S/N of the injected clump's flux (band) and R_e."""
    from .params import make_state, parametrize
    from .uncertainty import fisher_matrix, safe_inverse

    nb = len(model.layouts)
    snr_f = np.zeros((fluxes.size, sizes.size))
    snr_r = np.zeros_like(snr_f)
    for i, f in enumerate(fluxes):
        for j, s in enumerate(sizes):
            acc_f, acc_r = [], []
            for p in pos:
                # a zero-flux injection has S/N 0; Fisher at a tiny flux keeps the matrix regular
                flux_b = jnp.asarray(max(f, 1e-12) * ratios)
                src = _with_clump(base, jnp.asarray(p), flux_b, jnp.asarray(s),
                                  jnp.asarray(float(clump_n)), jnp.asarray(float(clump_q)),
                                  jnp.asarray(0.0))
                last = src.clumps.count - 1
                param = parametrize(make_state(src, nb), {
                    "clumps.flux": _row_mask(src.clumps.count, nb, last),
                    "clumps.re_arcsec": [last], "clumps.center_arcsec": [last]})
                cov = np.asarray(safe_inverse(fisher_matrix(model, param)))
                lab = {l: k for k, l in enumerate(param.labels)}
                kf = lab[f"clumps.flux[{last},{band}]"]
                kr = lab[f"clumps.re_arcsec[{last}]"]
                acc_f.append(f / np.sqrt(cov[kf, kf]))
                acc_r.append(s / np.sqrt(cov[kr, kr]))
            snr_f[i, j] = np.mean(acc_f)
            snr_r[i, j] = np.mean(acc_r)
    return snr_f, snr_r


def _row_mask(n, nb, row):
    m = np.zeros((n, nb), bool)
    m[row] = True
    return m
