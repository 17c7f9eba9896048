"""What a worker does with one task: numpy arrays in, a dict of numpy arrays out.

A worker process keeps, per study variant, the prepared scene (population,
photometry, lens, PSFs) and one scene model per clump count (`Variant.model`),
and the jitted functions below are module-level `eqx.filter_jit`s taking the
model as an argument: tasks of one shape reuse one compiled program.

Lensed variants render clumps in "grid" source mode, in which a model accepts
clumps anywhere in its traced region (hybrid mode fixes each clump's linearised
images when the model is built, so moving a clump needs a new model).
"""

from __future__ import annotations

import dataclasses
import hashlib
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..source import Clumps, Source
from .spec import Study, variant_scene_dict
from .tasks import Task, bucket, draw_sample, map_offsets, positions, sample_rng

_CACHE: dict = {}          # per process: (study fingerprint, variant) → Variant


@dataclasses.dataclass
class Variant:
    """A prepared scene variant: base source, clump photometry and models by clump count."""

    prep: object
    base: Source
    center_arcsec: np.ndarray       # the host's centre: positions are offsets from it
    counts_per_msun: np.ndarray     # [B] counts/s per M☉ formed (burst of age_myr)
    arcsec_per_pc: float
    study: Study
    models: dict = dataclasses.field(default_factory=dict)

    @property
    def n_base(self) -> int:
        return 0 if self.base.clumps is None else self.base.clumps.count

    def model(self, slots: int):
        """The scene model for base + `slots` clumps (built once; clumps may then move)."""
        if slots not in self.models:
            from ..model import build_model
            prep, cl = self.prep, self.study.clumps
            r = cl["region_arcsec"]
            ang = 2 * np.pi * np.arange(slots) / max(slots, 1)
            # the model covers clumps of the largest size anywhere in the injection disc
            pos = self.center_arcsec + r * np.c_[np.cos(ang), np.sin(ang)]
            re = self.study.re_pc.max * self.arcsec_per_pc
            cover = _clumps(pos, np.ones((slots, len(prep.bands))), np.full(slots, re), cl)
            src = _append(self.base, cover)
            acc = prep.accuracy
            if prep.lens is not None:
                acc = dataclasses.replace(acc, source_mode="grid")
            r_ = prep.scene.render
            self.models[slots] = build_model(
                src, prep.bands, lens=prep.lens, field_arcsec=prep.field_arcsec,
                lens_pixel_arcsec=r_.lens_pixel_arcsec, source_pixel_arcsec=r_.source_pixel_arcsec,
                accuracy=acc, dtype=jnp.float64)
        return self.models[slots]


def fingerprint(study: Study) -> str:
    return hashlib.sha256(repr((study.text, study.scene_dicts, study.variants)).encode()).hexdigest()[:16]


def variant(study: Study, v: int) -> Variant:
    """The prepared variant v of a study (cached in this process)."""
    key = (fingerprint(study), v)
    if key not in _CACHE:
        from .. import cosmology, photometry
        from ..model import source_extent
        from ..pipeline import _cosmology, prepare
        from ..scene import scene_from_dict

        d, base_dir = variant_scene_dict(study, v)
        scene = scene_from_dict(d, base_dir=base_dir)
        prep = prepare(scene)
        base = prep.source.astype(jnp.float64)
        cosmo = _cosmology(scene)
        mags = np.asarray(photometry.ab_magnitudes(
            1.0, study.clumps["age_myr"], filters=list(scene.band_names), z=scene.z_source,
            metallicity=study.clumps["metallicity"], sfh="burst", cosmology=cosmo)).reshape(-1)
        zps = np.array([prep.zeropoints[f] for f in scene.band_names])
        center = _host_center(base)
        if center is None:
            center, _ = source_extent(base, prep.accuracy.source_flux_fraction,
                                      prep.accuracy.stamp_flux_fraction)
        _CACHE[key] = Variant(prep, base, np.asarray(center, float), 10 ** (-0.4 * (mags - zps)),
                              float(cosmology.arcsec_per_pc(scene.z_source, cosmo)), study)
    return _CACHE[key]


