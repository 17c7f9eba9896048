"""Accuracy of `clump_pixels = "exponential_mog"`: a round exponential (Sérsic n = 1) clump
drawn as the 8-Gaussian mixture `gaussian_mixtures.EXPONENTIAL` (each Gaussian integrated
exactly over pixels) against the exact Sérsic pixel integrals (`profiles.
sersic_pixel_flux_exact`, every pixel), float64.

    .venv/bin/python benchmarks/bench_mog_accuracy.py          (~1 min)

For R_e from 1e-3 to 30 pixels and three centres (a pixel centre, a pixel corner, an
arbitrary point), the largest |Δ| of a pixel relative to the exact image's peak pixel and
to the flux: without a PSF, and after both images are convolved with the S1063 F150W
WebbPSF (../shared/data/real, detector pixels; the widest-core of the three is F200W, the
narrowest F115W: F115W reported too). Grids of ±6 R_e + 12 pixels, at most 256 pixels a
side (a 30-pixel R_e sees ±4.3 R_e: 99.4 % of its light; the errors are at the core).

In noise units: the peak-pixel S/N of a clump is at most the largest SCI/ERR of the S1063
cutout (host + clump light), so max |Δ|/σ ≤ (error relative to the peak) × that S/N, for
each band with its PSF, over R_e ≤ the fits' upper bound (0.15", 4.8 pixels).

Writes benchmarks/results/mog_accuracy.{json,md}.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from astropy.io import fits
from scipy.signal import fftconvolve

jax.config.update("jax_enable_x64", True)

from clumpylen_jax import profiles, render  # noqa: E402
from clumpylen_jax.gaussian_mixtures import round_mixture  # noqa: E402

HERE = Path(__file__).resolve().parent
DATA = HERE.parents[0].parent / "shared" / "data" / "real" / "abell_s1063_sys4_im1"
RE_PIX = (1e-3, 0.01, 0.1, 0.3, 1.0, 2.0, 4.8, 10.0, 30.0)
CENTRES = ((0.0, 0.0), (0.5, 0.5), (0.3111, -0.1734))     # pixel units from a pixel centre
FIT_RE_MAX_PIX = 4.8                                         # 0.15" / 0.0312"
BANDS = ("f115w", "f150w", "f200w")


def edges(side):
    return np.arange(side + 1) - side / 2.0                  # pixel 1: units of pixels


def exact_image(side, c, re):
    e = edges(side)

    @jax.jit
    def fan(c1, c2, r):
        return profiles.sersic_pixel_flux_exact(
            e[None, :-1], e[None, 1:], e[:-1, None], e[1:, None], flux=1.0, re_arcsec=r, n=1.0,
            q=1.0, pa_rad=0.0, center1=c1, center2=c2)
    return np.asarray(fan(c[0], c[1], re))


def mog_image(side, c, re):
    _, a, s = round_mixture("exponential_mog")
    sig = jnp.asarray(s) * re
    e = edges(side)
    fx = render.gaussian_pixel_fractions(e, jnp.full(len(s), c[0]), sig)
    fy = render.gaussian_pixel_fractions(e, jnp.full(len(s), c[1]), sig)
    return np.asarray(jnp.einsum("k,ki,kj->ij", jnp.asarray(a), fy, fx))


def psf(band):
    p = fits.getdata(DATA / f"psf_webbpsf_{band}.fits").astype(float)
    return p / p.sum()


def max_snr(band):
    with fits.open(DATA / f"s1063_sys4_im1_{band}.fits") as h:
        sci, err = h["SCI"].data.astype(float), h["ERR"].data.astype(float)
    ok = np.isfinite(sci) & np.isfinite(err) & (err > 0)
    return float(np.max(sci[ok] / err[ok]))


def main():
    psfs = {b: psf(b) for b in BANDS}
    rows = []
    for re in RE_PIX:
        side = int(min(256, 2 * np.ceil(6 * re) + 24))
        for c in CENTRES:
            ex, mg = exact_image(side, c, re), mog_image(side, c, re)
            row = dict(re_pix=re, centre=c, side=side, flux_exact=float(ex.sum()),
                       flux_mog=float(mg.sum()))
            for name, k in [("none", None)] + [(b, psfs[b]) for b in BANDS]:
                a, b = (ex, mg) if k is None else (fftconvolve(ex, k, "same"),
                                                   fftconvolve(mg, k, "same"))
                d = np.abs(b - a).max()
                row[f"peak_{name}"] = float(d / a.max())
                row[f"flux_{name}"] = float(d)           # unit flux
            rows.append(row)
            print(f"R_e {re:7.3g} px, centre {c}: Δ/peak {row['peak_none']:.2e} (no PSF), "
                  f"{row['peak_f150w']:.2e} (F150W); Δ/flux {row['flux_none']:.2e}, "
                  f"{row['flux_f150w']:.2e}", flush=True)
    noise = {}
    for b in BANDS:
        worst = max(r[f"peak_{b}"] for r in rows if r["re_pix"] <= FIT_RE_MAX_PIX)
        snr = max_snr(b)
        noise[b] = dict(max_snr=snr, worst_peak_error=worst, max_delta_sigma=worst * snr)
    summary = {"rows": rows, "noise_s1063": noise,
               "max_peak_error_no_psf": max(r["peak_none"] for r in rows),
               "max_flux_error_no_psf": max(r["flux_none"] for r in rows),
               "max_peak_error_psf": max(r[f"peak_{b}"] for r in rows for b in BANDS),
               "max_flux_error_psf": max(r[f"flux_{b}"] for r in rows for b in BANDS)}
    out = HERE / "results"
    (out / "mog_accuracy.json").write_text(json.dumps(summary, indent=1) + "\n")
    lines = ["# exponential_mog against the exact n = 1 pixel integrals (bench_mog_accuracy.py)", "",
             "max |Δ| of a pixel / the exact peak pixel, and / the flux (worst of 3 centres)", "",
             "| R_e (px) | peak, no PSF | peak, F115W | peak, F150W | peak, F200W | flux, no PSF | flux, F150W |",
             "|---|---|---|---|---|---|---|"]
    for re in RE_PIX:
        rr = [r for r in rows if r["re_pix"] == re]
        m = lambda k: max(r[k] for r in rr)  # noqa: E731
        lines.append(f"| {re:g} | {m('peak_none'):.1e} | {m('peak_f115w'):.1e} | "
                     f"{m('peak_f150w'):.1e} | {m('peak_f200w'):.1e} | {m('flux_none'):.1e} | "
                     f"{m('flux_f150w'):.1e} |")
    lines += ["", "S1063 noise (R_e ≤ 4.8 px): max SCI/ERR of the cutout × worst peak error = "
              "max |Δ| in σ", ""]
    lines += [f"- {b}: S/N ≤ {v['max_snr']:.0f}, error ≤ {v['worst_peak_error']:.1e} of the peak "
              f"→ |Δ| ≤ {v['max_delta_sigma']:.3f} σ" for b, v in noise.items()]
    (out / "mog_accuracy.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
