"""Recovery of clumps by `clumpylen fit` from the images alone (issue 18).

For each seed: a catalogue of clumps (random positions around the host, magnitudes
spanning S/N ≈ 3–100, R_e 5–30 mas, q 0.5–1) and a scene (a Sérsic host by magnitude,
one NIRCam F200W band with a Gaussian PSF file, or `--psf diffraction` the built-in one) are
written; `clumpylen simulate` makes
the image; `clumpylen fit SCENE --image F200W=... --out DIR` fits it with no catalogue
(the scene's clumps are never read by fit). Scenes: "unlensed"; "sis" (the same source
behind an SIS of θ_E = 1" near its caustic: an arc); "arc" (cosmic-archipelago's z = 6.145
source plane behind its MACS0416-like cluster, every clump inside a fold caustic: two
mirror images of each across the critical curve, |μ| ≈ 5–18 per image, 78 × 113 pixels).

Truth matching: each true clump (brightest first) takes the nearest unmatched fitted
clump within `MATCH_PIX` detector pixels in the image plane: the source-plane offset mapped
by ∂θ/∂β at the true clump's most magnified image (`_image_maps`; a lens stretches one
direction only, so one isotropic source-plane radius cannot stand for a pixel distance).
The earlier rule (|Δβ| √|μ| within MATCH_PIX pixels) is reported beside it.
Reported: recovered fraction vs the Fisher S/N of the true clump's flux
(`detect.clump_detectability`, marginalised over every clump's flux, size and position)
and vs flux and R_e; false clumps per scene (all, and with fitted S/N > 10); pulls
(fit − true)/σ of flux, R_e and β; blends (fitted clumps with several true ones within
twice the match distance: flux bias). Beside the fit's recovered fraction, the
detection-only completeness of the same clumps (`--completeness N`, default 8:
`inference.completeness.completeness_grids`, each true clump's flux and R_e injected round
at N random positions within the catalogue's spread of the host's centre, into the noisy
image of the host alone, found by photutils segmentation, no fit): what a detection
catalogue would find of the clumps the fit recovers, plain and with photutils' deblending
(the same injections scored both ways);
"in a segment" counts a clump inside any segment, the host's included (found but blended:
no position or flux of its own). The outside check: at S/N > 10, ≥ 90 % recovered,
|pull| < 3 for flux and size in ≥ 90 % of them, ≤ 1 false clump per scene with S/N > 10.

Run: .venv/bin/python benchmarks/bench_recovery.py [--seeds 4] [--scenes unlensed,sis,arc]
Writes benchmarks/results/recovery.{json,md} (`--name`). With `--keep DIR`, a seed whose fit
is already in DIR (its fit_s.json written) is evaluated again without simulating or fitting.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table

import clumpylen_jax

clumpylen_jax.enable_float64()  # float64: the caller's choice
from clumpylen_jax.cli import main as cli

from _common import RESULTS, machine

PIX = 0.031
MATCH_PIX = 1.5
N_CLUMPS = 6
SNR_BINS = [0, 5, 10, 20, 1e9]
RE_BINS_MAS = [5, 10, 20, 30]   # the catalogue's R_e range, 5–30 mas

SCENE = """
[scene]
name = "recovery-{kind}-{seed}"
seed = {seed}
z_source = {z_source}

[source]
center_arcsec = {center}

[source.bulge]
magnitudes = {{ F200W = {host_mag} }}
re_arcsec = {host_re}
n = 1.0
q = 0.7
pa_rad = 0.5

[source.clumps]
catalog = "clumps.ecsv"
{lens}
[render]
source_pixel_arcsec = 0.001
lens_pixel_arcsec = 0.01
field_arcsec = {{ x = [{x0}, {x1}], y = [{y0}, {y1}] }}
accuracy = "fast"

[[bands]]
instrument = "JWST/NIRCam"
filter = "F200W"
exptime_s = 2000.0
sky_counts_per_s = 0.16
{psf_lines}