def _host_center(src: Source):
    for comp in (src.bulge, None if src.disk is None else src.disk.sersic):
        if comp is not None:
            return np.asarray(comp.center_arcsec, float)
    return None


def _clumps(pos, flux, re, cl: dict) -> Clumps:
    n = len(re)
    return Clumps(jnp.asarray(pos, float).reshape(n, 2), jnp.asarray(flux, float),
                  jnp.asarray(re, float), jnp.full(n, cl["sersic_n"]), jnp.full(n, cl["q"]),
                  jnp.zeros(n))


def _append(base: Source, new: Clumps) -> Source:
    """base's clumps followed by `new` (traceable)."""
    if base.clumps is None or base.clumps.count == 0:
        cl = new
    else:
        cl = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b.astype(a.dtype)]),
                                    base.clumps, new)
    return Source(bulge=base.bulge, disk=base.disk, clumps=cl)


# ---------------------------------------------------------------- compiled kernels


@eqx.filter_jit
def _observe(model, src, seed):
    return model.observe(src, jax.random.key(seed))


@eqx.filter_jit
def _inject(model, base, new: Clumps, seeds):
    """For each injected clump (vmapped): noisy images, variances and its noiseless image alone
    (the scene with it minus the scene without it: images are linear in the light), and
    the known scene without it (with sky), what detection subtracts."""
    first = jax.tree_util.tree_map(lambda x: x[:1], new)
    host = model.noiseless(_append(base, eqx.tree_at(lambda c: c.flux, first, first.flux * 0)))

    def one(c, s):
        noisy, clean, var = model.observe(_append(base, c), jax.random.key(s))
        return noisy, var, tuple(a - h for a, h in zip(clean, host))

    noisy, var, alone = jax.vmap(one)(jax.tree_util.tree_map(lambda x: x[:, None], new), seeds)
    return noisy, var, alone, host


@eqx.filter_jit
def fisher_snr(model, base, new: Clumps):
    """Forecast S/N of each injected clump's flux per band, [P, B] (vmapped over clumps).

    Fisher matrix (`uncertainty.fisher_of`) of (flux per band, R_e, centre) with the
    expected Poisson variance (model + sky)/t, marginalised over R_e, centre and the other
    bands (F⁻¹, `safe_inverse`).
    """
    from ..inference.uncertainty import fisher_of, pixel_weights, safe_inverse
    nb = len(model.layouts)

    def one(c):
        def mu(theta):
            cl = eqx.tree_at(lambda k: (k.flux, k.re_arcsec, k.center_arcsec), c,
                             (theta[None, :nb], theta[nb:nb + 1], theta[None, nb + 1:]))
            return jnp.concatenate([im.ravel() for im in model.noiseless(_append(base, cl))])

        theta = jnp.concatenate([c.flux[0], c.re_arcsec, c.center_arcsec[0]])
        cov = safe_inverse(fisher_of(mu, theta, lambda m: pixel_weights(model, None, m)))
        return theta[:nb] / jnp.sqrt(jnp.diag(cov)[:nb])

    return jax.vmap(one)(jax.tree_util.tree_map(lambda x: x[:, None], new))


# ---------------------------------------------------------------- tasks


def run_task(study: Study, task: Task) -> dict:
    """Execute one task; returns plain numpy arrays (what the store writes)."""
    fn = {"simulate": _simulate, "fit": _fit, "inject": _inject_task, "map": _map_task}[task.kind]
    return fn(study, task)


