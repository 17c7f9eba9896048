"""Speed against lenstronomy on the same lensed clumpy scene (issue 7, part b).

Both codes render the same scene:
- the same deflection map: an SIS (θ_E = 1") rasterised on a 0.01" grid
  (lenstronomy: ``INTERPOL`` with its default bilinear spline; this project:
  `DeflectionGrid`, bilinear);
- the same N Sérsic clumps (lenstronomy: ``SERSIC_ELLIPSE``), converted so that
  the profiles are identical: lenstronomy's R_sersic is the product-average
  radius √q·R_e and its b(n) is the linear fit 1.9992 n − 0.3271, so its R_sersic
  is rescaled by (b_fit/b_exact)^n and its amp set to I(R_sersic); its Sérsic
  floors the radius at ``smoothing`` = 1e-4" (0.1 mas) by default, which removes
  0.6–0.9 % of the light of the 0.5–0.8 mas n = 1 clumps here (measured against
  brute-force ray tracing), so it is given smoothing = 1e-9";
- the same pixels: 0.03" detector pixels, +x = +θ1 (lenstronomy's pixel grid is
  given an explicit transform, not its default East-left one), the same
  21 × 21 Moffat PSF at detector sampling.

Check first (`--check`, always run): lenstronomy with supersampling 12 (point
samples at the centres of 2.5 mas sub-pixels) against this project with the
same rays (2.5 mas lens pixels, lens_subsampling = 1, clumps analytic, PSF at
detector sampling); the residual is reported.

Timing, in one run, for N = 10, 30, 100, 300, 1000 clumps (warm: the median of
repeated calls once compiled/cached; lenstronomy in its fastest honest mode,
``compute_mode="adaptive"`` supersampling only the detector pixels the source
lands on, the same pixels this project traces):
- "matched rays": lenstronomy supersampling 12 vs this project lens_subsampling 1
  (the check configuration), clumps analytic and on the source grid;
- "matched accuracy": this project's hybrid mode (clumps away from the caustic
  integrated through the local linear lens map, no rays) and grid mode (4 × 4
  Gauss–Legendre rays per lens pixel, clumps on the 0.25 mas source grid) vs
  lenstronomy at the smallest supersampling of LT_SUPERSAMPLING whose error is
  no larger than hybrid's (and, for comparison with earlier runs, at 36).
The error of every setting against a converged reference (lenstronomy at
supersampling 288, i.e. 0.1 mas point samples; 216 vs 288 given as its own
convergence) is measured on the 30-clump scene first, so that the ratios
compare settings of known accuracy.

Run: ``python benchmarks/bench_lenstronomy.py [--counts 10,30,100,300,1000] [--quick]``;
the larger counts in their own processes with ``--counts 300 --append`` (XLA's CPU JIT
can fail with "LLVM compilation error: Cannot allocate memory" after many models).
Needs lenstronomy (optional: ``pip install lenstronomy``). Writes
benchmarks/results/lenstronomy.{json,md}.
"""

from __future__ import annotations

import argparse
import json
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
from clumpylen_jax.lensing.grid import DeflectionGrid  # noqa: E402
from clumpylen_jax.model import Accuracy, Band, build_model  # noqa: E402
from clumpylen_jax.pixels import Grid  # noqa: E402
from clumpylen_jax.source import Clumps, Source  # noqa: E402

import _common as C  # noqa: E402

PIXEL = 0.03
LENS_PIXEL = 0.0025
SOURCE_PIXEL = 0.00025
FIELD = ((-1.05, 1.65), (-1.35, 1.35))     # 90 × 90 detector pixels (square: lenstronomy
# images are [nx, ny]-shaped, a trap with non-square grids)
MAP_PIXEL = 0.01
MAP_HALF = 2.0
THETA_E = 1.0
SOURCE_CENTER = np.array([0.25, 0.05])
SOURCE_RADIUS = 0.08
EXPTIME, SKY = 2920.4, 0.160606
RENDER = jax.jit(lambda m, s: m.band_images(s))


