"""Observation scenes: `[[observations]]`, `[fit]`, `[scene]` and `[lens.local]` from TOML.

A scene with `[[observations]]` (SCENE.md, "Fitting observed images (v2)")
describes data to fit instead of bands to simulate. `load_observation_scene`
checks every key (unknown ones are an error naming the nearest valid key),
resolves paths relative to the scene file, and returns an `ObservationScene`.
Nothing is read or computed beyond the TOML here.

Beyond SCENE.md, `[fit]` takes the knobs of the fit (defaults in `FitOptions`) and
`[lens]` a lens through which intrinsic (source-plane) sizes, magnitudes, positions and
magnifications are reported: `[lens.local]`, convergence and shear at the arc, constant
over the cutout (`{ convergence = 0.7, shear = [0.1, -0.05] }`); or a lens model with the
keys of a simulation scene's `[lens]` (z_lens, center_radec_deg, and deflection maps, a
built-in model or analytic components), placed on the cutout by the data's celestial WCS,
or by `cutout_center_radec_deg` / `cutout_center_arcsec` (where the first observation's
central pixel lies: on the sky, or in θ from the lens centre).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import tomllib
from pathlib import Path
from typing import Optional

from ..errors import ConfigError
from .read import ObservationSpec

FIT_METHODS = ("map", "nuts", "emcee")


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """[fit]: what is fitted and how (one place for each default).

    clumps: "auto" (found in the data, inference.auto), "none" (host only), or a
        catalogue path of starting guesses (columns x_pix/y_pix of the first
        observation, or ra_deg/dec_deg, or theta1_arcsec/theta2_arcsec; optional
        re_arcsec).
    max_clumps: most clumps "auto" may add.
    method: "map" (the optimum, errors from the Fisher matrix), or "nuts" / "emcee": the
        posterior sampled from that optimum (observations/sample.py), its median and
        standard deviations reported; `--method` overrides it.
    image_match_arcsec, image_separation_min_arcsec: with a lens model, clumps whose β agree
        within image_match_arcsec (⊕ 3σ of the fitted β) and that have opposite parity or lie
        at least image_separation_min_arcsec apart are images of one source clump
        (`source_id`; observations/multiple_images.py).
    sampler_chains: NUTS chains (emcee: 2 × parameters + 2 walkers, always).
    sampler_warmup: NUTS adaptation steps per chain, or emcee steps discarded as burn-in.
    sampler_samples: draws kept per chain (NUTS) or per walker (emcee).
    clump_n: Sérsic index of the clumps (fixed). Round clumps are drawn without stamps
        (`model.clumps.RoundGaussianClumps`): n = 0.5 as one Gaussian (exact), n = 1 (the
        default) as 8 Gaussians ("exponential_mog", ≤ 0.011 σ of the S1063 data from the
        exact n = 1 pixels; the S1063 fit 990 → 411 s, same answer); other n on Sérsic
        stamps. The default stays 1.0 because on S1063 n = 0.5 counted 5 clumps where
        n = 1 counted 10, at a χ² worse by 557 (more than the 5 clumps' BIC penalty of
        320: CHANGELOG, 2026-11-25 "round Gaussian clumps").
    clump_shape: "round" or "elliptical".
    clump_re_max_arcsec: the largest clump R_e a fit may reach (the stamps are built
        for it); clump_re_min_arcsec the smallest.
    host: "sersic" (one smooth Sérsic, free in every band) or "none".
    background: fit a constant level per band.  psf_oversampling: odd sub-grid factor.
    diffuse_spacing_arcsec: a smooth diffuse light per band, on cubic B-spline nodes this far
        apart (at least 4 pixels of the coarsest band), fitted with the host and clumps and
        profiled out of the likelihood (`inference.diffuse`): for arcs and rings that one
        Sérsic cannot draw. It holds the background level (not fitted separately then).
        None (default): no diffuse light.
    detection_snr: a band detects a clump when flux/σ_flux ≥ this (else: upper limit).
    """

    clumps: str = "auto"
    max_clumps: int = 20
    method: str = "map"
    clump_n: float = 1.0
    clump_shape: str = "round"
    clump_re_max_arcsec: float = 0.15
    clump_re_min_arcsec: float = 0.002
    host: str = "sersic"
    background: bool = True
    psf_oversampling: int = 1
    detection_snr: float = 3.0
    max_steps: int = 200
    diffuse_spacing_arcsec: Optional[float] = None
    # images of one source clump (multiple_images.py): β within this (the lens model's
    # precision in the source plane, plus 3σ of the fitted β), and opposite parity or at
    # least image_separation_min_arcsec apart
    image_match_arcsec: float = 0.1
    image_separation_min_arcsec: float = 1.0
    # S1063 (102 parameters): 2 × (200 + 300) NUTS steps, ~15 leapfrog steps each, 231–259 s
    sampler_chains: int = 2
    sampler_warmup: int = 200
    sampler_samples: int = 300

    def validate(self):
        def need(ok, key, expected):
            if not ok:
                raise ConfigError(f"fit.{key}", getattr(self, key), expected)
        need(isinstance(self.clumps, str) and self.clumps, "clumps",
             '"auto", "none" or a catalogue path')
        need(isinstance(self.max_clumps, int) and 0 <= self.max_clumps <= 200, "max_clumps",
             "an integer in [0, 200]")
        need(self.method in FIT_METHODS, "method",
             " or ".join(f'"{m}"' for m in FIT_METHODS))
        need(_num(self.image_match_arcsec) and self.image_match_arcsec >= 0,
             "image_match_arcsec", "a source-plane distance ≥ 0 arcsec")
        need(_num(self.image_separation_min_arcsec) and self.image_separation_min_arcsec > 0,
             "image_separation_min_arcsec", "an image-plane distance > 0 arcsec")
        need(isinstance(self.sampler_chains, int) and 1 <= self.sampler_chains <= 64,
             "sampler_chains", "an integer in [1, 64]")
        need(isinstance(self.sampler_warmup, int) and 0 <= self.sampler_warmup <= 100000,
             "sampler_warmup", "an integer in [0, 100000]")
        need(isinstance(self.sampler_samples, int) and 10 <= self.sampler_samples <= 100000,
             "sampler_samples", "an integer in [10, 100000]")
        need(_num(self.clump_n) and 0.2 <= self.clump_n <= 10, "clump_n", "a Sérsic index in [0.2, 10]")
        need(self.clump_shape in ("round", "elliptical"), "clump_shape", '"round" or "elliptical"')
        need(_num(self.clump_re_min_arcsec) and self.clump_re_min_arcsec > 0, "clump_re_min_arcsec",
             "a positive size (arcsec)")
        need(_num(self.clump_re_max_arcsec) and
             self.clump_re_min_arcsec < self.clump_re_max_arcsec <= 2.0, "clump_re_max_arcsec",
             "a size (arcsec) above clump_re_min_arcsec and at most 2\"")
        need(self.host in ("sersic", "none"), "host", '"sersic" or "none"')
        need(isinstance(self.background, bool), "background", "true or false")
        need(isinstance(self.psf_oversampling, int) and self.psf_oversampling % 2 == 1
             and 1 <= self.psf_oversampling <= 9, "psf_oversampling", "an odd integer in [1, 9]")
        need(_num(self.detection_snr) and self.detection_snr > 0, "detection_snr", "a positive S/N")
        need(isinstance(self.max_steps, int) and 1 <= self.max_steps <= 10000, "max_steps",
             "an integer in [1, 10000]")
        need(self.diffuse_spacing_arcsec is None or (_num(self.diffuse_spacing_arcsec)
                                                     and self.diffuse_spacing_arcsec > 0),
             "diffuse_spacing_arcsec", "a node spacing > 0 arcsec")
        return self


@dataclasses.dataclass(frozen=True)
class LocalLens:
    """A lens constant over the cutout: β − β0 = A (θ − θ0), A = [[1−κ−γ1, −γ2], [−γ2, 1−κ+γ1]]."""

    convergence: float
    shear: tuple = (0.0, 0.0)

    @property
    def matrix(self):
        k, (g1, g2) = self.convergence, self.shear
        return ((1 - k - g1, -g2), (-g2, 1 - k + g1))

    @property
    def magnification(self) -> float:
        (a, b), (c, d) = self.matrix
        return 1.0 / (a * d - b * c)


@dataclasses.dataclass(frozen=True)
class LensModel:
    """A lens model (a simulation scene's `scene.Lens`) and where the cutout sits in its θ frame:
    `cutout_center_radec_deg` (RA, Dec of the first observation's central pixel; for cutouts
    without a celestial WCS) or `cutout_center_arcsec` (θ of that pixel from the lens centre),
    or neither when the data's WCS and the lens's centre place it."""

    spec: object
    cutout_center_radec_deg: Optional[tuple] = None
    cutout_center_arcsec: Optional[tuple] = None


@dataclasses.dataclass(frozen=True)
class ObservationScene:
    name: str
    observations: tuple
    fit: FitOptions
    z_source: Optional[float] = None
    seed: int = 0
    lens: Optional[object] = None   # LocalLens or LensModel
    cosmology: tuple = (70.0, 0.3)
    path: Optional[str] = None
    sps: tuple = ()                 # extra photometry.ab_magnitudes options
    age_prior: tuple = ()           # (slope, min_myr, max_myr) of the SED fit's p(t) ∝ t^slope


def _num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_keys(table: dict, allowed, where: str):
    for key in table:
        if key not in allowed:
            near = difflib.get_close_matches(key, list(allowed), n=1)
            hint = f" (did you mean '{near[0]}'?)" if near else ""
            raise ConfigError(f"{where}.{key}", table[key], f"one of {sorted(allowed)}{hint}")


_OBS_KEYS = {f.name for f in dataclasses.fields(ObservationSpec)}
_PATH_KEYS = ("image", "psf", "mask")


def _observation(t: dict, base: Path, k: int) -> ObservationSpec:
    if not isinstance(t, dict):
        raise ConfigError(f"observations[{k}]", t, "a table")
    name = t.get("filter")
    if not isinstance(name, str) or not name.strip():
        raise ConfigError(f"observations[{k}].filter", name, "a filter name, e.g. \"F150W\"")
    where = f"observations[{name.upper()}]"
    _check_keys(t, _OBS_KEYS, where)
    if not isinstance(t.get("image"), str):
        raise ConfigError(f"{where}.image", t.get("image"), "a FITS file path")
    d = dict(t, filter=name.strip().upper())
    for key in _PATH_KEYS:
        if isinstance(d.get(key), str):
            d[key] = str(base / d[key])
    for key in ("error", "weight"):     # an HDU name stays a name; anything else is a path
        v = d.get(key)
        if isinstance(v, str) and ("/" in v or v.lower().endswith((".fits", ".fit", ".fz"))):
            d[key] = str(base / v)
    for key in ("pixel_arcsec", "zeropoint_ab", "psf_pixel_arcsec", "exptime_s"):
        if key in d and not _num(d[key]):
            raise ConfigError(f"{where}.{key}", d[key], "a number")
    pm = d.get("pixel_matrix_arcsec")
    if pm is not None and not (isinstance(pm, list) and len(pm) == 2 and all(
            isinstance(r, list) and len(r) == 2 and all(_num(x) for x in r) for r in pm)):
        raise ConfigError(f"{where}.pixel_matrix_arcsec", pm,
                          "[[E/x, E/y], [N/x, N/y]]: four numbers, arcsec per pixel")
    if "noise" in d and not isinstance(d["noise"], dict):
        raise ConfigError(f"{where}.noise", d["noise"], "{ background_rms = ..., exptime_s = ... }")
    return ObservationSpec(**d)


def _local_lens(loc) -> LocalLens:
    _check_keys(loc, {"convergence", "shear"}, "lens.local")
    k, g = loc.get("convergence"), loc.get("shear", [0.0, 0.0])
    if not _num(k):
        raise ConfigError("lens.local.convergence", k, "a number")
    if not (isinstance(g, list) and len(g) == 2 and all(_num(x) for x in g)):
        raise ConfigError("lens.local.shear", g, "[gamma1, gamma2]")
    lens = LocalLens(float(k), (float(g[0]), float(g[1])))
    mu = lens.magnification
    if not (math.isfinite(mu) and abs(mu) < 1e4):
        raise ConfigError("lens.local", loc, "a lens away from a critical curve (|μ| < 1e4)")
    return lens


_PLACEMENT_KEYS = ("cutout_center_radec_deg", "cutout_center_arcsec")


def _lens(t, z_source, base):
    """`[lens]`: LocalLens ([lens.local]) or LensModel (a simulation scene's lens keys plus
    where the cutout sits), or None."""
    if t is None:
        return None
    if not isinstance(t, dict):
        raise ConfigError("lens", t, "a table: [lens.local] or a lens model")
    if "local" in t:
        if set(t) - {"local"}:
            raise ConfigError("lens", sorted(t), "either [lens.local] alone or a lens model "
                              "(z_lens, center_radec_deg, deflection | model | components)")
        return _local_lens(t["local"])
    if z_source is None:
        raise ConfigError("scene.z_source", None, "a redshift: a lens model's deflection scales "
                          "with D_ls/D_s(z_lens, z_source)")
    from ..scene import parse_lens
    place = {k: t[k] for k in _PLACEMENT_KEYS if k in t}
    if len(place) > 1:
        raise ConfigError("lens", sorted(place), "at most one of " + ", ".join(_PLACEMENT_KEYS))
    for key, v in place.items():
        if not (isinstance(v, list) and len(v) == 2 and all(_num(x) for x in v)):
            raise ConfigError(f"lens.{key}", v, "[two numbers]" + (
                " (RA, Dec in degrees)" if key.endswith("radec_deg") else " (θ1, θ2 in arcsec)"))
    spec = parse_lens({k: v for k, v in t.items() if k not in _PLACEMENT_KEYS}, z_source, base)
    ra_dec = place.get("cutout_center_radec_deg")
    if ra_dec is not None and spec.center_radec_deg is None:
        raise ConfigError("lens.center_radec_deg", "<missing>", "the lens centre's [RA, Dec] "
                          "(degrees): cutout_center_radec_deg places the cutout on the sky")
    return LensModel(spec, None if ra_dec is None else tuple(map(float, ra_dec)),
                     None if "cutout_center_arcsec" not in place
                     else tuple(map(float, place["cutout_center_arcsec"])))


def parse_observation_scene(doc: dict, path: Optional[str] = None) -> ObservationScene:
    """An ObservationScene from a parsed TOML document (see the module doc)."""
    base = Path(path).resolve().parent if path else Path.cwd()
    _check_keys(doc, {"scene", "observations", "fit", "lens", "sps"}, "scene file")
    sc = doc.get("scene", {})
    _check_keys(sc, {"name", "z_source", "seed", "cosmology", "description"}, "scene")
    z = sc.get("z_source")
    if z is not None and not (_num(z) and 0 < z < 20):
        raise ConfigError("scene.z_source", z, "a redshift in (0, 20)")
    seed = sc.get("seed", 0)
    if not (isinstance(seed, int) and 0 <= seed < 2**63):
        raise ConfigError("scene.seed", seed, "an integer in [0, 2**63)")
    cosmo = sc.get("cosmology", {"H0": 70.0, "Om0": 0.3})
    obs = doc.get("observations")
    if not isinstance(obs, list) or not obs:
        raise ConfigError("observations", obs, "one [[observations]] table per band")
    specs = tuple(_observation(t, base, k) for k, t in enumerate(obs))
    names = [s.filter for s in specs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError("observations.filter", dup, "each filter once")
    fit = doc.get("fit", {})
    _check_keys(fit, {f.name for f in dataclasses.fields(FitOptions)}, "fit")
    fit = dict(fit)
    clumps = fit.get("clumps")
    if isinstance(clumps, str) and clumps not in ("auto", "none"):
        fit["clumps"] = str(base / clumps)
    options = FitOptions(**fit).validate()
    sps = doc.get("sps", {})
    if not isinstance(sps, dict):
        raise ConfigError("sps", sps, "a table of stellar-population settings")
    sps = dict(sps)
    _check_keys(sps, {"metallicity", "sfh", "sfh_duration_myr", "dust_av", "ages"}, "sps")
    cosmology = (float(cosmo.get("H0", 70.0)), float(cosmo.get("Om0", 0.3)))
    age_prior = _age_prior(sps.pop("ages", {}), z, cosmology)
    return ObservationScene(sc.get("name", Path(path).stem if path else "fit"), specs, options,
                            None if z is None else float(z), seed,
                            _lens(doc.get("lens"), None if z is None else float(z), base),
                            cosmology, path, tuple(sorted(sps.items())), age_prior)


def _age_prior(t, z, cosmology) -> tuple:
    """(slope, min_myr, max_myr) of the SED fit's age prior from `[sps] ages` (the keys of a
    simulation scene's `[source.clumps.ages]`; missing ones from `defaults.AGES`)."""
    from .. import defaults as D
    from ..cosmology import make_cosmology
    from ..population import validate_age_range

    if not isinstance(t, dict):
        raise ConfigError("sps.ages", t, "a table with slope, min_myr, max_myr")
    _check_keys(t, set(D.AGES), "sps.ages")
    slope, lo, hi = (t.get(k, D.AGES[k]) for k in ("slope", "min_myr", "max_myr"))
    validate_age_range(slope, lo, hi, prefix="sps.ages")
    if z is not None:
        universe = float(make_cosmology(*cosmology).age(float(z)).to_value("Myr"))
        if lo >= universe:
            raise ConfigError("sps.ages.min_myr", lo, f"an age below the universe's "
                              f"{universe:.0f} Myr at z_source = {z}")
    return float(slope), float(lo), float(hi)


def load_observation_scene(path: str) -> ObservationScene:
    with open(path, "rb") as fh:
        doc = tomllib.load(fh)
    return parse_observation_scene(doc, path)


def is_observation_scene(path: str) -> bool:
    """True when the TOML file at `path` has [[observations]] (False when it cannot be read)."""
    try:
        with open(path, "rb") as fh:
            return "observations" in tomllib.load(fh)
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        return False
