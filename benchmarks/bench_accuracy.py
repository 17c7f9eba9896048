"""Accuracy against time for each approximation of the renderer (issue 7, part a).

Single-effect scenes, each compared with a converged reference (DESIGN.md,
"Accuracy: what is exact"):

- ``sersic``: one Sérsic on a detector grid, n ∈ {0.5, 1, 4}, R_e from 0.3 to
  30 pixels, centred on a pixel centre (the cusp trap). Reference: the exact fan
  integral `sersic_pixel_flux_exact` with 64 angular nodes on every pixel.
  Knobs: source_order (Gauss–Legendre samples per pixel side), exact_core,
  float32.
- ``lensed-near`` / ``lensed-far``: three Sérsic clumps (R_e 0.5–3 mas,
  n 0.5–1.5) lensed by an SIS (θ_E = 1"), near its point caustic (μ ≈ 80) and far
  from it (μ ≈ 3 and 1). Reference: every clump evaluated analytically at every
  ray, 1.25 mas lens pixels with lens_subsampling = 16, float64 (the tested models
  use the paper's 2.5 mas lens pixels).
  Knobs: lens_subsampling, source mode (grid / analytic), source_pixel_arcsec,
  float32.
- ``psf``: a compact Sérsic (R_e = 0.7 pixel) convolved with a Moffat PSF
  (FWHM 2 pixels, β = 2.5, 61 pixels wide), given to the model already averaged
  on the sub-grid of each oversampling (so that only the discrete convolution is
  tested). Reference: Richardson extrapolation (error ∝ h²) of oversampling 15
  and 11.
  Knobs: psf_oversampling, PSF truncation (the PSF cropped and renormalised).

Errors: per-pixel error in units of the sky noise σ = sqrt(sky·t)/t of a deep
exposure (max and rms over the image), total-flux relative error and, for
clumps, the per-clump aperture flux error (apertures: the detector pixels where
that clump dominates the reference image and holds ≥ 1e-4 of its peak). Errors
in σ scale with the source's flux, which is stated per case.

- ``caustic``: one clump (R_e 1 mas) at distances β = 2–256 mas from the SIS point
  caustic, rendered by hybrid, by the linear lens map wherever the rim test allows,
  and by ray tracing: the error of linearisation against distance to the caustic.
  Reference as for the lensed cases.

Run: ``python benchmarks/bench_accuracy.py [--parts sersic,lensed,caustic,deflection,host,psf]
[--quick]`` (a subset of parts writes accuracy_<parts>.*).
Writes benchmarks/results/accuracy.{json,md} and accuracy.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import clumpylen_jax  # noqa: E402
clumpylen_jax.enable_float64()  # float64: the caller's choice
from clumpylen_jax import profiles  # noqa: E402
from clumpylen_jax.lensing.analytic import SIS, MassSheet  # noqa: E402
from clumpylen_jax.model import ACCURACY_PRESETS, Accuracy, Band, build_model  # noqa: E402
from clumpylen_jax.pixels import Grid  # noqa: E402
from clumpylen_jax.source import Clumps, Sersic, Source  # noqa: E402

import _common as C  # noqa: E402

RENDER = jax.jit(lambda m, s: m.band_images(s))


def sigma_of(band: Band):
    return math.sqrt(band.sky_counts_per_s * band.exptime_s) / band.exptime_s


def error_metrics(img, ref, sigma):
    img = np.asarray(img, np.float64)
    ref = np.asarray(ref, np.float64)
    d = img - ref
    return {
        "max_err_sigma": float(np.max(np.abs(d)) / sigma),
        "rms_err_sigma": float(np.sqrt(np.mean(d * d)) / sigma),
        "flux_rel_err": float(abs(d.sum()) / ref.sum()),
        "max_err_rel_peak": float(np.max(np.abs(d)) / np.max(np.abs(ref))),
        "finite": bool(np.all(np.isfinite(img))),
    }


# ============================================================ part 1: one Sérsic on a grid

SERSIC_PIXEL = 0.1
SERSIC_HALF = 40            # 81 × 81 detector pixels
SERSIC_FLUX = 100.0         # counts/s (AB ≈ 21 at a zero point of 26)
SERSIC_BAND = Band("deep", SERSIC_PIXEL, 5511.747, 0.5331)  # WFC3-IR F160W depth of the paper
SERSIC_N = (0.5, 1.0, 4.0)
SERSIC_RE_PIX = (0.3, 1.0, 3.0, 10.0, 30.0)


def sersic_source(n, re_pix, dtype=jnp.float64):
    s = Sersic(jnp.array([SERSIC_FLUX]), jnp.array(re_pix * SERSIC_PIXEL), jnp.array(n),
               jnp.array(0.7), jnp.array(0.3), jnp.array([0.0, 0.0]))
    return Source(bulge=s).astype(dtype)


def sersic_field():
    h = (SERSIC_HALF + 0.5) * SERSIC_PIXEL
    return ((-h, h), (-h, h))


_REF_FNS = {}


def sersic_reference(n, re_pix, nodes=64):
    if nodes not in _REF_FNS:  # one compilation per node count; R_e and n are arguments
        (x0, x1), (y0, y1) = sersic_field()
        g = Grid.covering((x0, x1), (y0, y1), SERSIC_PIXEL)
        xe, ye = jnp.asarray(g.x_edges()), jnp.asarray(g.y_edges())
        _REF_FNS[nodes] = jax.jit(lambda re, nn: profiles.sersic_pixel_flux_exact(
            xe[:-1][None, :], xe[1:][None, :], ye[:-1][:, None], ye[1:][:, None],
            flux=SERSIC_FLUX, re_arcsec=re, n=nn, q=0.7, pa_rad=0.3, center1=0.0, center2=0.0,
            nodes=nodes))
    return np.asarray(_REF_FNS[nodes](jnp.array(re_pix * SERSIC_PIXEL), jnp.array(n)))


def run_sersic(quick=False):
    sigma = sigma_of(SERSIC_BAND)
    refs, ref_check = {}, 0.0
    t0 = time.perf_counter()
    for n in SERSIC_N:
        for re in SERSIC_RE_PIX:
            refs[(n, re)] = sersic_reference(n, re)
            if re in (0.3, 3.0):  # reference convergence: 32 vs 64 angular nodes
                r32 = sersic_reference(n, re, nodes=32)
                ref_check = max(ref_check, float(np.max(np.abs(r32 - refs[(n, re)])) / sigma))
    print(f"  sersic references: {time.perf_counter() - t0:.1f}s, 32 vs 64 nodes: "
          f"{ref_check:.2e} σ", flush=True)
    if quick:
        configs = [(1, 0, "float64"), (3, 5, "float64"), (3, 5, "float32")]
    else:
        configs = [(o, c, "float64") for o in (1, 2, 3, 4, 6) for c in (0, 3, 5, 7)]
        configs += [(8, 7, "float64"), (2, 3, "float32"), (3, 5, "float32"), (5, 7, "float32")]
    rows = []
    for order, core, dt in configs:
        dtype = jnp.float32 if dt == "float32" else jnp.float64
        acc = Accuracy(source_order=order, exact_core=core)
        s0 = sersic_source(4.0, 3.0, dtype)
        t = time.perf_counter()
        model = build_model(s0, [SERSIC_BAND], field_arcsec=sersic_field(), accuracy=acc,
                            dtype=dtype)
        C.block(RENDER(model, s0))
        cold = time.perf_counter() - t
        warm = C.warm_time(RENDER, model, s0)
        mem = C.compiled_bytes(RENDER, model, s0)
        worst = {"max_err_sigma": 0.0, "rms_err_sigma": 0.0, "flux_rel_err": 0.0}
        detail = {}
        finite = True
        for (n, re), ref in refs.items():
            img = RENDER(model, sersic_source(n, re, dtype))[0]
            if img.dtype != jnp.dtype(dtype):
                raise AssertionError(f"dtype changed: {img.dtype} from {dtype}")
            m = error_metrics(img, ref, sigma)
            finite &= m.pop("finite")
            detail[f"n={n},re={re}px"] = m
            for k in worst:
                worst[k] = max(worst[k], m[k])
        row = dict(case="sersic", knob=f"order={order} core={core}", source_order=order,
                   exact_core=core, dtype=dt, cold_s=cold, warm_s=warm,
                   mem_mb=None if mem is None else mem / 2**20, finite=finite, **worst,
                   detail=detail)
        rows.append(row)
        print(f"  sersic {row['knob']:18s} {dt}: max {worst['max_err_sigma']:.3g}σ "
              f"flux {worst['flux_rel_err']:.2e} warm {warm * 1e3:.2f} ms cold {cold:.1f}s",
              flush=True)
    meta = dict(pixel_arcsec=SERSIC_PIXEL, shape=[2 * SERSIC_HALF + 1] * 2, flux=SERSIC_FLUX,
                sigma=sigma, n=SERSIC_N, re_pix=SERSIC_RE_PIX, q=0.7, pa_rad=0.3,
                reference="sersic_pixel_flux_exact, 64 angular nodes",
                reference_convergence_sigma=ref_check)
    return rows, meta


# ============================================================ part 2: lensed clumps, SIS

LENS = SIS(jnp.array(1.0), jnp.array([0.0, 0.0]))
LENS_BAND = Band("nircam-sw", 0.03, 2920.4, 0.160606)   # F200W depth of the paper
LENS_PIXEL = 0.0025
CLUMP_FLUX = 1.0            # counts/s per clump (AB ≈ 28 at a zero point of 28)
CLUMP_RE = np.array([0.0005, 0.001, 0.003])   # arcsec: 0.5, 1, 3 mas
CLUMP_N = np.array([0.5, 1.0, 1.5])   # n = 4 clumps: see README (stamp size)
CLUMP_Q = np.array([1.0, 0.6, 0.8])
CLUMP_PA = np.array([0.0, 0.7, 2.0])


def lensed_case(name):
    if name == "lensed-near":  # around the SIS point caustic: μ ≈ 2/β = 80+
        phi = np.deg2rad([0.0, 60.0, 120.0])
        centers = 0.012 * np.stack([np.cos(phi), np.sin(phi)], axis=1)
        field = ((-1.2, 1.2), (-1.2, 1.2))
    else:                      # far from it: two images, μ ≈ 3 and 1
        centers = np.array([[0.5, 0.0], [0.45, 0.05], [0.56, -0.04]])
        field = ((-0.75, 1.8), (-0.6, 0.6))
    return centers, field


def clumps_source(centers, nb=1, dtype=jnp.float64):
    n = len(centers)
    flux = np.full((n, 1), CLUMP_FLUX) if nb == 1 else CLUMP_FLUX * np.eye(n)
    return Source(clumps=Clumps(jnp.asarray(centers), jnp.asarray(flux), jnp.asarray(CLUMP_RE),
                                jnp.asarray(CLUMP_N), jnp.asarray(CLUMP_Q),
                                jnp.asarray(CLUMP_PA))).astype(dtype)


REF_LENS_PIXEL = 0.00125


def lensed_model(src, field, acc, dtype, source_pixel, nb=1, lens_pixel=LENS_PIXEL):
    bands = [LENS_BAND] if nb == 1 else [Band(f"c{k}", LENS_BAND.pixel_arcsec,
                                              LENS_BAND.exptime_s, LENS_BAND.sky_counts_per_s)
                                         for k in range(nb)]
    return build_model(src, bands, lens=LENS, field_arcsec=field, lens_pixel_arcsec=lens_pixel,
                       source_pixel_arcsec=source_pixel, accuracy=acc, dtype=dtype)


def clump_apertures(per_clump):
    """Masks [N, ny, nx]: pixels where clump k dominates and holds ≥ 1e-4 of its peak."""
    per = np.asarray(per_clump)
    dominant = np.argmax(per, axis=0)
    masks = []
    for k in range(per.shape[0]):
        masks.append((dominant == k) & (per[k] >= 1e-4 * per[k].max()))
    return np.array(masks)


def run_lensed(quick=False):
    sigma = sigma_of(LENS_BAND)
    rows, meta = [], {}
    for case in ("lensed-near", "lensed-far"):
        centers, field = lensed_case(case)
        ref_acc = Accuracy(lens_subsampling=16, source_mode="analytic")
        t = time.perf_counter()
        src_b = clumps_source(centers, nb=len(centers))
        ref_model = lensed_model(src_b, field, ref_acc, jnp.float64, 0.00025, nb=len(centers),
                                 lens_pixel=REF_LENS_PIXEL)
        per = np.array([np.asarray(x) for x in RENDER(ref_model, src_b)])
        ref = per.sum(axis=0)
        masks = clump_apertures(per)
        ref_ap = np.array([ref[m].sum() for m in masks])
        # reference convergence: 12 × 12 rays per lens pixel instead of 16 × 16
        chk_model = lensed_model(clumps_source(centers), field,
                                 Accuracy(lens_subsampling=12, source_mode="analytic"),
                                 jnp.float64, 0.00025, lens_pixel=REF_LENS_PIXEL)
        chk = np.asarray(RENDER(chk_model, clumps_source(centers))[0])
        conv = error_metrics(chk, ref, sigma)
        print(f"  {case} reference {time.perf_counter() - t:.1f}s; 12² vs 16² rays: "
              f"{conv['max_err_sigma']:.2e}σ, flux {conv['flux_rel_err']:.1e}; "
              f"image flux {ref.sum():.3g} (μ_total ≈ {ref.sum() / (len(centers) * CLUMP_FLUX):.3g})",
              flush=True)
        meta[case] = dict(centers=centers.tolist(), field=field, re_arcsec=CLUMP_RE.tolist(),
                          n=CLUMP_N.tolist(), clump_flux=CLUMP_FLUX, sigma=sigma,
                          lens="SIS theta_E=1", lens_pixel_arcsec=LENS_PIXEL,
                          detector_pixel_arcsec=LENS_BAND.pixel_arcsec,
                          reference="analytic, lens pixel 1.25 mas, lens_subsampling=16, float64",
                          reference_convergence=conv,
                          aperture_ref_flux=ref_ap.tolist(),
                          total_magnification=float(ref.sum() / (len(centers) * CLUMP_FLUX)))
        if quick:
            configs = [(1, "grid", 0.00025, "float64"), (4, "grid", 0.00025, "float64"),
                       (3, "analytic", None, "float64"), (4, "grid", 0.00025, "float32"),
                       (4, "hybrid", 0.00025, "float64"), (4, "hybrid", 0.00025, "float32")]
        else:
            configs = [(ls, "grid", 0.00025, "float64") for ls in (1, 2, 3, 4, 6)]
            configs += [(ls, "analytic", None, "float64") for ls in (1, 2, 3, 4, 6)]
            configs += [(3, "grid", sp, "float64") for sp in (0.001, 0.0005, 0.000125)]
            configs += [(3, "grid", 0.00025, "float32"), (3, "analytic", None, "float32"),
                        (5, "grid", 0.000125, "float64")]
            # hybrid: clumps off the caustic through the local linear lens map (no rays);
            # the ray count then only matters for clumps near the caustic
            configs += [(ls, "hybrid", 0.00025, "float64") for ls in (1, 4)]
            configs += [(4, "hybrid", 0.00025, "float32")]
        for ls, mode, sp, dt in configs:
            dtype = jnp.float32 if dt == "float32" else jnp.float64
            acc = Accuracy(lens_subsampling=ls, source_mode=mode)
            src = clumps_source(centers, dtype=dtype)
            t = time.perf_counter()
            model = lensed_model(src, field, acc, dtype, sp or 0.00025)
            img = C.block(RENDER(model, src))[0]
            cold = time.perf_counter() - t
            if img.dtype != jnp.dtype(dtype):
                raise AssertionError(f"dtype changed: {img.dtype} from {dtype}")
            warm = C.warm_time(RENDER, model, src, repeats=3)
            mem = C.compiled_bytes(RENDER, model, src)
            img = np.asarray(img, np.float64)
            m = error_metrics(img, ref, sigma)
            ap = np.array([img[mk].sum() for mk in masks])
            clump_err = np.abs(ap - ref_ap) / ref_ap
            sp_mas = None if mode == "analytic" else (sp or 0.00025) * 1e3
            knob = f"sub={ls} {mode}" + ("" if sp_mas is None else f" src={sp_mas:g}mas")
            row = dict(case=case, knob=knob, lens_subsampling=ls, source_mode=mode,
                       source_pixel_mas=sp_mas, dtype=dt, cold_s=cold, warm_s=warm,
                       mem_mb=None if mem is None else mem / 2**20,
                       model_mb=C.tree_bytes(model) / 2**20,
                       clump_flux_err=float(clump_err.max()),
                       clump_flux_errs=clump_err.tolist(), **m)
            rows.append(row)
            print(f"  {case} {knob:28s} {dt}: max {m['max_err_sigma']:.3g}σ clump "
                  f"{clump_err.max():.2e} warm {warm * 1e3:.1f} ms cold {cold:.1f}s",
                  flush=True)
    return rows, meta


# ============================================================ part 2b: linearisation vs caustic distance

CAUSTIC_BETA_MAS = (2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0)
CAUSTIC_SETTINGS = {
    "reference's own convergence: analytic, 12² rays": "convergence",
    "hybrid (default)": Accuracy(),
    "linearised wherever the rim test allows (tolerance ∞)": Accuracy(linearise_tolerance=1e9),
    "grid, 4² rays (ray-traced)": Accuracy(source_mode="grid"),
}


def run_caustic(quick=False):
    """One clump (R_e 1 mas, n 1, q 0.7) at distance β from the SIS point caustic.

    For each β: the clump alone, rendered by hybrid (linearised only when its images pass
    the linearisation test), by the linear lens map wherever the rim test allows (the
    tolerance off: what linearisation costs near the caustic), and by ray tracing (grid
    mode, 4² rays per lens pixel), against every ray analytic at 16² rays per 1.25 mas
    lens pixel. Linearisation's error grows as the clump nears the caustic (the lens
    map's curvature across the clump's images, relative to their size); the rim test
    (8 points on the clump's 99.99 % stamp circle with as many images as its centre)
    refuses clumps whose stamp the caustic crosses.
    """
    sigma = sigma_of(LENS_BAND)
    betas = CAUSTIC_BETA_MAS[::2] if quick else CAUSTIC_BETA_MAS
    rows = []
    for k, beta_mas in enumerate(betas):
        phi = np.deg2rad(20.0 + 37.0 * k)
        center = np.array([[np.cos(phi), np.sin(phi)]]) * beta_mas * 1e-3
        src = Source(clumps=Clumps(jnp.asarray(center), jnp.asarray([[CLUMP_FLUX]]),
                                   jnp.asarray([0.001]), jnp.asarray([1.0]), jnp.asarray([0.7]),
                                   jnp.asarray([0.4])))
        field = ((-1.4, 1.4), (-1.4, 1.4))
        ref_model = lensed_model(src, field, Accuracy(lens_subsampling=16, source_mode="analytic"),
                                 jnp.float64, 0.00025, lens_pixel=REF_LENS_PIXEL)
        ref = np.asarray(RENDER(ref_model, src)[0])
        del ref_model
        for name, acc in CAUSTIC_SETTINGS.items():
            t = time.perf_counter()
            if acc == "convergence":
                model = lensed_model(src, field, Accuracy(lens_subsampling=12,
                                                          source_mode="analytic"),
                                     jnp.float64, 0.00025, lens_pixel=REF_LENS_PIXEL)
            else:
                model = lensed_model(src, field, acc, jnp.float64, 0.00025)
            img = np.asarray(C.block(RENDER(model, src))[0])
            cold = time.perf_counter() - t
            warm = C.warm_time(RENDER, model, src, repeats=3)
            m = error_metrics(img, ref, sigma)
            lin = model.lin_images
            mu = float(ref.sum() / CLUMP_FLUX)
            row = dict(case="caustic", knob=name, beta_mas=beta_mas, magnification=mu,
                       linearised=bool(lin is not None and lin.count > 0),
                       images=None if lin is None else int(lin.count), dtype="float64",
                       clump_flux_err=float(abs(img.sum() / ref.sum() - 1)), cold_s=cold,
                       warm_s=warm, **m)
            rows.append(row)
            print(f"  caustic β={beta_mas:g} mas μ={mu:.1f} {name:55s} linearised="
                  f"{row['linearised']} max {m['max_err_sigma']:.3g}σ flux "
                  f"{row['clump_flux_err']:.2e} warm {warm * 1e3:.1f} ms", flush=True)
    meta = dict(clump="R_e 1 mas, n 1, q 0.7, flux 1 count/s", lens="SIS theta_E=1",
                sigma=sigma, detector_pixel_arcsec=LENS_BAND.pixel_arcsec,
                reference="analytic, lens pixel 1.25 mas, lens_subsampling=16, float64")
    return rows, meta


# ============================================================ part 2c: deflection maps

DEFLECTION_MAP_MAS = (5.0, 10.0, 20.0, 40.0, 80.0)


def sis_deflection_map(pixel_arcsec, half=2.0):
    """The SIS of LENS rasterised on a map (pixel centres on multiples of the pixel)."""
    from clumpylen_jax.lensing.grid import DeflectionGrid
    x = np.arange(-half, half + pixel_arcsec / 2, pixel_arcsec)
    xx, yy = np.meshgrid(x, x)
    r = np.hypot(xx, yy)
    r = np.where(r > 0, r, 1.0)
    return DeflectionGrid(jnp.asarray(xx / r), jnp.asarray(yy / r), jnp.asarray([x[0], x[0]]),
                          pixel_arcsec)


def run_deflection(quick=False):
    """The lensed clumps of part 2 through the SIS rasterised on maps of 5–80 mas pixels
    (bilinear interpolation, the only order implemented) against the analytic SIS, both
    rendered at the default accuracy: the error of the map's resolution and interpolation
    alone (HFF maps: 30–60 mas)."""
    sigma = sigma_of(LENS_BAND)
    rows = []
    for case in ("lensed-near", "lensed-far"):
        centers, field = lensed_case(case)
        src = clumps_source(centers)
        acc = ACCURACY_PRESETS["default"]
        ref = np.asarray(RENDER(lensed_model(src, field, acc, jnp.float64, 0.00025), src)[0])
        for map_mas in DEFLECTION_MAP_MAS[::2] if quick else DEFLECTION_MAP_MAS:
            t = time.perf_counter()
            model = build_model(src, [LENS_BAND], lens=sis_deflection_map(map_mas * 1e-3),
                                field_arcsec=field, lens_pixel_arcsec=LENS_PIXEL,
                                source_pixel_arcsec=0.00025, accuracy=acc)
            img = np.asarray(C.block(RENDER(model, src))[0])
            cold = time.perf_counter() - t
            warm = C.warm_time(RENDER, model, src, repeats=3)
            m = error_metrics(img, ref, sigma)
            rows.append(dict(case="deflection", knob=f"{case}: bilinear map, {map_mas:g} mas",
                             dtype="float64", cold_s=cold, warm_s=warm, **m))
            print(f"  deflection {case} map {map_mas:g} mas: max {m['max_err_sigma']:.3g}σ "
                  f"flux {m['flux_rel_err']:.2e} warm {warm * 1e3:.1f} ms", flush=True)
    meta = dict(lens="SIS theta_E=1 rasterised (map half-size 2\")", sigma=sigma,
                reference="the same scene through the analytic SIS, default accuracy",
                clumps="part 2's three clumps per case, 1 count/s each")
    return rows, meta


# ============================================================ part 2d: a compact lensed host

HOST_KAPPA = 0.5                  # a mass sheet: β = (1 − κ) θ, a linear lens map
HOST_RE_MAS = (1.0, 2.5, 5.0, 20.0)
HOST_SETTINGS = {
    "sampled at lens-pixel centres (exact_core 0)": Accuracy(exact_core=0),
    "fast": ACCURACY_PRESETS["fast"],
    "default (exact footprints near the centre)": ACCURACY_PRESETS["default"],
    "high": ACCURACY_PRESETS["high"],
}


def run_host(quick=False):
    """A compact n = 4 host (q 0.7, 10 counts/s) behind a mass sheet κ = 0.5, 2.5 mas lens
    pixels, 0.03" detector pixels, source_flux_fraction 0.99999 in every setting.

    The sheet maps the source linearly, so the lensed image is exactly an unlensed Sérsic
    with R_e / (1 − κ), flux / (1 − κ)² and centre / (1 − κ): the reference is that
    profile's exact pixel integrals (the unlensed path, tested against scipy). What is
    measured is the host's sampling on the lens plane near its cusp: at lens-pixel
    centres, or (default) integrated exactly over sub-pixel footprints there.
    """
    sigma = sigma_of(LENS_BAND)
    flux, center = 10.0, np.array([0.0113, -0.0071])
    field = ((-0.9, 0.9), (-0.9, 0.9))
    lens = MassSheet(jnp.asarray(HOST_KAPPA), jnp.asarray([0.0, 0.0]))
    rows = []
    for re_mas in HOST_RE_MAS[1:3] if quick else HOST_RE_MAS:
        def host(f, re, c):
            return Source(bulge=Sersic(jnp.asarray([f]), jnp.asarray(re), jnp.asarray(4.0),
                                       jnp.asarray(0.7), jnp.asarray(0.4), jnp.asarray(c)))
        s = 1 - HOST_KAPPA
        ref_src = host(flux / s**2, re_mas * 1e-3 / s, center / s)
        ref_model = build_model(ref_src, [LENS_BAND], field_arcsec=field,
                                accuracy=Accuracy(source_order=6, exact_core=7))
        ref = np.asarray(RENDER(ref_model, ref_src)[0])
        src = host(flux, re_mas * 1e-3, center)
        for name, acc in HOST_SETTINGS.items():
            acc = dataclasses.replace(acc, source_flux_fraction=0.99999)
            t = time.perf_counter()
            model = build_model(src, [LENS_BAND], lens=lens, field_arcsec=field,
                                lens_pixel_arcsec=LENS_PIXEL, accuracy=acc)
            img = np.asarray(C.block(RENDER(model, src))[0])
            cold = time.perf_counter() - t
            warm = C.warm_time(RENDER, model, src, repeats=3)
            m = error_metrics(img, ref, sigma)
            core = model.host_core_index
            rows.append(dict(case="lensed-host", knob=f"R_e {re_mas:g} mas: {name}",
                             dtype="float64", cold_s=cold, warm_s=warm,
                             exact_pixels=0 if core is None else int(core.size), **m))
            print(f"  host R_e={re_mas:g} mas {name:45s} max {m['max_err_sigma']:.3g}σ "
                  f"({m['max_err_rel_peak']:.2e} of peak) flux {m['flux_rel_err']:.2e} "
                  f"warm {warm * 1e3:.1f} ms", flush=True)
    meta = dict(host="n 4, q 0.7, 10 counts/s", lens=f"mass sheet kappa={HOST_KAPPA}",
                sigma=sigma, lens_pixel_arcsec=LENS_PIXEL,
                reference="the unlensed image of the equivalent Sérsic, exact pixels "
                          "(source_order 6, exact_core 7)")
    return rows, meta


# ============================================================ part 3: PSF oversampling, truncation

PSF_PIXEL = 0.1
PSF_SIDE = 61               # detector pixels
PSF_BAND_KW = dict(exptime_s=2920.4, sky_counts_per_s=0.160606)


def moffat_psf(fine, side_pix=PSF_SIDE, fwhm_pix=2.0, beta=2.5):
    """Moffat PSF area-averaged (4 × 4 samples) on a grid of `fine` samples per detector pixel."""
    n = side_pix * fine
    x = (np.arange(n) - (n - 1) / 2) / fine
    xx, yy = np.meshgrid(x, x)
    alpha = fwhm_pix / (2 * math.sqrt(2 ** (1 / beta) - 1))
    o = (np.arange(4) - 1.5) / 4 / fine
    k = np.zeros_like(xx)
    for dy in o:
        for dx in o:
            k += (1 + ((xx + dx) ** 2 + (yy + dy) ** 2) / alpha**2) ** (-beta)
    return k / k.sum()


def run_psf(quick=False):
    src = Source(bulge=Sersic(jnp.array([SERSIC_FLUX]), jnp.array(0.07), jnp.array(2.0),
                              jnp.array(0.8), jnp.array(0.4), jnp.array([0.013, -0.021])))
    h = 20.5 * PSF_PIXEL
    field = ((-h, h), (-h, h))

    def band(s, side=PSF_SIDE):
        return Band("psf", PSF_PIXEL, psf=moffat_psf(s, side), psf_pixel_arcsec=PSF_PIXEL / s,
                    **PSF_BAND_KW)

    sigma = sigma_of(band(1))

    def render_at(s):
        acc = Accuracy(source_order=6, exact_core=9, psf_oversampling=s)
        return np.asarray(RENDER(build_model(src, [band(s)], field_arcsec=field,
                                             accuracy=acc), src)[0])

    t = time.perf_counter()
    # the oversampling error is O(h²) (midpoint rule on the sub-grid): Richardson-extrapolate
    i15, i13, i11 = render_at(15), render_at(13), render_at(11)
    ref = (225 * i15 - 121 * i11) / (225 - 121)
    alt = (225 * i15 - 169 * i13) / (225 - 169)
    conv = error_metrics(alt, ref, sigma)
    conv["plain_15_vs_extrapolated"] = error_metrics(i15, ref, sigma)["max_err_sigma"]
    print(f"  psf reference {time.perf_counter() - t:.0f}s: extrapolated (15,13) vs (15,11): "
          f"{conv['max_err_sigma']:.2e}σ; plain 15 vs reference "
          f"{conv['plain_15_vs_extrapolated']:.2e}σ", flush=True)
    configs = [(s, PSF_SIDE, "float64") for s in ((1, 3) if quick else (1, 3, 5, 7))]
    if not quick:
        configs += [(3, side, "float64") for side in (41, 21, 11, 5)]
        configs += [(3, PSF_SIDE, "float32")]
    rows = []
    for s, side, dt in configs:
        dtype = jnp.float32 if dt == "float32" else jnp.float64
        srcd = src.astype(dtype)
        t = time.perf_counter()
        model = build_model(srcd, [band(s, side)], field_arcsec=field,
                            accuracy=Accuracy(psf_oversampling=s), dtype=dtype)
        img = C.block(RENDER(model, srcd))[0]
        cold = time.perf_counter() - t
        warm = C.warm_time(RENDER, model, srcd)
        mem = C.compiled_bytes(RENDER, model, srcd)
        m = error_metrics(img, ref, sigma)
        row = dict(case="psf", knob=f"oversampling={s} psf={side}px", psf_oversampling=s,
                   psf_side_pix=side, dtype=dt, cold_s=cold, warm_s=warm,
                   mem_mb=None if mem is None else mem / 2**20, **m)
        rows.append(row)
        print(f"  psf {row['knob']:26s} {dt}: max {m['max_err_sigma']:.3g}σ flux "
              f"{m['flux_rel_err']:.2e} warm {warm * 1e3:.2f} ms", flush=True)
    meta = dict(pixel_arcsec=PSF_PIXEL, psf="Moffat FWHM 2 px, beta 2.5, 61 px, averaged on the sub-grid",
                source="Sersic n=2, R_e=0.7 px, q=0.8, flux 100", sigma=sigma,
                reference="Richardson (h^2) extrapolation of psf_oversampling 15 and 11, "
                          "source_order=6, exact_core=9",
                reference_convergence=conv)
    return rows, meta


# ============================================================ report


def plot(rows, path):
    import matplotlib
    import matplotlib.ticker
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cases = [c for c in ("sersic", "lensed-near", "lensed-far", "caustic", "deflection",
                         "lensed-host", "psf")
             if any(r["case"] == c for r in rows)]
    fig, axes = plt.subplots(1, len(cases), figsize=(4.2 * len(cases), 3.8), squeeze=False)
    for ax, case in zip(axes[0], cases):
        rs = [r for r in rows if r["case"] == case]
        if case == "caustic":
            # error against distance to the caustic, one line per setting
            for k, knob in enumerate(dict.fromkeys(r["knob"] for r in rs)):
                kr = [r for r in rs if r["knob"] == knob]
                # hybrid coincides with ray tracing until it linearises: dashed, on top
                ax.plot([r["beta_mas"] for r in kr], [max(r["max_err_sigma"], 1e-12) for r in kr],
                        ("-", "--", "-", "-")[k % 4], marker="o", ms=3, zorder=3 - (k != 1),
                        label=knob.split(" (")[0].split(",")[0])
                lin = [r for r in kr if r["linearised"]]
                ax.plot([r["beta_mas"] for r in lin], [max(r["max_err_sigma"], 1e-12) for r in lin],
                        "k.", ms=2)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.axhline(1.0, color="k", lw=0.5, ls="--")
            ax.set_xlabel("distance from the caustic β (mas)")
            ax.set_ylabel("max |error| / σ_sky")
            ax.set_title("clump near an SIS caustic (dots: linearised)", fontsize=9)
            ax.legend(fontsize=6)
            continue
        for r in rs:
            marker = "s" if r["dtype"] == "float32" else "o"
            group = (r.get("source_mode") or r.get("exact_core") or r.get("psf_side_pix"))
            ax.scatter(r["warm_s"] * 1e3, max(r["max_err_sigma"], 1e-12), marker=marker,
                       label=None)
            ax.annotate(r["knob"].replace("core=", "c").replace("order=", "o")
                        .replace("oversampling=", "os").replace(" analytic", " an"),
                        (r["warm_s"] * 1e3, max(r["max_err_sigma"], 1e-12)), fontsize=5,
                        alpha=0.7)
            del group
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # no crowded labels
        ax.set_yscale("log")
        ax.axhline(1.0, color="k", lw=0.5, ls="--")
        ax.axhline(0.1, color="k", lw=0.5, ls=":")
        ax.set_xlabel("warm render time (ms)")
        ax.set_ylabel("max |error| / σ_sky")
        ax.set_title(case + " (squares: float32)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


COLUMNS = [("knob", "setting"), ("dtype", "dtype"), ("max_err_sigma", "max |Δ|/σ"),
           ("max_err_rel_peak", "max |Δ|/peak"),
           ("rms_err_sigma", "rms Δ/σ"), ("flux_rel_err", "total flux rel. err"),
           ("clump_flux_err", "worst clump flux rel. err"), ("warm_s", "warm s"),
           ("cold_s", "cold s"), ("mem_mb", "XLA MiB")]


CAUSTIC_COLUMNS = [("beta_mas", "β from caustic (mas)"), ("magnification", "μ"),
                   ("knob", "setting"), ("linearised", "linearised"),
                   ("max_err_sigma", "max |Δ|/σ"), ("max_err_rel_peak", "max |Δ|/peak"),
                   ("clump_flux_err", "clump flux rel. err"), ("warm_s", "warm s")]


def markdown(rows, meta):
    out = ["# Accuracy against time", "",
           "Generated by `benchmarks/bench_accuracy.py`. σ is the sky noise per detector pixel "
           "of the case's exposure; errors are against the converged reference of each case "
           "(see the JSON `meta` for its definition and its own convergence). Warm: median "
           "of repeated calls of the compiled render; cold: build + compile + first call.", ""]
    for case in ("sersic", "lensed-near", "lensed-far", "caustic", "deflection", "lensed-host",
                 "psf"):
        rs = [r for r in rows if r["case"] == case]
        if not rs:
            continue
        out += [f"## {case}", "", "```", str({k: v for k, v in meta.get(case, {}).items()
                                              if k not in ("aperture_ref_flux",)}), "```", ""]
        cols = [c for c in CAUSTIC_COLUMNS if case == "caustic"] or COLUMNS
        cols = [c for c in cols if any(r.get(c[0]) is not None for r in rs)]
        out += [C.markdown_table(rs, cols), ""]
    return "\n".join(out)


# part name → (runner, key of its meta entry; None: the runner's meta is merged)
PARTS = {"sersic": (run_sersic, "sersic"), "lensed": (run_lensed, None),
         "caustic": (run_caustic, "caustic"), "deflection": (run_deflection, "deflection"),
         "host": (run_host, "lensed-host"), "psf": (run_psf, "psf")}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parts", default=",".join(PARTS))
    ap.add_argument("--quick", action="store_true", help="a few settings per part")
    args = ap.parse_args(argv)
    parts = args.parts.split(",")
    if set(parts) - set(PARTS):
        ap.error(f"--parts {args.parts}: expected names from {','.join(PARTS)}")
    rows, meta = [], {"machine": C.machine(), "quick": args.quick}
    t0 = time.perf_counter()
    for part in parts:
        run, key = PARTS[part]
        r, m = run(args.quick)
        rows += r
        if key is None:          # "lensed" holds one meta entry per case
            meta.update(m)
        else:
            meta[key] = m
    meta["total_s"] = time.perf_counter() - t0
    meta["peak_rss_mb"] = C.peak_rss_mb()
    suffix = "" if parts == list(PARTS) else "_" + "_".join(parts)
    C.write_json("accuracy" + suffix, {"meta": meta, "rows": rows})
    C.write_text(f"accuracy{suffix}.md", markdown(rows, meta))
    plot(rows, C.RESULTS / f"accuracy{suffix}.png")
    print(f"done in {meta['total_s']:.0f}s; results in {C.RESULTS}")
    return rows, meta


if __name__ == "__main__":
    main()