def sis_map():
    x = np.arange(-MAP_HALF, MAP_HALF + MAP_PIXEL / 2, MAP_PIXEL)
    xx, yy = np.meshgrid(x, x)            # arrays [y, x], ascending axes
    r = np.hypot(xx, yy)
    r = np.where(r > 0, r, 1.0)
    return x, THETA_E * xx / r, THETA_E * yy / r


def moffat_kernel(side=21, fwhm_pix=2.5, beta=2.5):
    x = np.arange(side) - side // 2
    xx, yy = np.meshgrid(x, x)
    alpha = fwhm_pix / (2 * math.sqrt(2 ** (1 / beta) - 1))
    k = (1 + (xx**2 + yy**2) / alpha**2) ** (-beta)
    return k / k.sum()


def make_clumps(n, seed=1):
    rng = np.random.default_rng(seed)
    r = SOURCE_RADIUS * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    centers = SOURCE_CENTER + np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)
    re = np.exp(rng.uniform(np.log(0.0005), np.log(0.003), n))
    nn = rng.choice([0.5, 1.0], n)
    q = rng.uniform(0.3, 1.0, n)
    pa = rng.uniform(0, np.pi, n)
    flux = 10.0 * rng.dirichlet(np.ones(n))[:, None]          # 10 counts/s in all
    return dict(center=centers, flux=flux, re=re, n=nn, q=q, pa=pa)


def our_source(c):
    return Source(clumps=Clumps(jnp.asarray(c["center"]), jnp.asarray(c["flux"]),
                                jnp.asarray(c["re"]), jnp.asarray(c["n"]), jnp.asarray(c["q"]),
                                jnp.asarray(c["pa"])))


def lenstronomy_kwargs(c):
    """SERSIC_ELLIPSE keywords giving the same profiles as this project's clumps."""
    out = []
    for k in range(len(c["re"])):
        n, q, re, pa = float(c["n"][k]), float(c["q"][k]), float(c["re"][k]), float(c["pa"][k])
        b_exact = float(profiles.sersic_b(n))
        b_fit = max(1.9992 * n - 0.3271, 1e-5)
        i0 = float(c["flux"][k, 0]) * math.exp(float(profiles.sersic_log_norm(1.0, re, n, q,
                                                                                b_exact)))
        r_l = math.sqrt(q) * re * (b_fit / b_exact) ** n   # same exp(-b (R/R_e)^(1/n)) profile
        e = (1 - q) / (1 + q)
        out.append(dict(amp=i0 * math.exp(-b_fit), R_sersic=r_l, n_sersic=n,
                        e1=e * math.cos(2 * pa), e2=e * math.sin(2 * pa),
                        center_x=float(c["center"][k, 0]), center_y=float(c["center"][k, 1])))
    return out


def detector_grid():
    return Grid.covering(FIELD[0], FIELD[1], PIXEL)


class Lenstronomy:
    """lenstronomy's ImageModel for the scene; construction is part of its cold time."""

    def __init__(self, n_clumps, supersampling, mask):
        from lenstronomy.Data.pixel_grid import PixelGrid
        from lenstronomy.Data.psf import PSF
        from lenstronomy.ImSim.image_model import ImageModel
        from lenstronomy.LensModel.lens_model import LensModel
        from lenstronomy.LightModel.light_model import LightModel
        g = detector_grid()
        pg = PixelGrid(nx=g.nx, ny=g.ny, transform_pix2angle=np.diag([PIXEL, PIXEL]),
                       ra_at_xy_0=g.x0_arcsec, dec_at_xy_0=g.y0_arcsec)
        psf = PSF(psf_type="PIXEL", kernel_point_source=moffat_kernel())
        numerics = dict(supersampling_factor=supersampling, supersampling_convolution=False)
        if mask is not None:
            numerics.update(compute_mode="adaptive", supersampled_indexes=mask)
        # a fresh LensModel per instance: INTERPOL caches its splines at the first call
        light = LightModel(["SERSIC_ELLIPSE"] * n_clumps,
                           profile_kwargs_list=[dict(smoothing=LT_SMOOTHING)] * n_clumps)
        self.model = ImageModel(pg, psf, lens_model_class=LensModel(["INTERPOL"]),
                                source_model_class=light, kwargs_numerics=numerics)
        axis, a1, a2 = sis_map()
        self.kw_lens = [dict(grid_interp_x=axis, grid_interp_y=axis, f_x=a1, f_y=a2)]

    def render(self, kw_source):
        return self.model.image(kwargs_lens=self.kw_lens, kwargs_source=kw_source,
                                unconvolved=False)