def _sample_clumps(var: Variant, sample, slots: int):
    """The sample's clumps padded to `slots` (zero-flux copies at the centre) and a validity mask."""
    n = len(sample.mass_msun)
    pos = np.tile(var.center_arcsec, (slots, 1))
    pos[:n] += sample.offset_arcsec
    flux = np.zeros((slots, len(var.counts_per_msun)))
    flux[:n] = sample.mass_msun[:, None] * var.counts_per_msun[None, :]
    re = np.full(slots, var.study.re_pc.max * var.arcsec_per_pc)
    re[:n] = sample.re_pc * var.arcsec_per_pc
    return pos, flux, re, np.arange(slots) < n


def _simulate(study: Study, task: Task) -> dict:
    var = variant(study, task.variant)
    sample = draw_sample(study, task.sample)
    slots = bucket(len(sample.mass_msun), study.options["buckets"])
    pos, flux, re, valid = _sample_clumps(var, sample, slots)
    src = _append(var.base, _clumps(pos, flux, re, study.clumps))
    noisy, clean, vr = _observe(var.model(slots), src, np.uint32(sample.noise_seed))
    if not study.options["noise"]:
        noisy = clean
    return {"image": np.stack([np.asarray(x, np.float32) for x in noisy]),
            "noiseless": np.stack([np.asarray(x, np.float32) for x in clean]),
            "variance": np.stack([np.asarray(x, np.float32) for x in vr]),
            "clump_x_arcsec": pos[:, 0], "clump_y_arcsec": pos[:, 1],
            "clump_mass_msun": np.where(valid, np.r_[sample.mass_msun, np.zeros(slots - valid.sum())], 0.0),
            "clump_re_pc": np.where(valid, re / var.arcsec_per_pc, 0.0),
            "clump_re_arcsec": np.where(valid, re, 0.0), "clump_flux": flux,
            "clump_valid": valid, "n_clumps": np.int64(valid.sum()),
            "noise_seed": np.int64(sample.noise_seed), "variant": np.int64(task.variant)}


def _inject_task(study: Study, task: Task) -> dict:
    from photutils.utils.exceptions import NoDetectionsWarning

    from ..inference.completeness import detect, image_peaks, _centroids

    var = variant(study, task.variant)
    opts = study.options
    idx = np.asarray(task.positions)
    pad = np.r_[idx, np.full(opts["positions_per_task"] - idx.size, idx[-1])]   # one shape
    pos = var.center_arcsec + positions(study, task.variant)[pad]
    mass = study.mass_msun.values[task.mass_index]
    re = study.re_pc.values[task.size_index] * var.arcsec_per_pc
    flux = np.tile(mass * var.counts_per_msun, (pad.size, 1))
    new = _clumps(pos, flux, np.full(pad.size, re), study.clumps)
    seeds = np.array([sample_rng(study, 2, task.variant, task.mass_index, task.size_index, int(p))
                      .integers(0, 2**31 - 1) for p in pad], np.uint32)
    model = var.model(1)
    noisy, vr, alone, host = _inject(model, var.base, new, seeds)
    noisy, vr, alone = (np.asarray(x) for x in (noisy, vr, alone))
    nb = len(model.layouts)
    rec = np.zeros((idx.size, nb), bool)
    det = np.zeros_like(rec)
    for p in range(idx.size):
        for b, lay in enumerate(model.layouts):
            # against the known host (and sky): the clump's own detectability, what the
            # Fisher forecast (host known) predicts; set subtract_host = false for sky only
            img = noisy[b][p] - (np.asarray(host[b]) if opts["subtract_host"] else lay.sky_counts_per_s)
            with warnings.catch_warnings():   # an empty image is an answer here, not a problem
                warnings.simplefilter("ignore", NoDetectionsWarning)
                seg = detect(img, np.sqrt(vr[b][p]), nsigma=opts["nsigma"], npixels=opts["npixels"])
            cents = _centroids(img, seg)
            for r, c in image_peaks(alone[b][p]):
                lab = int(seg[r, c])
                if lab:
                    det[p, b] = True
                    cy, cx = cents[lab]
                    rec[p, b] |= np.hypot(cy - r, cx - c) <= opts["match_radius_pix"]
    return {"position_index": idx, "offset_arcsec": pos[:idx.size] - var.center_arcsec,
            "recovered": rec, "detected": det}


