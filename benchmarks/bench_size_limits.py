"""Coverage of the R_e upper limits of unresolved clumps (`inference/size_limits.py`).

Per mock, one round n = 1 clump with R_e uniform in [0, RE_MAX_PSF] × the PSF's σ (0.1–0.6 px
under a Gaussian PSF of σ 1.2 px at 0.03″) and S/N log-uniform in [8, 60] on a flat
background, Gaussian noise; fitted by `observations.fit.fit_observations` from a start off the
truth (R_e 1 px, position 1 px away, flux from the residual). Where the fit flags the size
unresolved (σ(R_e) > R_e), the one-sided 95 % upper limit should lie above the true R_e in
about 95 % of mocks; the limit holds the position and background, so a little below 95 % is
what "a little tight" (size_limits.py) means. Also reported: how often the size is flagged, the
flux pulls of the unresolved clumps (errors from the Fisher matrix at R_e's bound: finite
since the LM keeps u within its range), and the seconds per limit.

    .venv/bin/python benchmarks/bench_size_limits.py [--mocks 60] [--name size_limits]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json, write_text  # noqa: E402

import clumpylen_jax  # noqa: E402

clumpylen_jax.enable_float64()

import jax.numpy as jnp  # noqa: E402
from astropy.io import fits  # noqa: E402

from clumpylen_jax.inference.size_limits import re_upper_limit  # noqa: E402
from clumpylen_jax.observations import FitOptions, write_cutout  # noqa: E402
from clumpylen_jax.observations.config import load_observation_scene  # noqa: E402
from clumpylen_jax.observations.fit import fit_observations, make_model_factory  # noqa: E402
from clumpylen_jax.observations.run import read_scene_data  # noqa: E402
from clumpylen_jax.source import Clumps, Source  # noqa: E402

PIX = 0.03
SHAPE = (32, 32)
SIGMA = 0.01               # noise per pixel (data units)
PSF_SIGMA_PIX = 1.2
RE_MAX_PSF = 0.5           # true R_e up to this × the PSF's σ
SNR = (8.0, 60.0)
RE_MAX_FIT = 0.2           # the fit's upper R_e bound [arcsec]


def _setup(work: Path):
    y, x = np.mgrid[:15, :15] - 7.0
    psf = np.exp(-(x**2 + y**2) / (2 * PSF_SIGMA_PIX**2))
    h = fits.Header()
    h["PIXSCALE"] = PIX
    fits.PrimaryHDU(psf, h).writeto(work / "psf.fits", overwrite=True)
    path = write_cutout(work / "c.fits", np.random.default_rng(0).normal(0.0, SIGMA, SHAPE),
                        np.full(SHAPE, SIGMA),
                        extra={"PIXSCALE": PIX})
    (work / "scene.toml").write_text(
        f'[scene]\nname = "limits"\n\n[[observations]]\nfilter = "F150W"\nimage = "{path}"\n'
        f'psf = "{work / "psf.fits"}"\n\n[fit]\nhost = "none"\nclumps = "none"\n')
    obs, frame = read_scene_data(load_observation_scene(str(work / "scene.toml")))
    p = psf / psf.sum()
    return obs, frame, SIGMA / np.sqrt(np.sum(p * p))     # a point source's flux σ


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mocks", type=int, default=60)
    ap.add_argument("--name", default="size_limits")
    args = ap.parse_args()
    t_all = time.time()
    work = Path(tempfile.mkdtemp(prefix="size-limits-"))
    obs0, frame, flux_sigma = _setup(work)
    opts = FitOptions(host="none", clumps="none", clump_re_max_arcsec=RE_MAX_FIT, clump_n=1.0)
    make_model = make_model_factory(obs0, frame, opts)
    f = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
    rows = []
    for seed in range(args.mocks):
        rng = np.random.default_rng(seed)
        re = rng.uniform(0.0, RE_MAX_PSF) * PSF_SIGMA_PIX * PIX
        flux = flux_sigma * np.exp(rng.uniform(*np.log(SNR)))
        pos = rng.uniform(-2 * PIX, 2 * PIX, 2)
        truth = Source(clumps=Clumps(center_arcsec=f([pos]), flux=f([[flux]]),
                                     re_arcsec=f([max(re, 1e-4)]), n=f([1.0]), q=f([1.0]),
                                     pa_rad=f([0.0])))
        img = np.asarray(make_model(truth).band_images(truth)[0])
        obs = [dataclasses.replace(obs0[0], data=img + rng.normal(0.0, SIGMA, SHAPE))]
        start = pos + PIX * np.array([0.8, -0.6])
        fit = fit_observations(obs, frame, opts, {"phi": start[None], "re_arcsec": np.array([PIX])})
        err = dict(zip(fit.uncertainty.labels, np.asarray(fit.uncertainty.err)))
        re_fit, re_err = float(fit.state.source.clumps.re_arcsec[0]), err["clumps.re_arcsec[0]"]
        row = dict(seed=seed, re_true=re, snr=flux / flux_sigma, re_fit=re_fit, re_err=re_err,
                   flux_pull=(float(fit.state.source.clumps.flux[0, 0]) - flux)
                   / err["clumps.flux[0,0]"], converged=bool(fit.success),
                   unresolved=bool(re_err > re_fit))
        if row["unresolved"]:
            model, state = fit.drawing()
            t0 = time.perf_counter()
            row["re_ul"] = re_upper_limit(model, fit.data, state, 0, RE_MAX_FIT)
            row["ul_s"] = time.perf_counter() - t0
        rows.append(row)
        print(seed, {k: (round(v, 5) if isinstance(v, float) else v) for k, v in row.items()})
    unres = [r for r in rows if r["unresolved"]]
    covered = sum(r["re_true"] < r["re_ul"] for r in unres)
    pulls = np.array([r["flux_pull"] for r in unres])
    payload = dict(machine=machine(), mocks=args.mocks, rows=rows, unresolved=len(unres),
                   covered=covered, wall_s=time.time() - t_all)
    write_json(args.name, payload)
    bins = [(0.0, 0.25), (0.25, 0.5)]
    md = ["# R_e upper limits of unresolved clumps: coverage (`inference/size_limits.py`)", "",
          f"{machine()['date']}; {args.mocks} mocks, one round n = 1 clump each, R_e uniform in "
          f"[0, {RE_MAX_PSF}] × PSF σ ({PSF_SIGMA_PIX} px Gaussian, {PIX}″ pixels), S/N "
          f"log-uniform in {list(SNR)}; fits started off the truth; "
          f"{time.time() - t_all:.0f} s wall in all.", "",
          f"- Flagged unresolved (σ(R_e) > R_e): {len(unres)}/{len(rows)}; converged "
          f"{sum(r['converged'] for r in rows)}/{len(rows)}.",
          f"- True R_e below the one-sided 95 % limit: **{covered}/{len(unres)}**"
          + (f" ({covered / len(unres):.2f})" if unres else "") + ".",
          f"- Limit / PSF σ: median {np.median([r['re_ul'] for r in unres]) / (PSF_SIGMA_PIX * PIX):.2f}"
          if unres else "- no limit computed",
          f"- Flux pulls of the unresolved clumps: mean {pulls.mean():+.2f}, std "
          f"{pulls.std(ddof=1):.2f}, within 3: {np.mean(np.abs(pulls) < 3):.2f}" if len(pulls) > 1
          else "- too few flux pulls",
          f"- Seconds per limit (after the first): median "
          f"{np.median([r['ul_s'] for r in unres[1:]]):.3f}" if len(unres) > 1 else "", "",
          "| true R_e / PSF σ | unresolved | covered |", "|---|---|---|"]
    s = PSF_SIGMA_PIX * PIX
    for lo, hi in bins:
        sel = [r for r in unres if lo <= r["re_true"] / s < hi]
        md.append(f"| {lo}–{hi} | {len(sel)} | {sum(r['re_true'] < r['re_ul'] for r in sel)} |")
    write_text(f"{args.name}.md", "\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