[output]
noise = true
unlensed = false
"""

LENS = """
[lens]
z_lens = 0.5
components = [ { kind = "sis", theta_e_arcsec = 1.0, center_arcsec = [0.0, 0.0] } ]
"""

# cosmic-archipelago's lens (the built-in MACS0416-like cluster, its z_lens and centre)
CLUSTER = """
[lens]
z_lens = 0.396
center_radec_deg = [64.038142, -24.067472]
model = "macs0416-like"
"""

# The arc: cosmic-archipelago's z = 6.145 source plane behind its cluster. Its source
# centre (β = −13.7166, 3.6177) lies 8 mas inside a fold caustic of the lens
# (`lensing.derived.caustics` of `builtin_lens("macs0416-like", 6.145)` on a 0.01" grid):
# nearest caustic point β = (−13.7230, 3.6231), inward normal (0.2414, −0.9704), critical
# point θ = (−35.635, 19.112). Clumps are placed inside that fold (local straight-line
# caustic, 3 mas margin), 3–77 mas from it: each is imaged twice, on either side of the
# critical curve, at |μ| ≈ 5–18 per image and 0.5–1.9" apart (`find_images`), the two
# mirror images of the paper's arc. The field (2.4" × 3.5", 78 × 113 pixels, 0.86 of the SIS
# field's count) holds both images of every clump; the third image (θ ≈ −36.9, 23.4) is
# outside it, as in cosmic-archipelago's field.
FOLD = ((-13.7230, 3.6231), (0.2414, -0.9704))

KINDS = {
    "unlensed": dict(center=[0.0, 0.0], host_mag=22.5, host_re=0.3, spread=0.35,
                     field=((-0.9, 0.9), (-0.9, 0.9)), mags=(24.5, 28.5), lens="", z_source=2.0),
    "sis": dict(center=[0.08, 0.03], host_mag=25.0, host_re=0.08, spread=0.08,
                field=((-1.6, 1.6), (-1.6, 1.6)), mags=(27.0, 31.0), lens=LENS, z_source=2.0),
    "arc": dict(center=[-13.7145, 3.5891], host_mag=26.5, host_re=0.08, spread=0.035,
                field=((-36.8, -34.4), (17.4, 20.9)), mags=(25.5, 29.5), lens=CLUSTER,
                z_source=6.145, fold=FOLD),
}


def _psf(path):
    r = np.arange(-7, 8)
    k = np.exp(-0.5 * (r[:, None] ** 2 + r[None, :] ** 2) / 1.0**2)
    fits.PrimaryHDU(k / k.sum()).writeto(path, overwrite=True)


def _catalog(kind, seed, path):
    cfg = KINDS[kind]
    rng = np.random.default_rng(1000 + seed)
    pos = []
    while len(pos) < N_CLUMPS:
        p = np.asarray(cfg["center"]) + rng.uniform(-cfg["spread"], cfg["spread"], 2)
        if "fold" in cfg and np.dot(p - cfg["fold"][0], cfg["fold"][1]) < 0.003:
            continue   # outside the fold: no image in the arc's field
        if all(np.hypot(*(p - q)) > 0.4 * cfg["spread"] for q in pos):
            pos.append(p)
    pos = np.array(pos)
    t = Table({"beta1_arcsec": pos[:, 0], "beta2_arcsec": pos[:, 1],
               "re_arcsec": rng.uniform(0.005, 0.03, N_CLUMPS), "q": rng.uniform(0.5, 1.0, N_CLUMPS),
               "pa_rad": rng.uniform(0, np.pi, N_CLUMPS),
               "mag_F200W": rng.uniform(*cfg["mags"], N_CLUMPS)})
    t.write(path, format="ascii.ecsv", overwrite=True)


def _truth(scene_path):
    """Fisher S/N of each true clump's flux (truth model: evaluation only), and the prepared
    scene (its lens and field)."""
    from clumpylen_jax import scene as sc
    from clumpylen_jax.inference.detect import clump_detectability
    from clumpylen_jax.pipeline import prepare
    prep = prepare(sc.load_scene(scene_path))
    return np.asarray(clump_detectability(prep.model, prep.source)["snr_flux_F200W"]), prep


def _image_maps(prep, true):
    """∂θ/∂β (2 × 2) per true clump at its most magnified image in the field: the map of a
    source-plane offset to the image-plane offset that matching measures (identity unlensed).

    A lens magnifies along one direction: the fold of the arc kind by 1/|λ_r| ≈ 7–15 along the
    arc, and compresses by 1/|λ_t| ≈ 0.7 across it (the SIS: 1/λ_t ≈ 12 and 1). A source-plane
    radius of MATCH_PIX pixels / √|μ| is then 3–4 pixels along the arc and 0.3 across it."""
    from clumpylen_jax.lensing.derived import deflection_jacobian
    from clumpylen_jax.lensing.images import find_images

    if prep.lens is None:
        return np.broadcast_to(np.eye(2), (len(true), 2, 2))
    field = tuple(tuple(float(v) for v in r) for r in prep.field_arcsec)
    out = []
    for b1, b2 in zip(true["beta1_arcsec"], true["beta2_arcsec"]):
        im = find_images(prep.lens, float(b1), float(b2), field=field, pixel_arcsec=PIX / 2)
        valid = np.asarray(im.valid)
        if not valid.any():   # no image in the field: nothing to match it to
            out.append(np.full((2, 2), np.inf))
            continue
        k = int(np.argmax(np.where(valid, np.abs(np.asarray(im.magnification)), -1.0)))
        a = np.reshape([float(x) for x in deflection_jacobian(prep.lens, im.theta1[k], im.theta2[k])], (2, 2))
        out.append(np.linalg.inv(np.eye(2) - a))
    return np.array(out)


def _distances(true, fit, maps):
    """(n_true, n_fit) image-plane distances in detector pixels, |∂θ/∂β · (β_fit − β_true)|,
    and the isotropic source-plane ones |β_fit − β_true| · √max(|μ|, 1) (the rule of the runs
    before 2026-11-26, kept for comparison)."""
    db = np.stack([np.asarray(fit["beta1_arcsec"])[None, :] - np.asarray(true["beta1_arcsec"])[:, None],
                   np.asarray(fit["beta2_arcsec"])[None, :] - np.asarray(true["beta2_arcsec"])[:, None]], -1)
    with np.errstate(invalid="ignore"):   # inf map × 0 offset: no image, never matched
        img = np.nan_to_num(np.hypot(*np.einsum("iab,ijb->aij", maps, db)), nan=np.inf) / PIX
    mu = np.abs(np.asarray(true["magnification"])) if "magnification" in true.colnames else np.ones(len(true))
    iso = np.hypot(db[..., 0], db[..., 1]) * np.sqrt(np.maximum(mu, 1.0))[:, None] / PIX
    return img, iso


def _match(true, dist):
    """Index of the matched fitted clump per true clump (−1: none), brightest first: the
    nearest unmatched one within MATCH_PIX (dist: (n_true, n_fit) in detector pixels)."""
    out = np.full(len(true), -1)
    used = set()
    for i in np.argsort(-np.asarray(true["flux"])):
        for j in np.argsort(dist[i]):
            if dist[i, j] > MATCH_PIX:
                break
            if j not in used:
                out[i] = j
                used.add(int(j))
                break
    return out


def _simulate_and_fit(kind, seed, d: Path, psf: str):
    """Scene, image and fit in d; the fit's wall time, load and peak RSS in d/fit_s.json.
    psf: "gaussian" (σ 1 pixel, a file) or "diffraction" (the built-in NIRCam PSF, wings
    and all; the fit uses the same)."""
    cfg = KINDS[kind]
    d.mkdir(parents=True)
    if psf == "gaussian":
        _psf(d / "psf.fits")
        psf_lines = f'psf = "psf.fits"\npsf_pixel_arcsec = {PIX}'
    else:
        psf_lines = 'psf = "diffraction"'
    _catalog(kind, seed, d / "clumps.ecsv")
    (x0, x1), (y0, y1) = cfg["field"]
    (d / "scene.toml").write_text(SCENE.format(kind=kind, seed=seed, center=cfg["center"],
                                               z_source=cfg["z_source"], host_mag=cfg["host_mag"],
                                               host_re=cfg["host_re"], lens=cfg["lens"],
                                               x0=x0, x1=x1, y0=y0, y1=y1,
                                               psf_lines=psf_lines))
    assert cli(["simulate", str(d / "scene.toml"), "--out", str(d / "run"), "-q"]) == 0
    t0 = time.perf_counter()
    assert cli(["fit", str(d / "scene.toml"), "--image", f"F200W={d}/run/bands/F200W.fits",
                "--out", str(d / "fit"), "-q"]) == 0
    # the process's peak so far (simulate, fit and the earlier seeds' truth S/N run in it)
    (d / "fit_s.json").write_text(json.dumps({
        "fit_s": time.perf_counter() - t0, "load": os.getloadavg()[0],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))


def _detection_completeness(prep, true, kind, seed, n_trials):
    """Detection-only completeness of each true clump's flux and R_e (module doc): the
    diagonal of `completeness_grids` over the clumps' fluxes × R_e, the same injections
    scored plain and with photutils' deblending (`completeness.detect`); round clumps of the
    scene's Sérsic index (the catalogue's q, 0.5–1, is not injected). Returns (plain
    completeness, plain in-segment fraction, deblended completeness)."""
    import jax

    from clumpylen_jax.inference.completeness import completeness_grids
    from clumpylen_jax.source import Source
    plain, deblended = completeness_grids(
        Source(bulge=prep.source.bulge, disk=prep.source.disk), prep.bands,
        np.asarray(true["flux"], float), np.asarray(true["re_arcsec"], float),
        jax.random.key(5000 + seed), lens=prep.lens, field_arcsec=prep.field_arcsec,
        n_trials=n_trials, region_arcsec=KINDS[kind]["spread"],
        clump_n=float(prep.source.clumps.n[0]), accuracy=prep.accuracy, fisher=False,
        deblend=(False, True))
    return (np.diag(plain.completeness), np.diag(plain.detected_fraction),
            np.diag(deblended.completeness))


def _truth_against_fit(d: Path, true, fit):
    """χ² of the noiseless truth and of the fitted model against the image (the simulation's
    VARIANCE, which the fit's σ equals), and the BIC difference truth − fit, counting 4
    parameters per clump (flux, β, R_e) and 2 more per elliptical one (truth: q < 1; fit: q
    fitted). ΔBIC < 0: the truth is the better model by the fit's own criterion, so a miss is
    the search's; > 0: the data do not ask for the truth's extra clumps (the criterion's).
    Every pixel counts (these mocks have no mask); the hosts' parameters are left out of
    both counts (the truth's one Sérsic against the fit's one Sérsic)."""
    with fits.open(d / "run/bands/F200W.fits") as h:
        data, truth, var = (np.asarray(h[k].data, float) for k in (0, "NOISELESS", "VARIANCE"))
    model = np.asarray(fits.getdata(d / "fit/residuals_F200W.fits", "MODEL"), float)
    n = data.size
    chi2_t, chi2_f = (float(np.sum((data - m) ** 2 / var)) for m in (truth, model))
    k_t = int(np.sum(4 + 2 * (np.asarray(true["q"]) < 1)))
    k_f = int(np.sum(4 + 2 * np.isfinite(np.asarray(fit["q_err"], float)))) if "q_err" in fit.colnames \
        else 4 * len(fit)
    return {"chi2_truth": chi2_t, "chi2_fit": chi2_f, "n_pix": n, "k_truth": k_t, "k_fit": k_f,
            "delta_bic_truth_fit": chi2_t - chi2_f + (k_t - k_f) * float(np.log(n))}


def run_one(kind, seed, work: Path, psf: str = "gaussian", completeness_trials: int = 8):
    d = work / f"{kind}-{seed}"
    if not (d / "fit_s.json").exists():   # a kept seed (--keep) is evaluated again, not refitted
        _simulate_and_fit(kind, seed, d, psf)
    timing = json.loads((d / "fit_s.json").read_text())
    zp = fits.getheader(d / "run/bands/F200W.fits")["ZP_AB"]
    true = Table.read(d / "run/catalog.ecsv")
    true["flux"] = 10 ** (-0.4 * (np.asarray(true["mag_F200W"]) - zp))
    snr, prep = _truth(d / "scene.toml")
    true["snr"] = snr
    fit = Table.read(d / "fit/fit.ecsv")
    dist, dist_iso = _distances(true, fit, _image_maps(prep, true))
    m = _match(true, dist)
    m_iso = _match(true, dist_iso)
    none = np.full(len(true), np.nan)
    det, det_any, det_deb = (_detection_completeness(prep, true, kind, seed, completeness_trials)
                             if completeness_trials else (none, none, none))
    rows = []
    for i, j in enumerate(m):
        q = float(true["q"][i])
        r = {"snr": float(true["snr"][i]), "flux": float(true["flux"][i]),
             "re_arcsec": float(true["re_arcsec"][i]), "q": q, "recovered": bool(j >= 0),
             "recovered_iso": bool(m_iso[i] >= 0),
             "detection_completeness": float(det[i]), "detected_in_segment": float(det_any[i]),
             "detection_completeness_deblended": float(det_deb[i])}
        if j >= 0:
            f = fit[j]
            # a round fitted clump's R_e estimates the circularised R_e·√q of an elliptical
            # one; one made elliptical (merge and shape moves) has its own q: both pulls are
            # reported, the circularised one with the fit's √q on both R_e and its error
            qf = float(f["q"]) if "q" in fit.colnames else 1.0
            r.update(fit_flux=float(f["flux_F200W"]), fit_flux_err=float(f["flux_F200W_err"]),
                     fit_re_arcsec=float(f["re_arcsec"]), fit_re_err=float(f["re_arcsec_err"]),
                     offset_pix=float(dist[i, j]),
                     pull_flux=float((f["flux_F200W"] - r["flux"]) / f["flux_F200W_err"]),
                     pull_re=float((f["re_arcsec"] - r["re_arcsec"]) / f["re_arcsec_err"]),
                     pull_re_circ=float((f["re_arcsec"] * np.sqrt(qf) - r["re_arcsec"] * np.sqrt(q))
                                        / (f["re_arcsec_err"] * np.sqrt(qf))), fit_q=qf,
                     pull_beta1=float((f["beta1_arcsec"] - true["beta1_arcsec"][i]) / f["beta1_arcsec_err"]),
                     pull_beta2=float((f["beta2_arcsec"] - true["beta2_arcsec"][i]) / f["beta2_arcsec_err"]),
                     flag=int(f["flag"]))
        rows.append(r)
    unmatched = [j for j in range(len(fit)) if j not in set(m.tolist())]
    fit_snr = np.asarray(fit["flux_F200W"]) / np.asarray(fit["flux_F200W_err"])
    # a blend: a fitted clump with several true ones within twice the match distance
    near = dist < 2 * MATCH_PIX
    blends = [{"n_true": int(near[:, j].sum()),
               "flux_ratio": float(fit["flux_F200W"][j] / np.sum(true["flux"][near[:, j]]))}
              for j in range(len(fit)) if near[:, j].sum() > 1]
    return {"kind": kind, "seed": seed, "clumps": rows, "n_fit": len(fit), **timing,
            "false": len(unmatched), "false_snr10": int(np.sum(fit_snr[unmatched] > 10)) if unmatched else 0,
            "false_iso": int(len(fit) - np.sum(m_iso >= 0)), "blends": blends,
            **_truth_against_fit(d, true, fit)}


def summarise(results):
    clumps = [c for r in results for c in r["clumps"]]
    snr = np.array([c["snr"] for c in clumps])
    rec = np.array([c["recovered"] for c in clumps])
    det = np.array([c.get("detection_completeness", np.nan) for c in clumps], float)
    seg = np.array([c.get("detected_in_segment", np.nan) for c in clumps], float)
    deb = np.array([c.get("detection_completeness_deblended", np.nan) for c in clumps], float)
    out = {"bins": []}
    for lo, hi in zip(SNR_BINS[:-1], SNR_BINS[1:]):
        sel = (snr >= lo) & (snr < hi)
        d, g, e = (a[sel & np.isfinite(a)] for a in (det, seg, deb))
        out["bins"].append({"snr": [lo, hi], "n": int(sel.sum()),
                            "recovered": float(rec[sel].mean()) if sel.any() else None,
                            "detection_completeness": float(d.mean()) if d.size else None,
                            "detected_in_segment": float(g.mean()) if g.size else None,
                            "detection_completeness_deblended": float(e.mean()) if e.size
                            else None})
    # by size, at S/N > 10 (fainter ones are missed whatever their size)
    re_mas = np.array([1e3 * c["re_arcsec"] for c in clumps])
    out["re_bins"] = []
    for lo, hi in zip(RE_BINS_MAS[:-1], RE_BINS_MAS[1:]):
        sel = (re_mas >= lo) & (re_mas < hi) & (snr > 10)
        out["re_bins"].append({"re_mas": [lo, hi], "n": int(sel.sum()),
                               "recovered": float(rec[sel].mean()) if sel.any() else None})
    for key, a in (("detection_completeness", det), ("detection_completeness_deblended", deb)):
        a10 = a[(snr > 10) & np.isfinite(a)]
        out[f"snr_gt10_{key}"] = float(a10.mean()) if a10.size else None
    hi = [c for c in clumps if c["snr"] > 10 and c["recovered"]]
    for key in ("recovered", "recovered_iso"):
        out[f"snr_gt10_{key}"] = float(np.mean([c[key] for c in clumps if c["snr"] > 10])) \
            if any(c["snr"] > 10 for c in clumps) else None
    for p in ("flux", "re", "re_circ", "beta1", "beta2"):
        v = np.array([c[f"pull_{p}"] for c in hi if f"pull_{p}" in c])   # NaN counts as > 3
        out[f"pull_{p}_within3"] = float(np.mean(np.abs(v) < 3)) if v.size else None
        out[f"pull_{p}_median"] = float(np.median(v)) if v.size else None
    out["converged"] = float(np.mean([(c["flag"] & 1) == 0 for c in clumps if c["recovered"]])) \
        if any(c["recovered"] for c in clumps) else None
    out["false_per_scene"] = float(np.mean([r["false"] for r in results]))
    out["false_iso_per_scene"] = float(np.mean([r["false_iso"] for r in results]))
    out["false_snr10_per_scene"] = float(np.mean([r["false_snr10"] for r in results]))
    out["max_false_snr10"] = int(max(r["false_snr10"] for r in results))
    return out


def _fmt(v):
    return "" if v is None else f"{v:.2f}"


def _write(results, kinds, n_seeds, wall_s, name="recovery", psf="gaussian"):
    """recovery.{json,md} from the seeds done so far (rewritten after each seed)."""
    summary = {k: summarise([r for r in results if r["kind"] == k]) for k in kinds
               if any(r["kind"] == k for r in results)}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(
        {"machine": machine(), "psf": psf, "results": results, "summary": summary}, indent=2))
    done = {k: sum(r["kind"] == k for r in results) for k in kinds}
    lines = ["# bench_recovery: clumpylen simulate -> clumpylen fit, images only", "",
             f"{N_CLUMPS} clumps per scene; PSF {psf}; seeds done {done} of {n_seeds} each; "
             f"{machine()['date']}; {wall_s:.0f} s wall in all", "",
             "Per seed: fit wall time, 1-min load average when it ended (the machine "
             "is shared), the process's peak RSS so far, clumps found, false (unmatched) ones, "
             "recovered/true; χ² of the fit and of the noiseless truth, and ΔBIC truth − fit "
             "(< 0: the truth is better by the fit's criterion, a miss of the search; > 0: the "
             "data do not ask for the truth's clumps).", "",
             "| scene | seed | fit s | load | peak RSS GB | found | false (S/N>10) | recovered "
             "| χ² fit | χ² truth | ΔBIC |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['kind']} | {r['seed']} | {r['fit_s']:.0f} | {r['load']:.1f} | "
              f"{r.get('peak_rss_mb', float('nan')) / 1024:.1f} | {r['n_fit']} | "
              f"{r['false']} ({r['false_snr10']}) | {sum(c['recovered'] for c in r['clumps'])}/"
              f"{len(r['clumps'])} | {r.get('chi2_fit', float('nan')):.1f} | "
              f"{r.get('chi2_truth', float('nan')):.1f} | "
              f"{r.get('delta_bic_truth_fit', float('nan')):+.1f} |" for r in results]
    lines.append("")
    for k, s in summary.items():
        lines += [f"## {k}", "", "| Fisher S/N | clumps | recovered (fit) | detection-only "
                  "completeness | deblended | in a segment (blended too) |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {b['snr'][0]}-{b['snr'][1] if b['snr'][1] < 1e8 else 'inf'} | {b['n']} | "
                  f"{_fmt(b['recovered'])} | {_fmt(b.get('detection_completeness'))} | "
                  f"{_fmt(b.get('detection_completeness_deblended'))} | "
                  f"{_fmt(b.get('detected_in_segment'))} |" for b in s["bins"]]
        lines += ["", "| R_e mas (S/N > 10) | clumps | recovered |", "|---|---|---|"]
        lines += [f"| {b['re_mas'][0]}-{b['re_mas'][1]} | {b['n']} | {_fmt(b['recovered'])} |"
                  for b in s["re_bins"]]
        lines += ["", f"S/N > 10: recovered {_fmt(s['snr_gt10_recovered'])} (detection-only "
                  f"completeness {_fmt(s.get('snr_gt10_detection_completeness'))}, deblended "
                  f"{_fmt(s.get('snr_gt10_detection_completeness_deblended'))}; isotropic "
                  f"√|μ| rule: {_fmt(s['snr_gt10_recovered_iso'])}); |pull| < 3: flux "
                  f"{_fmt(s['pull_flux_within3'])}, R_e {_fmt(s['pull_re_within3'])} "
                  f"(circularised R_e√q: {_fmt(s['pull_re_circ_within3'])}), "
                  f"β1 {_fmt(s['pull_beta1_within3'])}, β2 {_fmt(s['pull_beta2_within3'])}; "
                  f"median pull flux {_fmt(s['pull_flux_median'])}, R_e {_fmt(s['pull_re_median'])} "
                  f"(R_e√q {_fmt(s['pull_re_circ_median'])}); converged (flag bit 1 clear) "
                  f"{_fmt(s['converged'])}; "
                  f"false clumps per scene {s['false_per_scene']:.2f} "
                  f"(S/N > 10: {s['false_snr10_per_scene']:.2f}, max {s['max_false_snr10']}; "
                  f"isotropic rule: {s['false_iso_per_scene']:.2f})", ""]
    (RESULTS / f"{name}.md").write_text("\n".join(lines) + "\n")
    return lines


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--scenes", default="sis,unlensed")
    ap.add_argument("--name", default="recovery", help="results/<name>.{json,md}")
    ap.add_argument("--keep", default=None, help="work folder kept (scenes, images, fits)")
    ap.add_argument("--psf", choices=("gaussian", "diffraction"), default="gaussian",
                    help="the band's PSF: a σ = 1 pixel Gaussian file, or the built-in NIRCam one")
    ap.add_argument("--completeness", type=int, default=8, metavar="N",
                    help="positions per clump of the detection-only completeness (0: none)")
    args = ap.parse_args()
    kinds = args.scenes.split(",")
    results = []
    t_all = time.perf_counter()
    with (contextlib.nullcontext(args.keep) if args.keep else tempfile.TemporaryDirectory()) as tmp:
        # seeds interleaved across scenes: a run cut short still has numbers for each
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            for kind in kinds:
                r = run_one(kind, seed, Path(tmp), args.psf, args.completeness)
                results.append(r)
                print(kind, seed, f"fit {r['fit_s']:.0f} s (load {r['load']:.1f}), found {r['n_fit']}, "
                      f"false {r['false']} (S/N>10: {r['false_snr10']}), recovered "
                      f"{sum(c['recovered'] for c in r['clumps'])}/{len(r['clumps'])}", flush=True)
                lines = _write(results, kinds, args.seeds, time.perf_counter() - t_all, args.name,
                               args.psf)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
