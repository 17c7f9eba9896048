"""The fitted-clump catalogue: one row per clump, catalogue column names with `_err` twins.

Columns (SCENE.md names): id, beta1_arcsec, beta2_arcsec, re_arcsec, n, q, pa_rad,
flux_<FILTER> (intrinsic counts/s), mag_<FILTER> (AB, when zero points are given),
and mass_msun, age_myr for photometric fits; each followed by `<name>_err`
(1σ; NaN where the parameter was held fixed). Magnitude errors by the delta method:
σ_m = 2.5/ln 10 · σ_F/F.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .params import FitState, Parametrization

MAG_PER_LN = 2.5 / np.log(10.0)   # σ_m = MAG_PER_LN · σ_F / F (delta method)


def ab_magnitude(flux, zeropoint_ab):
    """AB magnitude ZP − 2.5 log10 F of fluxes F > 0 in the zero point's units (counts/s)."""
    return zeropoint_ab - 2.5 * np.log10(flux)


def ab_magnitude_err(flux, flux_err):
    """1σ magnitude error of a flux F ± σ_F by the delta method."""
    return MAG_PER_LN * flux_err / flux


def errors_state(param: Parametrization, err) -> FitState:
    """A FitState-shaped pytree of 1σ errors (`err` in the layout of u; NaN for fixed entries)."""
    return param.scatter(np.asarray(err, float), fill=np.nan)


def fit_table(state: FitState, errors: Optional[FitState] = None, *, band_names,
              zeropoints_ab: Optional[dict] = None):
    """astropy Table of the clumps of `state` with errors from `errors` (see `errors_state`).

    band_names: filter names in band order (column suffixes).
    zeropoints_ab: {band: AB zero point giving 1 count/s} to add mag_<band> columns.
    """
    from astropy import units as u
    from astropy.table import Table

    src = state.render_source()
    cl = src.clumps
    n = 0 if cl is None else cl.count
    t = Table()
    t["id"] = np.arange(n)
    if n == 0:
        return t
    nan = np.full(n, np.nan)

    def err_of(getter):
        if errors is None:
            return nan
        try:
            val = getter(errors)
        except AttributeError:
            return nan
        return nan if val is None else np.asarray(val, float)

    def add(name, value, error, unit=None):
        t[name] = np.asarray(value, float)
        t[f"{name}_err"] = np.asarray(error, float)
        if unit is not None:
            t[name].unit = unit
            t[f"{name}_err"].unit = unit

    center = np.asarray(cl.center_arcsec, float)
    c_err = err_of(lambda e: e.source.clumps.center_arcsec)
    c_err = np.broadcast_to(c_err[:, None], (n, 2)) if np.ndim(c_err) == 1 else c_err
    add("beta1_arcsec", center[:, 0], c_err[:, 0], u.arcsec)
    add("beta2_arcsec", center[:, 1], c_err[:, 1], u.arcsec)
    add("re_arcsec", cl.re_arcsec, err_of(lambda e: e.source.clumps.re_arcsec), u.arcsec)
    add("n", cl.n, err_of(lambda e: e.source.clumps.n))
    add("q", cl.q, err_of(lambda e: e.source.clumps.q))
    add("pa_rad", cl.pa_rad, err_of(lambda e: e.source.clumps.pa_rad), u.rad)
    if state.mass_msun is not None:
        add("mass_msun", state.mass_msun, err_of(lambda e: e.mass_msun))
        add("age_myr", state.age_myr, err_of(lambda e: e.age_myr))
    flux = np.asarray(cl.flux, float)
    f_err = err_of(lambda e: e.source.clumps.flux)
    f_err = np.broadcast_to(f_err[:, None], flux.shape) if np.ndim(f_err) == 1 else f_err
    zps = zeropoints_ab or {}
    for b, name in enumerate(band_names):
        add(f"flux_{name}", flux[:, b], f_err[:, b])
        if name in zps:
            with np.errstate(divide="ignore", invalid="ignore"):
                mag = np.where(flux[:, b] > 0, ab_magnitude(flux[:, b], zps[name]), np.inf)
                mag_err = ab_magnitude_err(flux[:, b], f_err[:, b])
            add(f"mag_{name}", mag, np.where(flux[:, b] > 0, mag_err, np.inf))
    return t


def host_meta(state: FitState, labels=None, err=None) -> dict:
    """The fitted host components for fit.ecsv's header: {"bulge": …, "disk": …}, each with
    flux per band (counts/s), re_arcsec, center_arcsec, n, q, pa_rad, and with `labels` and
    `err` (a parametrization's labels and 1σ per entry) `<field>_err` for the fitted ones.
    A fit without clumps still reports what it fitted; a fit with them shows where a host
    holds light the clumps do not (a cusp can hold a compact clump's)."""
    errs = {} if err is None else dict(zip(labels, np.asarray(err, float)))
    src = state.render_source()
    out = {}
    for name, comp in (("bulge", src.bulge), ("disk", None if src.disk is None else src.disk.sersic)):
        if comp is None:
            continue
        path = "bulge" if name == "bulge" else "disk.sersic"
        d = {}
        for field in ("flux", "re_arcsec", "center_arcsec", "n", "q", "pa_rad"):
            val = np.asarray(getattr(comp, field), float)
            d[field] = val.tolist()
            e = [errs.get(f"{path}.{field}[{','.join(map(str, i))}]") for i in np.ndindex(val.shape)]
            if any(x is not None for x in e):
                d[f"{field}_err"] = [float("nan") if x is None else float(x) for x in e] \
                    if val.shape else float(e[0])
        out[name] = d
    return out
