"""Pulls of `clumpylen fit` on mocks written as real products, clumps found without the truth
(issue 17: "on mocks written in the same real-product formats, fitted magnitudes, sizes and
masses agree with the truth within their uncertainties, pulls ~ N(0, 1) over many clumps").

Per seed and format, a z = 2 host (Sérsic n = 1) with N_CLUMPS n = 1 clumps (round, or with
--clump-q-min an axis ratio uniform in [Q, 1]; --clump-shape: the fit's clump_shape), whose band
fluxes come from the stellar-population model (`photometry.band_fluxes_ujy`, constant SFH: a
mass log-uniform in 10^6.8–10^8.2 M☉ and an age drawn as the simulator draws clump ages,
`population.sample_ages_myr`, which is the SED fit's default prior), is rendered by the fit's
own model on the data's grids and written as:
- "jwst": NIRCam F150W (0.03″, 64²) and F444W (0.06″, 32²) i2d-like cutouts in MJy/sr
  (PIXAR_SR) with ERR, a celestial WCS rotated by a random angle, Gaussian noise;
- "hst": ACS F606W and F814W (0.05″, 48², one WCS rotated by a random angle) in e⁻/s with
  PHOTFLAM/PHOTPLAM, EXPTIME and a WHT (1/σ²) map, Gaussian background noise;
- "jwst_turned": "jwst" with F444W's WCS turned by another 20–70° (drawn per seed): the fit
  draws F444W on frame-aligned pixels turned onto the data's. Its truth there is drawn by
  the fit's model on F444W's own aligned frame (positions through the WCSs, PAs turned),
  not by the turned path under test. The same seed gives the same truth and noise values
  as "jwst".
Then `clumpylen fit scene.toml --out DIR` runs with `clumps = "auto"`: the clumps are found,
seeded and counted from the images; nothing of the truth reaches the fit (the scene gives
files, filters, z_source and the clumps' Sérsic index). Each true clump is matched to the
nearest fitted clump within MATCH_PIX finest pixels; pulls (fit − true)/σ of the AB
magnitude per band, R_e, RA, Dec and the stellar mass.

What it does not test: model mismatch (the mock is drawn by the fitted model family:
the pulls measure the fitter and its errors), source Poisson noise (drizzled WHT maps
carry the background's only), PSF mismatch.

    .venv/bin/python benchmarks/bench_observation_pulls.py [--seeds 4] [--formats jwst,hst]
        [--psf-oversampling 1] [--truth-oversampling N] [--name observation_pulls] [--keep DIR]
        [--clump-q-min 1.0] [--clump-shape round|elliptical]

--psf-oversampling sets the fit's `[fit] psf_oversampling`; --truth-oversampling the mock's
drawing (default: the same, so that the pulls measure the fitter; larger, e.g. 7, so that they
also measure the fit's model error against a near-converged drawing). --psf-sampling N writes
the PSF images N× finer than the pixels (default 1: an optical PSF at the pixel scale, which
a finer sub-grid reads as piecewise constant, i.e. wider than the Gaussian by a pixel box:
compare oversamplings with N ≥ the larger one).

Writes benchmarks/results/<name>.{json,md}. With --keep DIR, a mock whose fit is already in DIR
is evaluated again without fitting (the mocks are the same for the same seed).
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table

import clumpylen_jax

clumpylen_jax.enable_float64()  # float64: the caller's choice
import jax.numpy as jnp  # noqa: E402

from clumpylen_jax.cli import main as cli  # noqa: E402
from clumpylen_jax.observations import FitOptions, write_cutout  # noqa: E402
from clumpylen_jax.observations.fit import make_model_factory  # noqa: E402
from clumpylen_jax.observations.frame import BandFrame, celestial_wcs, fit_frame  # noqa: E402
from clumpylen_jax.observations.units import zeropoint_mjy_sr, zeropoint_photflam  # noqa: E402
from clumpylen_jax.cosmology import make_cosmology  # noqa: E402
from clumpylen_jax.inference.auto import FLAGS  # noqa: E402
from clumpylen_jax.photometry import AB_ZERO_UJY, band_fluxes_ujy  # noqa: E402
from clumpylen_jax.psf import load_psf_fits  # noqa: E402
from clumpylen_jax.population import sample_ages_myr  # noqa: E402
from clumpylen_jax.source import Clumps, Sersic, Source  # noqa: E402

from _common import machine, write_json, write_text  # noqa: E402

RA0, DEC0 = 64.038142, -24.067472
Z = 2.0
N_CLUMPS = 5
MATCH_PIX = 2.0
PSF_SIGMA_PIX = 1.3
# ACS/WFC PHOTFLAM (erg s⁻¹ cm⁻² Å⁻¹ per e⁻/s) and PHOTPLAM (Å), the STScI zero-point
# tables' values for recent epochs, rounded: any positive pair exercises the same path
ACS = {"F606W": (7.86e-20, 5921.9), "F814W": (7.07e-20, 8045.5)}
FORMATS = {
    # (filter, instrument, pixel arcsec, shape)
    "jwst": [("F150W", "JWST/NIRCam", 0.03, (64, 64)), ("F444W", "JWST/NIRCam", 0.06, (32, 32))],
    "hst": [("F606W", "HST/ACS", 0.05, (48, 48)), ("F814W", "HST/ACS", 0.05, (48, 48))],
}
FORMATS["jwst_turned"] = FORMATS["jwst"]
TURN_DEG = (20.0, 70.0)    # "jwst_turned": F444W's WCS turned by this much more than F150W's
TARGET_SNR = 25.0      # S/N of a 10^7.5 M☉, 100 Myr clump in each band (sets σ)
HST_EXPTIME_S = 2000.0


def _header(shape, pixel_arcsec, rot_deg):
    ny, nx = shape
    c, s = math.cos(math.radians(rot_deg)), math.sin(math.radians(rot_deg))
    p = pixel_arcsec / 3600.0
    h = fits.Header()
    h.update(CTYPE1="RA---TAN", CTYPE2="DEC--TAN", CRVAL1=RA0, CRVAL2=DEC0,
             CRPIX1=(nx + 1) / 2.0, CRPIX2=(ny + 1) / 2.0,
             CD1_1=-p * c, CD1_2=p * s, CD2_1=p * s, CD2_2=p * c)
    return h


def _psf_file(path, pixel_arcsec, size=15, sampling=1):
    """A Gaussian PSF of σ PSF_SIGMA_PIX detector pixels over `size` of them, sampled
    `sampling` times finer than the detector."""
    n = size * sampling
    y, x = (np.mgrid[:n, :n] - (n - 1) / 2) / sampling
    h = fits.Header()
    h["PIXSCALE"] = pixel_arcsec / sampling
    fits.PrimaryHDU(np.exp(-(x**2 + y**2) / (2 * PSF_SIGMA_PIX**2)), h).writeto(path, overwrite=True)
    return str(path)


class _Ob:   # what make_model_factory reads of an observation
    def __init__(self, name, psf):
        self.name, self.psf = name, psf


def _truth(rng, bands, frame):
    """Host and clumps (fit-frame arcsec; fluxes in each band's data units), masses, ages."""
    filters = [f"{inst}/{name}" for name, inst, _, _ in bands]
    pix = min(b[2] for b in bands)
    mass = 10 ** rng.uniform(6.8, 8.2, N_CLUMPS)
    age = sample_ages_myr(rng, N_CLUMPS)   # the simulator's law, the SED fit's default prior
    cosmo = make_cosmology(70.0, 0.3)     # the scene's default, which the fit's masses use
    ujy = np.asarray(band_fluxes_ujy(mass, age, filters=filters, z=Z, cosmology=cosmo), float)
    ref = np.asarray(band_fluxes_ujy(10**7.5, 100.0, filters=filters, z=Z, cosmology=cosmo), float)
    pos = []
    while len(pos) < N_CLUMPS:
        p = rng.uniform(-0.45, 0.45, 2)
        if all(np.hypot(*(p - q)) > 5 * pix for q in pos):
            pos.append(p)
    f = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
    return dict(mass=mass, age=age, ujy=ujy, ref_ujy=ref, pos=np.array(pos),
                re=rng.uniform(0.01, 0.06, N_CLUMPS), host_re=rng.uniform(0.25, 0.4),
                host_q=rng.uniform(0.4, 0.9), host_pa=rng.uniform(0, np.pi), f=f)


def _in_own_frame(source: Source, frame, band_frame, k: int) -> tuple:
    """(band k's own aligned fit frame, `source`'s band-k light placed in it): positions
    through the two WCSs, position angles turned by the frames' relative angle."""
    own = fit_frame([band_frame], ["own"])
    move = lambda phi: own.phi_of_radec(*frame.radec(np.atleast_2d(np.asarray(phi, float))))  # noqa: E731
    d = move([[0.0, 0.0], [1.0, 0.0]])
    turn = math.atan2(d[1, 1] - d[0, 1], d[1, 0] - d[0, 0])
    f = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
    b, c = source.bulge, source.clumps
    return own, Source(
        bulge=Sersic(flux=f(np.asarray(b.flux)[k:k + 1]), re_arcsec=b.re_arcsec, n=b.n, q=b.q,
                     pa_rad=f(float(b.pa_rad) + turn), center_arcsec=f(move(b.center_arcsec)[0])),
        clumps=Clumps(center_arcsec=f(move(c.center_arcsec)), flux=f(np.asarray(c.flux)[:, k:k + 1]),
                      re_arcsec=c.re_arcsec, n=c.n, q=c.q, pa_rad=f(np.asarray(c.pa_rad) + turn)))


def _mock(kind, seed, work: Path, psf_oversampling: int = 1, truth_oversampling=None,
          psf_sampling: int = 1, clump_q_min: float = 1.0, clump_shape: str = "round"):
    """Write the mock's files and scene (drawn at `truth_oversampling`, default the fit's
    `psf_oversampling`; clumps' q uniform in [clump_q_min, 1] and PA uniform, from a generator
    of their own, so that every other draw is the round mock's; the scene's [fit]
    clump_shape); returns (scene path, truth table, zero points)."""
    rng = np.random.default_rng(500 + seed)
    bands = FORMATS[kind]
    rot = float(rng.uniform(0, 360))
    turn = [0.0] * len(bands)
    if kind == "jwst_turned":     # its own generator: the truth and noise stay "jwst"'s
        turn[1] = float(np.random.default_rng(900 + seed).uniform(*TURN_DEG))
    headers = [_header(shape, pix, rot + dr) for (_, _, pix, shape), dr in zip(bands, turn)]
    frames = [BandFrame(shape, pix, celestial_wcs(h)) for (_, _, pix, shape), h in zip(bands, headers)]
    frame = fit_frame(frames, [b[0] for b in bands])
    t = _truth(rng, bands, frame)
    shape_rng = np.random.default_rng(700 + seed)
    q = shape_rng.uniform(clump_q_min, 1.0, N_CLUMPS) if clump_q_min < 1 else np.ones(N_CLUMPS)
    pa = shape_rng.uniform(0.0, np.pi, N_CLUMPS) if clump_q_min < 1 else np.zeros(N_CLUMPS)
    if kind.startswith("jwst"):
        zps = [zeropoint_mjy_sr((pix / 206264.806) ** 2) for _, _, pix, _ in bands]
    else:
        zps = [zeropoint_photflam(*ACS[name]) for name, _, _, _ in bands]
    units = np.array([10 ** (-0.4 * (zp - AB_ZERO_UJY)) for zp in zps])     # μJy per data unit
    flux = t["ujy"] / units                                               # [N, B] data units
    f = t["f"]
    host_flux = 4.0 * t["ref_ujy"] / units
    truth = Source(bulge=Sersic(flux=f(host_flux), re_arcsec=f(t["host_re"]), n=f(1.0),
                                q=f(t["host_q"]), pa_rad=f(t["host_pa"]), center_arcsec=f([0.0, 0.0])),
                   clumps=Clumps(center_arcsec=f(t["pos"]), flux=f(flux), re_arcsec=f(t["re"]),
                                 n=f(np.ones(N_CLUMPS)), q=f(q), pa_rad=f(pa)))
    psfs = [load_psf_fits(_psf_file(work / f"psf_{name}.fits", pix, sampling=psf_sampling)) for name, _, pix, _ in bands]
    # elliptical clumps need the Sérsic renderer (the round ones ignore q and PA)
    opts = FitOptions(clump_n=1.0, clump_shape="elliptical" if clump_q_min < 1 else "round",
                      psf_oversampling=truth_oversampling or psf_oversampling)
    model = make_model_factory([_Ob(b[0], p) for b, p in zip(bands, psfs)], frame, opts)(truth)
    images = [np.asarray(i) for i in model.band_images(truth)]
    for k, dr in enumerate(turn):
        if dr:    # not by the turned path under test: the fit's model on the band's own frame
            own, src = _in_own_frame(truth, frame, frames[k], k)
            images[k] = np.asarray(make_model_factory([_Ob(bands[k][0], psfs[k])], own, opts)(
                src).band_images(src)[0])
    lines = [f'[scene]\nname = "pulls-{kind}-{seed}"\nz_source = {Z}\n']
    snr = []
    for k, ((name, inst, pix, shape), h, img) in enumerate(zip(bands, headers, images)):
        # σ: a point source of the reference clump's flux at S/N TARGET_SNR (4π σ_psf² pixels)
        sigma = (t["ref_ujy"][k] / units[k]) / (TARGET_SNR * math.sqrt(4 * math.pi) * PSF_SIGMA_PIX)
        sci = img + rng.normal(0.0, sigma, shape)
        # each clump's S/N in this band: a Gaussian matched filter of the PSF ⊕ the clump's
        # Gaussian-equivalent σ (R_e / 1.1774), approximate for n = 1 clumps
        s2 = PSF_SIGMA_PIX**2 + (t["re"] / 1.1774 / pix) ** 2
        snr.append(flux[:, k] / (sigma * np.sqrt(4 * math.pi * s2)))
        if kind.startswith("jwst"):
            path = write_cutout(work / f"{name}_i2d.fits", sci, np.full(shape, sigma), header=h,
                                bunit="MJy/sr", extra={"PIXAR_SR": (pix / 206264.806) ** 2})
        else:
            path = write_cutout(work / f"{name}_drz.fits", sci, header=h, bunit="ELECTRONS/S",
                                wht=np.full(shape, sigma**-2),
                                extra={"EXPTIME": HST_EXPTIME_S, "PHOTFLAM": ACS[name][0],
                                       "PHOTPLAM": ACS[name][1]})
        lines.append(f'[[observations]]\nfilter = "{name}"\ninstrument = "{inst}"\n'
                     f'image = "{path}"\npsf = "{work / f"psf_{name}.fits"}"\n')
    lines.append(f'[fit]\nclumps = "auto"\nclump_n = 1.0\npsf_oversampling = {psf_oversampling}\n'
                 f'clump_shape = "{clump_shape}"\n')
    scene = work / "scene.toml"
    scene.write_text("\n".join(lines))
    ra, dec = frame.radec(t["pos"])
    tab = Table({"ra_deg": ra, "dec_deg": dec, "re_arcsec": t["re"], "q": q, "mass_msun": t["mass"],
                 "age_myr": t["age"], "snr": np.sqrt(np.sum(np.square(snr), axis=0))})
    for k, (name, _, _, _) in enumerate(bands):
        tab[f"mag_{name}"] = zps[k] - 2.5 * np.log10(flux[:, k])
    return str(scene), tab, [b[0] for b in bands], min(b[2] for b in bands)


HOST_ALTERNATIVE = FLAGS["host_alternative"]


def _skewed_pull(fit, j, col, truth):
    """(fit − truth)/σ with σ the side of the posterior the truth lies on: median − p16 below,
    p84 − median above (the SED fit's mass posterior is skewed: with two rest-UV bands
    several tenths of a dex). Half the 16–84 % width where the table has no p16/p84."""
    m = float(fit[col][j])
    if f"{col}_p16" not in fit.colnames:
        return float((m - truth) / fit[f"{col}_err"][j])
    side = m - float(fit[f"{col}_p16"][j]) if truth < m else float(fit[f"{col}_p84"][j]) - m
    return float((m - truth) / side) if side > 0 else float("nan")


def _pulls(true: Table, fit: Table, names, pix):
    cosd = math.cos(math.radians(DEC0))
    d = np.hypot((np.asarray(fit["ra_deg"])[None, :] - np.asarray(true["ra_deg"])[:, None]) * cosd,
                 np.asarray(fit["dec_deg"])[None, :] - np.asarray(true["dec_deg"])[:, None]) * 3600 / pix
    used, rows = set(), []
    for i in np.argsort(np.asarray(true[f"mag_{names[0]}"])):      # brightest first
        j = next((int(j) for j in np.argsort(d[i]) if d[i, j] <= MATCH_PIX and int(j) not in used), None)
        row = dict(recovered=j is not None, mag=float(true[f"mag_{names[0]}"][i]),
                   snr=float(true["snr"][i]),
                   re_true=float(true["re_arcsec"][i]), q_true=float(true["q"][i]),
                   mass_true=float(true["mass_msun"][i]))
        if j is not None:
            used.add(j)
            p = lambda col, tv: float((fit[col][j] - tv) / fit[f"{col}_err"][j])  # noqa: E731
            for n in names:
                row[f"pull_mag_{n}"] = p(f"mag_{n}", true[f"mag_{n}"][i])
            # the colour (first band − second): what multiple images of one clump must share
            # (lensing is achromatic); σ from the two magnitudes' errors in quadrature, as a
            # reader of fit.ecsv would combine them (their covariance is not in the table)
            a, b = names[0], names[1]
            row["pull_colour"] = float(((fit[f"mag_{a}"][j] - fit[f"mag_{b}"][j])
                                        - (true[f"mag_{a}"][i] - true[f"mag_{b}"][i]))
                                       / math.hypot(fit[f"mag_{a}_err"][j], fit[f"mag_{b}_err"][j]))
            row["pull_re"] = p("re_arcsec", true["re_arcsec"][i])
            row["pull_ra"] = float((fit["ra_deg"][j] - true["ra_deg"][i]) * cosd * 3600
                                   / (fit["ra_deg_err"][j] * cosd * 3600))
            row["pull_dec"] = p("dec_deg", true["dec_deg"][i])
            if "mass_msun" in fit.colnames:
                row["pull_mass_sym"] = p("mass_msun", true["mass_msun"][i])
                row["pull_mass"] = _skewed_pull(fit, j, "mass_msun", true["mass_msun"][i])
            row["flag"] = int(fit["flag"][j])
            row["re_fit"] = float(fit["re_arcsec"][j])
            row["re_ul"] = float(fit["re_arcsec_ul"][j])     # NaN unless flag 16
            row["q_fit"] = float(fit["q"][j]) if "q" in fit.colnames else 1.0
        rows.append(row)
    # the false clumps' S/N: flux / σ per band, in quadrature (negative fluxes count as 0)
    unused = [j for j in range(len(fit)) if j not in used]
    false_snr = [float(np.sqrt(sum(max(fit[f"flux_{n}"][j] / fit[f"flux_{n}_err"][j], 0.0) ** 2
                                   for n in names))) for j in unused]
    return rows, false_snr


def _summary(rows):
    keys = sorted({k for r in rows for k in r if k.startswith("pull_")})
    out = {}
    for k in keys:
        v = np.array([r[k] for r in rows if k in r and np.isfinite(r[k])])
        if v.size:
            a = np.abs(v)
            out[k] = dict(n=int(v.size), mean=float(v.mean()), std=float(v.std(ddof=1)) if v.size > 1 else float("nan"),
                          within1=float(np.mean(a < 1)), within2=float(np.mean(a < 2)),
                          within3=float(np.mean(a < 3)))
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--formats", default="jwst,hst")
    ap.add_argument("--name", default="observation_pulls")
    ap.add_argument("--psf-oversampling", type=int, default=1)
    ap.add_argument("--psf-sampling", type=int, default=1,
                    help="PSF images this many times finer than the pixels (odd)")
    ap.add_argument("--truth-oversampling", type=int, default=None,
                    help="the mock's drawing (default: --psf-oversampling)")
    ap.add_argument("--keep", default=None, help="work folder kept (files, scenes, fits)")
    ap.add_argument("--clump-q-min", type=float, default=1.0,
                    help="clumps' axis ratio uniform in [Q, 1] (default 1: round)")
    ap.add_argument("--clump-shape", choices=("round", "elliptical"), default="round",
                    help="the fit's [fit] clump_shape")
    args = ap.parse_args()
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="obs-pulls-"))
    results, t_all = [], time.time()
    for kind in args.formats.split(","):
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            work = root / f"{kind}-{seed}"
            work.mkdir(parents=True, exist_ok=True)
            scene, true, names, pix = _mock(kind, seed, work, args.psf_oversampling,
                                            args.truth_oversampling, args.psf_sampling,
                                            args.clump_q_min, args.clump_shape)
            t0 = time.time()
            done = work / "fit" / "summary.json"
            if done.is_file():    # --keep: a finished fit is evaluated again, not refitted
                rc, wall = 0, json.loads(done.read_text())["timings_s"].get("command_total", np.nan)
            else:
                rc = cli(["fit", scene, "--out", str(work / "fit"), "-q"])
                wall = time.time() - t0
            if rc != 0:
                results.append(dict(kind=kind, seed=seed, rc=rc, fit_s=wall))
                continue
            fit = Table.read(work / "fit" / "fit.ecsv")
            summ = json.loads((work / "fit" / "summary.json").read_text())
            rows, false_snr = _pulls(true, fit, names, pix)
            false = len(false_snr)
            results.append(dict(kind=kind, seed=seed, rc=rc, fit_s=wall, n_fit=len(fit), false=false,
                                false_snr=false_snr,
                                chi2_per_dof=summ["chi2_per_dof"], clumps=rows))
            print(kind, seed, f"{wall:.0f} s", f"{sum(r['recovered'] for r in rows)}/{len(rows)} recovered,",
                  false, "false", flush=True)
    by_kind = {k: _summary([r for res in results if res["kind"] == k for r in res.get("clumps", [])
                            if r["recovered"]]) for k in args.formats.split(",")}
    allrows = [r for res in results for r in res.get("clumps", []) if r["recovered"]]
    bright = [r for res in results for r in res.get("clumps", []) if r["snr"] > 10]
    bright_rec = [r for r in bright if r["recovered"]]
    in3 = [all(abs(r[k]) < 3 for k in r if k.startswith("pull_") and not k.startswith("pull_mass")
               and np.isfinite(r[k])) for r in bright_rec]
    snr10 = dict(n=len(bright), recovered=len(bright_rec),
                 pulls_within3=int(sum(in3)),
                 false_per_mock=[res["false"] for res in results if "false" in res],
                 false_above_10_per_mock=[sum(v > 10 for v in res["false_snr"])
                                          for res in results if "false_snr" in res])
    # flag 64 (host_alternative): the counting found the host's light shared otherwise
    # nearly as well, with this clump's flux > 2σ away; its σ misses that systematic
    flagged = [r for r in allrows if r.get("flag", 0) & HOST_ALTERNATIVE]
    unflagged = [r for r in allrows if not r.get("flag", 0) & HOST_ALTERNATIVE]
    payload = dict(machine=machine(), n_clumps=N_CLUMPS, match_pix=MATCH_PIX, results=results,
                   summary=dict(by_format=by_kind, all=_summary(allrows), snr_above_10=snr10,
                                without_host_alternative=_summary(unflagged),
                                host_alternative=[{k: v for k, v in r.items()
                                                   if k.startswith("pull_mag") or k == "snr"}
                                                  for r in flagged]),
                   wall_s=time.time() - t_all)
    write_json(args.name, payload)
    md = ["# `clumpylen fit` pulls on mocks in real-product formats (issue 17)\n",
          f"{machine()['date']}; {N_CLUMPS} clumps per mock, z = {Z}, clumps = \"auto\" (no truth), "
          f"clumps' q in [{args.clump_q_min}, 1], fitted {args.clump_shape}, "
          f"psf_oversampling = {args.psf_oversampling} (mock drawn at "
          f"{args.truth_oversampling or args.psf_oversampling}), PSF images sampled "
          f"{args.psf_sampling}× finer than the pixels, "
          f"matched within {MATCH_PIX} finest pixels; {time.time() - t_all:.0f} s wall in all.\n",
          "| format | seed | fit s | χ²/dof | found | false | recovered |", "|---|---|---|---|---|---|---|"]
    for res in results:
        if res["rc"] != 0:
            md.append(f"| {res['kind']} | {res['seed']} | {res['fit_s']:.0f} | exit {res['rc']} | | | |")
            continue
        chi = ", ".join(f"{v:.3f}" for v in res["chi2_per_dof"].values())
        rec = sum(r["recovered"] for r in res["clumps"])
        md.append(f"| {res['kind']} | {res['seed']} | {res['fit_s']:.0f} | {chi} | {res['n_fit']} | "
                  f"{res['false']} | {rec}/{len(res['clumps'])} |")
    md += ["", f"At S/N > 10 (the truth's approximate S/N, bands in quadrature): "
           f"{snr10['recovered']}/{snr10['n']} recovered; magnitude, R_e and position pulls all "
           f"within ±3 for {snr10['pulls_within3']}/{snr10['recovered']}; false clumps per mock "
           f"(any S/N) {snr10['false_per_mock']}, at fitted S/N > 10 {snr10['false_above_10_per_mock']}"
           f" (false clumps' S/N: " + ", ".join(f"{v:.1f}" for res in results
                                                for v in res.get("false_snr", [])) + "). Unrecovered: "
           + ", ".join(f"mag {r['mag']:.1f} S/N {r['snr']:.1f}" for res in results
                       for r in res.get("clumps", []) if not r["recovered"]) + "."]
    md += ["", "Pulls (fit − true)/σ of the recovered clumps; N(0, 1) has 0.683 / 0.954 / 0.997 "
           "within 1 / 2 / 3. `mass`: σ the side of the skewed posterior the truth lies on "
           "(median − p16 or p84 − median); `mass_sym`: half the 16–84 % width:", "", "| format | pull | n | mean | std | within 1 | within 2 | within 3 |",
           "|---|---|---|---|---|---|---|---|"]
    for kind, summ in list(by_kind.items()) + [("all", payload["summary"]["all"])]:
        for k, s in summ.items():
            md.append(f"| {kind} | {k[5:]} | {s['n']} | {s['mean']:+.2f} | {s['std']:.2f} | "
                      f"{s['within1']:.2f} | {s['within2']:.2f} | {s['within3']:.2f} |")
    md += ["", f"Flag 64 (host alternative) on {len(flagged)} of {len(allrows)} recovered clumps; "
           "their magnitude pulls: " + (", ".join(
               "/".join(f"{r[k]:+.1f}" for k in sorted(r) if k.startswith("pull_mag"))
               for r in flagged) or "none") + ". The pulls of the others:", "",
           "| pull | n | mean | std | within 1 | within 2 | within 3 |", "|---|---|---|---|---|---|---|"]
    for k, s in payload["summary"]["without_host_alternative"].items():
        md.append(f"| {k[5:]} | {s['n']} | {s['mean']:+.2f} | {s['std']:.2f} | "
                  f"{s['within1']:.2f} | {s['within2']:.2f} | {s['within3']:.2f} |")
    # flag 16: the size unresolved; is the true R_e below the fit's 95 % upper limit?
    unres = [r for r in allrows if r.get("flag", 0) & FLAGS["size_unresolved"]]
    md += ["", f"Flag 16 (size unresolved) on {len(unres)} of {len(allrows)} recovered clumps; "
           f"true R_e below `re_arcsec_ul` (one-sided 95 %) for "
           f"{sum(r['re_true'] < r['re_ul'] for r in unres)}/{len(unres)}" + "".join(
               f"; S/N {r['snr']:.0f}: true {r['re_true'] * 1e3:.1f} mas, limit {r['re_ul'] * 1e3:.1f}"
               for r in unres) + "."]
    write_text(f"{args.name}.md", "\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