def our_model(src, acc, lens=None):
    """This project's model of the scene; lens: the rasterised SIS map unless given."""
    if lens is None:
        axis, a1, a2 = sis_map()
        lens = DeflectionGrid(jnp.asarray(a1), jnp.asarray(a2), jnp.asarray([axis[0], axis[0]]),
                              MAP_PIXEL)
    band = Band("b", PIXEL, EXPTIME, SKY, psf=moffat_kernel(), psf_pixel_arcsec=PIXEL)
    return build_model(src, [band], lens=lens, field_arcsec=FIELD, lens_pixel_arcsec=LENS_PIXEL,
                       source_pixel_arcsec=SOURCE_PIXEL, accuracy=acc)


def traced_mask(model):
    """Detector pixels holding at least one traced lens-plane pixel (for lenstronomy's adaptive mode)."""
    g = detector_grid()
    hr = model.hr_grid
    rows = np.asarray(model.traced_rows)
    cols = np.asarray(model.traced_cols)
    x = hr.x_centers()[cols]
    y = hr.y_centers()[rows]
    i = np.clip(np.floor((x - (g.x0_arcsec - PIXEL / 2)) / PIXEL).astype(int), 0, g.nx - 1)
    j = np.clip(np.floor((y - (g.y0_arcsec - PIXEL / 2)) / PIXEL).astype(int), 0, g.ny - 1)
    mask = np.zeros(g.shape, bool)
    mask[j, i] = True
    return mask


def time_ours(c, acc, repeats=3, lens=None):
    src = our_source(c)
    t = time.perf_counter()
    model = our_model(src, acc, lens)
    img = C.block(RENDER(model, src))[0]
    cold = time.perf_counter() - t
    warm = C.warm_time(RENDER, model, src, repeats=repeats, min_total=0.0)
    return np.asarray(img), cold, warm, model


def time_lenstronomy(c, supersampling, mask, repeats=2):
    kw = lenstronomy_kwargs(c)
    t = time.perf_counter()
    lm = Lenstronomy(len(kw), supersampling, mask)
    img = lm.render(kw)
    cold = time.perf_counter() - t
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        lm.render(kw)
        times.append(time.perf_counter() - t)
    return np.asarray(img), cold, float(np.median(times)) if times else None


def residual(a, b):
    sigma = math.sqrt(SKY * EXPTIME) / EXPTIME
    d = a - b
    return dict(max_abs_over_peak=float(np.max(np.abs(d)) / np.max(np.abs(b))),
                max_abs_over_sigma=float(np.max(np.abs(d)) / sigma),
                flux_rel=float(d.sum() / b.sum()), flux_ours=float(a.sum()),
                flux_lenstronomy=float(b.sum()))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--counts", default="10,30,100,300,1000")
    ap.add_argument("--quick", action="store_true", help="counts 10,30,300")
    ap.add_argument("--no-check", action="store_true",
                    help="timing rows only (no residual check, no error table)")
    ap.add_argument("--tag", default="", help="suffix of the result files (e.g. _gpu)")
    ap.add_argument("--matched-ss", type=int, default=144,
                    help="lenstronomy supersampling of the matched-accuracy column with --no-check")
    ap.add_argument("--append", action="store_true",
                    help="add these counts' rows to the existing result file, keeping its "
                         "error table and matched supersampling (one process per count: "
                         "XLA's CPU JIT can run out of code memory after many large models)")
    args = ap.parse_args(argv)
    counts = [10, 30, 300] if args.quick else [int(v) for v in args.counts.split(",")]
    try:
        import lenstronomy
    except ImportError:
        print("lenstronomy is not installed (pip install lenstronomy): skipped")
        return None
    meta = dict(machine=C.machine(), lenstronomy=lenstronomy.__version__, pixel_arcsec=PIXEL,
                lens_pixel_arcsec=LENS_PIXEL, source_pixel_arcsec=SOURCE_PIXEL, field=FIELD,
                deflection=f"SIS theta_E={THETA_E} rasterised at {MAP_PIXEL}\"",
                psf="Moffat 21x21 FWHM 2.5 px beta 2.5 at detector sampling")

    errors, rows = {}, []
    previous = C.RESULTS / f"lenstronomy{args.tag}.json"
    if args.append and previous.exists():
        old = json.loads(previous.read_text())
        errors = old["meta"].get("errors_30_clumps", {})
        for key in ("check_30_clumps", "errors_30_clumps"):
            if key in old["meta"]:
                meta[key] = old["meta"][key]
        rows = [r for r in old["rows"] if r["clumps"] not in counts]
        ss_match = old["meta"]["lt_supersampling_matched"]
    else:
        if not args.no_check:
            errors = check_and_errors(meta)
        ss_match = matched_supersampling(errors) if errors else args.matched_ss
    meta["lt_supersampling_matched"] = ss_match
    for n in counts:
        rows.append(time_row(n, ss_match))
        print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in rows[-1].items()},
              flush=True)
        meta["peak_rss_mb"] = C.peak_rss_mb()
        rows.sort(key=lambda r: r["clumps"])
        write_results(rows, meta, errors, args.tag)     # after every row: a cut-off run keeps them
    return rows, meta