def _map_task(study: Study, task: Task) -> dict:
    """Fisher S/N over the map grid and at every injection position, in one vmapped call."""
    var = variant(study, task.variant)
    grid = map_offsets(study)
    off = np.r_[grid, positions(study, task.variant)]
    mass = study.mass_msun.values[task.mass_index]
    re = study.re_pc.values[task.size_index] * var.arcsec_per_pc
    new = _clumps(var.center_arcsec + off, np.tile(mass * var.counts_per_msun, (len(off), 1)),
                  np.full(len(off), re), study.clumps)
    m = study.options["map_npix"]
    snr = np.asarray(fisher_snr(var.model(1), var.base, new))     # [M² + P, B], all at once
    return {"fisher_snr_map": snr[:len(grid)].T.reshape(-1, m, m), "map_offset_arcsec": grid,
            "fisher_snr_injected": snr[len(grid):]}


def _fit(study: Study, task: Task) -> dict:
    from ..inference.run import run_fit

    var = variant(study, task.variant)
    sample = draw_sample(study, task.sample)
    n = len(sample.mass_msun)
    pos, flux, re, _ = _sample_clumps(var, sample, n)
    truth = _append(var.base, _clumps(pos, flux, re, study.clumps))
    model = var.model(n)
    noisy, _, vr = _observe(model, truth, np.uint32(sample.noise_seed))
    # truth-seeded on purpose (the fitter's convergence and errors at scale; README "Studies"):
    # the true count and host, fluxes and sizes off by exp(scatter·N(0,1)), centres moved
    # by scatter·R_e·|N(0,1)| (at least half a pixel) in a random direction
    s = study.options["start_scatter"]
    f = sample.start_factors
    pix = min(b.pixel_arcsec for b in var.prep.bands)
    shift = np.maximum(s * re * np.abs(f[:, 2]), 0.5 * pix)
    start_pos = pos + shift[:, None] * np.c_[np.cos(sample.start_angles), np.sin(sample.start_angles)]
    start = _append(var.base, _clumps(start_pos, flux * np.exp(s * f[:, :1]), re * np.exp(s * f[:, 1]),
                                      study.clumps))
    rows = list(range(var.n_base, var.n_base + n))
    free = {"clumps.flux": rows, "clumps.re_arcsec": rows, "clumps.center_arcsec": rows}
    res = run_fit(model, start, [np.asarray(x) for x in noisy], [np.asarray(x) for x in vr],
                  free=free, likelihood="gaussian", seed=sample.noise_seed)
    cl = res.state.source.clumps
    err = dict(zip(res.uncertainty.labels, np.asarray(res.uncertainty.err)))
    nb = len(var.prep.bands)
    return {"true_x_arcsec": pos[:, 0], "true_y_arcsec": pos[:, 1], "true_flux": flux,
            "true_re_arcsec": re, "true_mass_msun": sample.mass_msun,
            "start_flux": flux * np.exp(s * f[:, :1]),
            "fit_x_arcsec": np.asarray(cl.center_arcsec)[rows, 0],
            "fit_y_arcsec": np.asarray(cl.center_arcsec)[rows, 1],
            "fit_flux": np.asarray(cl.flux)[rows], "fit_re_arcsec": np.asarray(cl.re_arcsec)[rows],
            "err_flux": np.array([[err.get(f"clumps.flux[{k},{b}]", np.nan) for b in range(nb)]
                                  for k in rows]),
            "err_re_arcsec": np.array([err.get(f"clumps.re_arcsec[{k}]", np.nan) for k in rows]),
            "success": np.bool_(res.map_result.success), "variant": np.int64(task.variant)}