def check_and_errors(meta):
    """Residual of the two codes with the same rays, and every setting's error (30 clumps)."""
    # ---- check: the same rays, the same profiles
    c = make_clumps(30)
    acc_check = Accuracy(lens_subsampling=1, source_mode="analytic", psf_oversampling=1)
    ours, _, _, model = time_ours(c, acc_check, repeats=1)
    mask = traced_mask(model)
    theirs_full, _, _ = time_lenstronomy(c, 12, None, repeats=0)
    theirs_ad, _, _ = time_lenstronomy(c, 12, mask, repeats=0)
    meta["check_30_clumps"] = dict(
        full_field=residual(ours, theirs_full), adaptive=residual(ours, theirs_ad),
        masked_pixels=int(mask.sum()), pixels=int(mask.size))
    print("check:", meta["check_30_clumps"], flush=True)

    # ---- accuracy of each setting against a converged reference (30 clumps): lenstronomy
    # point samples every 0.1 mas (its 216 vs 288 difference given as its own convergence)
    ref, _, _ = time_lenstronomy(c, REF_SUPERSAMPLING, mask, repeats=0)
    check, _, _ = time_lenstronomy(c, REF_CHECK_SUPERSAMPLING, mask, repeats=0)
    errors = {f"reference: lenstronomy ss={REF_CHECK_SUPERSAMPLING} vs {REF_SUPERSAMPLING}":
              residual(check, ref)}
    for name, acc in OURS.items():
        errors[f"ours {name}"] = residual(time_ours(c, acc, repeats=1)[0], ref)
    for ss in LT_SUPERSAMPLING:
        img = check if ss == REF_CHECK_SUPERSAMPLING else time_lenstronomy(c, ss, mask,
                                                                           repeats=0)[0]
        errors[f"lenstronomy ss={ss}"] = residual(img, ref)
    meta["errors_30_clumps"] = errors
    for k, v in errors.items():
        print(f"error {k}: {v}", flush=True)
    return errors


def matched_supersampling(errors):
    """The smallest lenstronomy supersampling whose max |Δ|/σ is no larger than hybrid's."""
    target = errors["ours hybrid"]["max_abs_over_sigma"]
    for ss in LT_SUPERSAMPLING:
        if errors[f"lenstronomy ss={ss}"]["max_abs_over_sigma"] <= target:
            return ss
    return LT_SUPERSAMPLING[-1]


def time_row(n, ss_match):
    """Cold and warm seconds of every setting of both codes for n clumps, and the ratios."""
    c = make_clumps(n)
    row = dict(clumps=n, lt_ss_matched=ss_match)
    model = None
    for name, acc in OURS.items():
        _, row[f"ours_{name}_cold_s"], row[f"ours_{name}_warm_s"], m = time_ours(c, acc)
        model = model or m
    mask = traced_mask(model)
    row["masked_pixels"] = int(mask.sum())
    for ss in sorted({12, 36, ss_match}):
        _, row[f"lt_ss{ss}_cold_s"], row[f"lt_ss{ss}_warm_s"] = time_lenstronomy(
            c, ss, mask, repeats=1 if ss > 12 else 2)
    row["lt_matched_warm_s"] = row[f"lt_ss{ss_match}_warm_s"]
    row["lt_matched_cold_s"] = row[f"lt_ss{ss_match}_cold_s"]
    row["ratio_matched_rays"] = row["lt_ss12_warm_s"] / min(row["ours_sub1_analytic_warm_s"],
                                                             row["ours_sub1_grid_warm_s"])
    row["ratio_ss36_default"] = row["lt_ss36_warm_s"] / row["ours_default_warm_s"]
    row["ratio_ss36_hybrid"] = row["lt_ss36_warm_s"] / row["ours_hybrid_warm_s"]
    row["ratio_matched_accuracy"] = row["lt_matched_warm_s"] / row["ours_hybrid_warm_s"]
    return row


def write_results(rows, meta, errors, tag):
    C.write_json("lenstronomy" + tag, {"meta": meta, "rows": rows})
    cols = [("clumps", "N clumps"), ("ours_sub1_analytic_warm_s", "ours sub=1 analytic"),
            ("ours_sub1_grid_warm_s", "ours sub=1 grid"), ("lt_ss12_warm_s", "lenstronomy ss=12"),
            ("ratio_matched_rays", "ratio (matched rays)"),
            ("ours_default_warm_s", "ours grid (default rays)"),
            ("ours_hybrid_warm_s", "ours hybrid"), ("lt_ss36_warm_s", "lenstronomy ss=36"),
            ("ratio_ss36_hybrid", "ratio ss=36 / hybrid"),
            ("lt_ss_matched", "lenstronomy ss matched"),
            ("lt_matched_warm_s", "lenstronomy matched"),
            ("ratio_matched_accuracy", "ratio matched accuracy / hybrid"),
            ("ours_hybrid_cold_s", "ours hybrid cold"),
            ("lt_matched_cold_s", "lenstronomy matched cold")]
    err_rows = [dict(setting=k, **v) for k, v in errors.items()]
    err_cols = [("setting", "setting (30 clumps)"), ("max_abs_over_sigma", "max |Δ|/σ"),
                ("max_abs_over_peak", "max |Δ|/peak"), ("flux_rel", "total flux error")]
    md = ["# Speed against lenstronomy", "", "Generated by `benchmarks/bench_lenstronomy.py` "
          "(warm seconds per render; ratio = lenstronomy / this project, measured in one run).",
          f"Machine: {meta['machine']}", ""]
    if errors:
        md += ["Check (30 clumps, the same rays): " + str(meta["check_30_clumps"]), "",
               "Error against the converged reference (lenstronomy point samples every "
               f"0.1 mas, supersampling {REF_SUPERSAMPLING}); matched accuracy: lenstronomy "
               f"supersampling {meta.get('lt_supersampling_matched')}, the smallest of "
               f"{LT_SUPERSAMPLING} with max |Δ|/σ no larger than hybrid's:", "",
               C.markdown_table(err_rows, err_cols), ""]
    md += [C.markdown_table(rows, cols), ""]
    C.write_text(f"lenstronomy{tag}.md", "\n".join(md))


# the settings timed: PSF at detector sampling in all (as lenstronomy's)
OURS = {
    "sub1_analytic": Accuracy(lens_subsampling=1, source_mode="analytic", psf_oversampling=1),
    "sub1_grid": Accuracy(lens_subsampling=1, source_mode="grid", psf_oversampling=1),
    "default": Accuracy(source_mode="grid", psf_oversampling=1),
    "hybrid": Accuracy(source_mode="hybrid", psf_oversampling=1),
}
LT_SUPERSAMPLING = (12, 36, 72, 108, 144, 216)
REF_SUPERSAMPLING, REF_CHECK_SUPERSAMPLING = 288, 216
LT_SMOOTHING = 1e-9      # arcsec: lenstronomy's Sérsic radius floor (its default 1e-4 loses light)


if __name__ == "__main__":
    main()
