"""Scene files: parsing, validation, defaults, built-in scenes and what will run.

A scene (SCENE.md is the contract) is read from TOML into frozen dataclasses.
Everything is checked up front, before any computation: a wrong type, a value
out of range, a missing required key, an unknown key (with a suggestion), a
file that does not exist — each raises `ConfigError` naming the full key path
(e.g. ``bands[2].exptime_s``; band indices count from 0 in file order).

Public API::

    load_scene(name_or_path) -> Scene
    scene_from_dict(d, base_dir=None) -> Scene
    resolved_dict(scene) -> dict          # defaults filled, TOML/JSON-serialisable
    to_toml(scene_or_dict) -> str
    stages(scene) -> list[str]
    list_builtin_scenes() -> list[tuple[str, str]]
    with_overrides(scene, *, seed=None, bands=None, noise=None) -> Scene

Relative paths inside a scene (deflection maps, PSF files, clump catalogues)
resolve against the scene file's directory and are stored absolute.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

from . import defaults as D
from .errors import ConfigError

__all__ = [
    "ACCURACY_PRESETS",
    "Accuracy",
    "AgeDistribution",
    "Arms",
    "Band",
    "CMF",
    "Clumps",
    "Cosmology",
    "Deflection",
    "Disk",
    "Field",
    "INSTRUMENTS",
    "LENS_COMPONENT_PARAMS",
    "LENS_MODELS",
    "Lens",
    "LensComponent",
    "Output",
    "Render",
    "SFH",
    "Scene",
    "Sersic",
    "SizeRelation",
    "Source",
    "Texture",
    "UnknownKeyError",
    "list_builtin_scenes",
    "load_scene",
    "resolved_dict",
    "scene_from_dict",
    "stages",
    "to_toml",
    "with_overrides",
]

# ----------------------------------------------------------------------------
# Vocabularies (single place; other modules import these rather than copy them)
# ----------------------------------------------------------------------------

INSTRUMENTS = ("HST/ACS", "HST/WFC3-IR", "JWST/NIRCam")

# Filters accepted per instrument (broad, medium and narrow imaging filters).
# `instruments.py` owns throughputs and zero points; this list only catches
# typos early and is deliberately generous.
KNOWN_FILTERS = {
    "HST/ACS": (
        "F435W", "F475W", "F502N", "F550M", "F555W", "F606W", "F625W", "F658N",
        "F660N", "F775W", "F814W", "F850LP", "F892N",
    ),
    "HST/WFC3-IR": (
        "F098M", "F105W", "F110W", "F125W", "F126N", "F127M", "F128N", "F130N",
        "F132N", "F139M", "F140W", "F153M", "F160W", "F164N", "F167N",
    ),
    "JWST/NIRCam": (
        "F070W", "F090W", "F115W", "F140M", "F150W", "F150W2", "F162M", "F164N",
        "F182M", "F187N", "F200W", "F210M", "F212N", "F250M", "F277W", "F300M",
        "F322W2", "F323N", "F335M", "F356W", "F360M", "F405N", "F410M", "F430M",
        "F444W", "F460M", "F466N", "F470N", "F480M",
    ),
}

LENS_MODELS = tuple(D.BUILTIN_LENSES)

# Seeds: numpy's generators take any int >= 0, jax.random.key a signed 64-bit one.
SEED_MAX = 2**63 - 1
# AB magnitudes a scene or catalogue may give (99: the usual "no flux" sentinel); beyond
# them fluxes overflow float32 (m < ZP - 96) or are nonsense for a galaxy
AB_MAG_RANGE = (0.0, 99.0)

SIZE_RELATIONS = D.SIZE_RELATIONS

SFH_KINDS = ("constant", "burst")

# Parameters of analytic lens components: name -> (required?, kind of value), and their
# defaults; from the one registry, clumpylen_jax.defaults.LENS_KINDS (values are for the
# scene's z_source, scale = 1).
LENS_COMPONENT_PARAMS: dict[str, dict[str, tuple[bool, str]]] = {
    kind: {name: (req, vkind) for name, (req, vkind, _) in schema.items()}
    for kind, (_, schema) in D.LENS_KINDS.items()}
_LENS_PARAM_DEFAULTS = {name: default for _, schema in D.LENS_KINDS.values()
                        for name, (_, _, default) in schema.items()}

# Accuracy presets, the knobs a scene file can name: `subsampling` is the
# Gauss–Legendre order per lens-plane pixel (rays per pixel = its square; no
# node ever sits on a pixel centre, so no sample lands on a cusp),
# `psf_oversampling` the odd factor of the grid, finer than the detector, on
# which the PSF acts, `source_mode` "hybrid" (clumps away from caustics through
# the local linear lens map, the others as "grid"), "grid" (clumps on the
# source-plane grid, interpolated at each ray) or "analytic" (every clump at
# every ray), `linearise_tolerance` how far (in finest detector pixels) "hybrid"
# lets the linear map misplace a clump's image before it ray-traces the clump,
# `source_flux_fraction` the fraction of each host component's light inside the
# source-plane disc whose images are ray-traced (the rest, a faint halo, is not
# simulated: 1 % of an n = 4 bulge at 0.99; raise it towards 1 to keep it).
# The values come from clumpylen_jax.accuracy.ACCURACY_PRESETS, chosen by benchmarks/.
def _scene_presets() -> dict[str, dict[str, Any]]:
    from .accuracy import ACCURACY_PRESETS as model_presets
    return {name: {"subsampling": a.lens_subsampling, "psf_oversampling": a.psf_oversampling,
                   "source_mode": a.source_mode, "linearise_tolerance": a.linearise_tolerance,
                   "source_flux_fraction": a.source_flux_fraction}
            for name, a in model_presets.items()}


def _source_modes() -> tuple:
    from .accuracy import SOURCE_MODES as modes
    return modes


ACCURACY_PRESETS: dict[str, dict[str, Any]] = _scene_presets()
SOURCE_MODES = _source_modes()
DTYPES = ("float64", "float32")

_FILTER_RE = re.compile(r"^F\d{3}[A-Z0-9]*$")


# ----------------------------------------------------------------------------
# Dataclasses (field names are part of the Python API used by pipeline.py)
# ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Cosmology:
    """Flat ΛCDM: H0 in km/s/Mpc, Om0 the matter density today."""

    H0: float = 70.0
    Om0: float = 0.3


@dataclass(frozen=True)
class SFH:
    """Star-formation history: "constant" over duration_myr, or an instantaneous "burst" (duration None)."""

    kind: str = "constant"
    duration_myr: float | None = 100.0


@dataclass(frozen=True, kw_only=True)
class Sersic:
    """A Sérsic host component (bulge). Flux from mass_msun via SPS and/or magnitudes per band.

    magnitudes: {FILTER: AB mag}; overrides SPS for those bands. Without
    mass_msun it must cover every band.
    """

    mass_msun: float | None = None
    re_arcsec: float
    n: float
    q: float = 1.0
    pa_rad: float = 0.0
    age_myr: float = 1000.0
    metallicity: float = 0.004
    sfh: SFH = field(default_factory=SFH)
    magnitudes: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Arms:
    """Spiral modulation (Metcalf et al. 2019): I ∝ 1 + A cos(N ϑ + α ln(2β/R_h) + φ_d)."""

    count: int = 4
    amplitude: float = 1.0
    winding: float = 10.0
    phase_rad: float = 1.0
    scale_arcsec: float = 0.1
    orientation_rad: float = 0.0


@dataclass(frozen=True)
class Texture:
    """Perlin-noise perturbation of the disk: relative amplitude, base scale, octaves."""

    amplitude: float = 0.3
    scale_arcsec: float = 0.05
    octaves: int = 3


@dataclass(frozen=True, kw_only=True)
class Disk(Sersic):
    """A Sérsic disk (n = 1 by default), optionally inclined, with arms and texture."""

    inclination_rad: float = 0.0
    arms: Arms | None = None
    texture: Texture | None = None


@dataclass(frozen=True)
class CMF:
    """Clump mass function f(M) ∝ M^slope exp[-delta (M/m_cut)^gamma] on [m_min, m_max]."""

    slope: float = D.CMF["slope"]
    m_cut_msun: float = D.CMF["m_cut_msun"]
    delta: float = D.CMF["delta"]
    gamma: float = D.CMF["gamma"]
    m_min_msun: float = D.CMF["m_min_msun"]
    m_max_msun: float = D.CMF["m_max_msun"]


@dataclass(frozen=True)
class SizeRelation:
    """Clump mass–size relation with a lognormal scatter (natural-log sigma)."""

    relation: str = D.SIZE["relation"]
    scatter_ln: float = D.SIZE["scatter_ln"]


@dataclass(frozen=True)
class AgeDistribution:
    """Clump ages: dN/dt ∝ t^slope on [min_myr, max_myr]."""

    slope: float = D.AGES["slope"]
    min_myr: float = D.AGES["min_myr"]
    max_myr: float = D.AGES["max_myr"]


@dataclass(frozen=True)
class Clumps:
    """Stellar clumps: sampled (mass budget = mass_fraction × host mass) or read from `catalog`."""

    mass_fraction: float = D.CLUMPS["mass_fraction"]
    host: str = D.CLUMPS["host"]
    cmf: CMF = field(default_factory=CMF)
    size: SizeRelation = field(default_factory=SizeRelation)
    ages: AgeDistribution = field(default_factory=AgeDistribution)
    sfh: SFH = field(default_factory=lambda: SFH(D.CLUMPS["sfh_kind"], D.CLUMPS["sfh_duration_myr"]))
    metallicity: float = D.CLUMPS["metallicity"]
    sersic_n: float = D.CLUMPS["sersic_n"]
    q_range: tuple[float, float] = D.CLUMPS["q_range"]
    catalog: str | None = None  # absolute path


@dataclass(frozen=True)
class Source:
    """The galaxy: centre β (arcsec, relative to the lens centre) and its components."""

    center_arcsec: tuple[float, float] = (0.0, 0.0)
    bulge: Sersic | None = None
    disk: Disk | None = None
    clumps: Clumps | None = None


@dataclass(frozen=True)
class Deflection:
    """Deflection maps (FITS, arcsec). Normalised to D_ls/D_s = 1 unless
    normalization_z_source is set: then they are the deflections for a source at that redshift."""

    x: str
    y: str
    normalization_z_source: float | None = None


@dataclass(frozen=True)
class LensComponent:
    """One analytic lens: kind in LENS_COMPONENT_PARAMS, params with defaults filled."""

    kind: str
    params: dict[str, Any]


@dataclass(frozen=True)
class Lens:
    """The lens: exactly one of deflection / model / components is set."""

    z_lens: float
    center_radec_deg: tuple[float, float] | None = None
    deflection: Deflection | None = None
    model: str | None = None
    components: tuple[LensComponent, ...] = ()


@dataclass(frozen=True)
class Field:
    """Lens-plane (or, unlensed, source-plane) field: θ ranges in arcsec from the reference."""

    x: tuple[float, float]
    y: tuple[float, float]


@dataclass(frozen=True)
class Accuracy:
    """Resolved accuracy knobs; `preset` is the preset they start from."""

    preset: str = D.ACCURACY_PRESET
    subsampling: int = ACCURACY_PRESETS[D.ACCURACY_PRESET]["subsampling"]
    psf_oversampling: int = ACCURACY_PRESETS[D.ACCURACY_PRESET]["psf_oversampling"]
    source_mode: str = ACCURACY_PRESETS[D.ACCURACY_PRESET]["source_mode"]
    linearise_tolerance: float = ACCURACY_PRESETS[D.ACCURACY_PRESET]["linearise_tolerance"]
    source_flux_fraction: float = ACCURACY_PRESETS[D.ACCURACY_PRESET]["source_flux_fraction"]


@dataclass(frozen=True)
class Render:
    """Resolutions (arcsec/pixel), lens-plane field, accuracy knobs, dtype."""

    source_pixel_arcsec: float = D.SOURCE_PIXEL_ARCSEC
    lens_pixel_arcsec: float = D.LENS_PIXEL_ARCSEC
    field_arcsec: Field | None = None
    accuracy: Accuracy = field(default_factory=Accuracy)
    dtype: str = D.DTYPE


@dataclass(frozen=True)
class Band:
    """One observed band. psf: "none", "diffraction" or an absolute path to a FITS PSF.

    psf_effective: the PSF already includes the pixel response (do not
    integrate over detector pixels again). pixel_arcsec and zeropoint_ab are
    filled from clumpylen_jax.instruments when absent (None if unavailable).
    """

    instrument: str
    filter: str
    exptime_s: float | None = None
    sky_counts_per_s: float = 0.0
    pixel_arcsec: float | None = None
    zeropoint_ab: float | None = None
    psf: str = "diffraction"
    psf_pixel_arcsec: float | None = None
    psf_effective: bool = False

    @property
    def telescope(self) -> str:
        """"HST" or "JWST"."""
        return self.instrument.split("/")[0]

    @property
    def camera(self) -> str:
        """"ACS", "WFC3-IR" or "NIRCam"."""
        return self.instrument.split("/")[1]


@dataclass(frozen=True)
class Output:
    """What to write: noise, unlensed images, RGB composites, high-resolution images."""

    noise: bool = True
    unlensed: bool = True
    rgb: tuple[tuple[str, str, str], ...] = ()
    hr_rgb_um: tuple[float, float, float] | None = None
    hr: bool = True


@dataclass(frozen=True)
class Scene:
    """A validated scene. `path`/`base_dir` say where it came from (not compared)."""

    name: str
    z_source: float
    source: Source
    bands: tuple[Band, ...]
    seed: int = 0
    description: str = ""
    cosmology: Cosmology = field(default_factory=Cosmology)
    lens: Lens | None = None
    render: Render = field(default_factory=Render)
    output: Output = field(default_factory=Output)
    path: str | None = field(default=None, compare=False)
    base_dir: str | None = field(default=None, compare=False)

    @property
    def band_names(self) -> tuple[str, ...]:
        """Filter names of the bands, in file order."""
        return tuple(b.filter for b in self.bands)

    def band(self, filter_name: str) -> Band:
        """The band observed through `filter_name`."""
        for b in self.bands:
            if b.filter == filter_name.upper():
                return b
        raise ConfigError("band", filter_name, f"one of {', '.join(self.band_names)}")


# ----------------------------------------------------------------------------
# Errors
# ----------------------------------------------------------------------------


class UnknownKeyError(ConfigError):
    """A key the scene format does not have; the message suggests the nearest valid one."""

    def __init__(self, setting: str, key: str, valid):
        valid = sorted(valid)
        near = difflib.get_close_matches(key, valid, n=1, cutoff=0.6)
        super().__init__(setting, key, "one of: " + ", ".join(valid))
        hint = f"did you mean '{near[0]}'?" if near else "valid keys: " + ", ".join(valid)
        self.suggestion = near[0] if near else None
        self.args = (f"unknown key '{setting}'; {hint}",)


# ----------------------------------------------------------------------------
# Small typed readers. `path` is the key path of the table being read.
# ----------------------------------------------------------------------------

_REQUIRED = object()


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _table(value, path: str) -> dict:
    if not isinstance(value, dict):
        raise ConfigError(path, value, "a table")
    return value


def _check_keys(d: dict, path: str, allowed) -> None:
    for key in d:
        if key not in allowed:
            raise UnknownKeyError(_join(path, key), key, allowed)


def _missing(d: dict, key: str, path: str, expected: str):
    raise ConfigError(_join(path, key), "<missing>", f"{expected} (required)")


def _is_number(v) -> bool:
    # bool is an int in Python; a scene's `true` is never a number.
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _float(d, key, path, default=_REQUIRED, *, lo=None, hi=None, lo_open=False, hi_open=False,
           expected=None):
    """Read a finite number in [lo, hi] (open ends where asked); None default allowed."""
    setting = _join(path, key)
    if key not in d:
        if default is _REQUIRED:
            _missing(d, key, path, expected or "a number")
        return default
    v = d[key]
    lo_s = "" if lo is None else (f"> {lo}" if lo_open else f">= {lo}")
    hi_s = "" if hi is None else (f"< {hi}" if hi_open else f"<= {hi}")
    exp = expected or "a number" + (" " + " and ".join(s for s in (lo_s, hi_s) if s) if lo_s or hi_s else "")
    if not _is_number(v) or not math.isfinite(v):
        raise ConfigError(setting, v, exp)
    v = float(v)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise ConfigError(setting, v, exp)
    if hi is not None and (v > hi or (hi_open and v == hi)):
        raise ConfigError(setting, v, exp)
    return v


def _int(d, key, path, default=_REQUIRED, *, lo=None, hi=None):
    setting = _join(path, key)
    if key not in d:
        if default is _REQUIRED:
            _missing(d, key, path, "an integer")
        return default
    v = d[key]
    exp = "an integer" + (f" >= {lo}" if lo is not None else "") + (f" <= {hi}" if hi is not None else "")
    if isinstance(v, bool) or not isinstance(v, int):
        raise ConfigError(setting, v, exp)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ConfigError(setting, v, exp)
    return v


def _bool(d, key, path, default):
    if key not in d:
        return default
    v = d[key]
    if not isinstance(v, bool):
        raise ConfigError(_join(path, key), v, "true or false")
    return v


def _choice(d, key, path, choices, default=_REQUIRED):
    setting = _join(path, key)
    exp = "one of " + ", ".join(f'"{c}"' for c in choices)
    if key not in d:
        if default is _REQUIRED:
            _missing(d, key, path, exp)
        return default
    v = d[key]
    if not isinstance(v, str) or v not in choices:
        near = difflib.get_close_matches(str(v), choices, n=1, cutoff=0.5)
        raise ConfigError(setting, v, exp + (f" (did you mean \"{near[0]}\"?)" if near else ""))
    return v


def _str(d, key, path, default=_REQUIRED):
    if key not in d:
        if default is _REQUIRED:
            _missing(d, key, path, "a string")
        return default
    v = d[key]
    if not isinstance(v, str):
        raise ConfigError(_join(path, key), v, "a string")
    return v


def _pair(d, key, path, default=_REQUIRED, *, increasing=False):
    """Two finite numbers [a, b] (a < b if increasing)."""
    setting = _join(path, key)
    if key not in d:
        if default is _REQUIRED:
            _missing(d, key, path, "a pair of numbers [a, b]")
        return default
    v = d[key]
    exp = "a pair of numbers [a, b]" + (" with a < b" if increasing else "")
    if (not isinstance(v, (list, tuple)) or len(v) != 2
            or not all(_is_number(x) and math.isfinite(x) for x in v)):
        raise ConfigError(setting, v, exp)
    a, b = float(v[0]), float(v[1])
    if increasing and not a < b:
        raise ConfigError(setting, v, exp)
    return (a, b)


def _file(d, key, path, base_dir: str | None, default=_REQUIRED) -> str | None:
    """A path to an existing file, resolved against the scene's directory."""
    p = _str(d, key, path, default)
    if p is None:
        return None
    return _existing_file(p, _join(path, key), base_dir)


def _existing_file(p: str, setting: str, base_dir: str | None) -> str:
    full = os.path.expanduser(p)
    if not os.path.isabs(full):
        full = os.path.join(base_dir or os.getcwd(), full)
    full = os.path.normpath(full)
    if not os.path.isfile(full):
        raise ConfigError(setting, p, f"an existing file (looked for {full})")
    return full


def _filter_name(v, setting: str) -> str:
    if not isinstance(v, str) or not _FILTER_RE.match(v.upper()):
        raise ConfigError(setting, v, 'a filter name such as "F115W"')
    return v.upper()


# ----------------------------------------------------------------------------
# Section parsers
# ----------------------------------------------------------------------------

_SFH_KEYS = ("kind", "duration_myr")


def _sfh(d, key, path, default: SFH) -> SFH:
    if key not in d:
        return default
    p = _join(path, key)
    t = _table(d[key], p)
    _check_keys(t, p, _SFH_KEYS)
    kind = _choice(t, "kind", p, SFH_KINDS, default="constant")
    if kind == "burst":
        if "duration_myr" in t:
            raise ConfigError(_join(p, "duration_myr"), t["duration_myr"],
                              'no duration for kind = "burst" (an instantaneous burst)')
        return SFH("burst", None)
    dflt = default.duration_myr if default.kind == "constant" else _REQUIRED
    return SFH("constant", _float(t, "duration_myr", p, dflt, lo=0, lo_open=True))


_SERSIC_KEYS = ("mass_msun", "re_arcsec", "n", "q", "pa_rad", "age_myr", "metallicity", "sfh", "magnitudes")
_DISK_KEYS = _SERSIC_KEYS + ("inclination_rad", "arms", "texture")


def _sersic_fields(t: dict, p: str, *, n_default: float, age_default: float, band_names) -> dict:
    mags = {}
    if "magnitudes" in t:
        mp = _join(p, "magnitudes")
        mt = _table(t["magnitudes"], mp)
        for k, v in mt.items():
            name = _filter_name(k, _join(mp, k))
            if name not in band_names:
                near = difflib.get_close_matches(name, band_names, n=1, cutoff=0.6)
                raise ConfigError(_join(mp, k), v, "a magnitude for one of the bands ("
                                  + ", ".join(band_names) + ")"
                                  + (f"; did you mean '{near[0]}'?" if near else ""))
            lo, hi = AB_MAG_RANGE
            mags[name] = _float(mt, k, mp, lo=lo, hi=hi,
                                expected=f"an AB magnitude in [{lo:g}, {hi:g}]")
    mass = _float(t, "mass_msun", p, None, lo=0, hi=1e13)   # above any galaxy: overflows
    if mass is None:
        missing = [b for b in band_names if b not in mags]
        if missing:
            raise ConfigError(_join(p, "mass_msun"), "<missing>",
                              "a stellar mass (for SPS) or magnitudes for every band; no magnitude for "
                              + ", ".join(missing))
    return dict(
        re_arcsec=_float(t, "re_arcsec", p, lo=0, lo_open=True, expected="a number > 0 (arcsec)"),
        n=_float(t, "n", p, n_default, lo=0.2, hi=10),
        q=_float(t, "q", p, 1.0, lo=0, hi=1, lo_open=True),
        pa_rad=_float(t, "pa_rad", p, 0.0),
        mass_msun=mass,
        age_myr=_float(t, "age_myr", p, age_default, lo=0, lo_open=True),
        metallicity=_float(t, "metallicity", p, 0.004, lo=0, lo_open=True, hi=0.1),
        sfh=_sfh(t, "sfh", p, SFH("constant", 100.0)),
        magnitudes=mags,
    )


def _bulge(t, p, band_names) -> Sersic:
    t = _table(t, p)
    _check_keys(t, p, _SERSIC_KEYS)
    return Sersic(**_sersic_fields(t, p, n_default=4.0, age_default=1000.0, band_names=band_names))


_ARMS_KEYS = ("count", "amplitude", "winding", "phase_rad", "scale_arcsec", "orientation_rad")
_TEXTURE_KEYS = ("amplitude", "scale_arcsec", "octaves")


def _disk(t, p, band_names) -> Disk:
    t = _table(t, p)
    _check_keys(t, p, _DISK_KEYS)
    f = _sersic_fields(t, p, n_default=1.0, age_default=500.0, band_names=band_names)
    arms = texture = None
    if "arms" in t:
        ap = _join(p, "arms")
        a = _table(t["arms"], ap)
        _check_keys(a, ap, _ARMS_KEYS)
        arms = Arms(
            count=_int(a, "count", ap, 4, lo=1),
            amplitude=_float(a, "amplitude", ap, 1.0, lo=0),
            winding=_float(a, "winding", ap, 10.0),
            phase_rad=_float(a, "phase_rad", ap, 1.0),
            # The paper's R_h: by default the exponential scale length R_e/1.678.
            scale_arcsec=_float(a, "scale_arcsec", ap, f["re_arcsec"] / 1.678, lo=0, lo_open=True),
            orientation_rad=_float(a, "orientation_rad", ap, 0.0),
        )
    if "texture" in t:
        tp = _join(p, "texture")
        x = _table(t["texture"], tp)
        _check_keys(x, tp, _TEXTURE_KEYS)
        texture = Texture(
            amplitude=_float(x, "amplitude", tp, 0.3, lo=0),
            scale_arcsec=_float(x, "scale_arcsec", tp, 0.05, lo=0, lo_open=True),
            octaves=_int(x, "octaves", tp, 3, lo=1, hi=12),
        )
    incl = _float(t, "inclination_rad", p, 0.0, lo=0, hi=math.pi / 2, hi_open=True)
    return Disk(**f, inclination_rad=incl, arms=arms, texture=texture)


_CLUMPS_KEYS = ("mass_fraction", "host", "cmf", "size", "ages", "sfh", "metallicity", "sersic_n",
                "q_range", "catalog")
_CMF_KEYS = ("slope", "m_cut_msun", "delta", "gamma", "m_min_msun", "m_max_msun")


def _clumps(t, p, source_tables: dict, base_dir, band_names) -> Clumps:
    t = _table(t, p)
    _check_keys(t, p, _CLUMPS_KEYS)
    cmf = CMF()
    if "cmf" in t:
        cp = _join(p, "cmf")
        c = _table(t["cmf"], cp)
        _check_keys(c, cp, _CMF_KEYS)
        cmf = CMF(
            slope=_float(c, "slope", cp, cmf.slope),
            m_cut_msun=_float(c, "m_cut_msun", cp, cmf.m_cut_msun, lo=0, lo_open=True),
            delta=_float(c, "delta", cp, cmf.delta, lo=0),
            gamma=_float(c, "gamma", cp, cmf.gamma, lo=0, lo_open=True),
            m_min_msun=_float(c, "m_min_msun", cp, cmf.m_min_msun, lo=0, lo_open=True),
            m_max_msun=_float(c, "m_max_msun", cp, cmf.m_max_msun, lo=0, lo_open=True),
        )
        if not cmf.m_min_msun < cmf.m_max_msun:
            raise ConfigError(_join(cp, "m_max_msun"), cmf.m_max_msun, f"> m_min_msun = {cmf.m_min_msun}")
    size = SizeRelation()
    if "size" in t:
        sp = _join(p, "size")
        s = _table(t["size"], sp)
        _check_keys(s, sp, ("relation", "scatter_ln"))
        size = SizeRelation(_choice(s, "relation", sp, SIZE_RELATIONS, size.relation),
                            _float(s, "scatter_ln", sp, size.scatter_ln, lo=0))
    ages = AgeDistribution()
    if "ages" in t:
        gp = _join(p, "ages")
        g = _table(t["ages"], gp)
        _check_keys(g, gp, ("slope", "min_myr", "max_myr"))
        ages = AgeDistribution(_float(g, "slope", gp, ages.slope),
                               _float(g, "min_myr", gp, ages.min_myr, lo=0, lo_open=True),
                               _float(g, "max_myr", gp, ages.max_myr, lo=0, lo_open=True))
        if not ages.min_myr < ages.max_myr:   # the age power law needs a range
            raise ConfigError(_join(gp, "max_myr"), ages.max_myr, f"> min_myr = {ages.min_myr}")
    dflt = Clumps()
    q_range = _pair(t, "q_range", p, dflt.q_range)
    if not 0 < q_range[0] <= q_range[1] <= 1:
        raise ConfigError(_join(p, "q_range"), list(q_range), "[q_min, q_max] with 0 < q_min <= q_max <= 1")
    catalog = _file(t, "catalog", p, base_dir, None)
    host = _choice(t, "host", p, ("disk", "bulge"), dflt.host)
    if catalog is None:
        # Sampling needs a host: its light places the clumps and its mass sets the budget.
        if host not in source_tables:
            raise ConfigError(_join(p, "host"), host, f"a component present in [source] (no [source.{host}])")
        if "mass_msun" not in _table(source_tables[host], _join("source", host)):
            raise ConfigError(_join(p, "host"), host,
                              "a host with mass_msun (the clump mass budget), or clumps.catalog")
    else:
        _check_catalog(catalog, _join(p, "catalog"), band_names)
    return Clumps(
        mass_fraction=_float(t, "mass_fraction", p, dflt.mass_fraction, lo=0, hi=1),
        host=host, cmf=cmf, size=size, ages=ages,
        sfh=_sfh(t, "sfh", p, dflt.sfh),
        metallicity=_float(t, "metallicity", p, dflt.metallicity, lo=0, lo_open=True, hi=0.1),
        sersic_n=_float(t, "sersic_n", p, dflt.sersic_n, lo=0.2, hi=10),
        q_range=q_range,
        catalog=catalog,
    )


def _check_catalog(path: str, setting: str, band_names) -> None:
    """A clump catalogue must give positions, sizes, and a flux route per band.

    Flux per band: a mag_<FILTER> column, or mass_msun + age_myr for SPS.
    Other columns pass through untouched.
    """
    # the reader `simulate` uses, so that `validate` refuses what it would (missing q, CSV,
    # NaN, magnitudes out of range); arcsec_per_pc = 1 stands in for the cosmology here,
    # which only converts re_pc
    from .population import read_clump_catalog  # lazy: astropy is slow to import

    read_clump_catalog(path, arcsec_per_pc=1.0, bands=list(band_names), setting=setting)


_SOURCE_KEYS = ("center_arcsec", "bulge", "disk", "clumps")


def _source(t, base_dir, band_names) -> Source:
    p = "source"
    t = _table(t, p)
    _check_keys(t, p, _SOURCE_KEYS)
    bulge = _bulge(t["bulge"], "source.bulge", band_names) if "bulge" in t else None
    disk = _disk(t["disk"], "source.disk", band_names) if "disk" in t else None
    clumps = _clumps(t["clumps"], "source.clumps", t, base_dir, band_names) if "clumps" in t else None
    if bulge is None and disk is None and clumps is None:
        raise ConfigError("source", t, "at least one of [source.bulge], [source.disk], [source.clumps]")
    return Source(center_arcsec=_pair(t, "center_arcsec", p, (0.0, 0.0)), bulge=bulge, disk=disk, clumps=clumps)


_LENS_KEYS = ("z_lens", "center_radec_deg", "deflection", "model", "components")


def parse_lens(t, z_source: float, base_dir) -> Lens:
    """The `[lens]` table of a scene (z_lens, center_radec_deg and one of deflection / model /
    components) as a `Lens`; relative map paths are resolved against base_dir."""
    p = "lens"
    t = _table(t, p)
    _check_keys(t, p, _LENS_KEYS)
    z_lens = _float(t, "z_lens", p, lo=0, expected="a redshift >= 0")
    if not z_source > z_lens:
        raise ConfigError("lens.z_lens", z_lens, f"< scene.z_source = {z_source} (the source behind the lens)")
    center = None
    if "center_radec_deg" in t:
        center = _pair(t, "center_radec_deg", p)
        if not (0 <= center[0] < 360 and -90 <= center[1] <= 90):
            raise ConfigError("lens.center_radec_deg", list(center), "[RA in [0, 360), Dec in [-90, 90]] degrees")
    given = [k for k in ("deflection", "model", "components") if k in t]
    if len(given) != 1:
        raise ConfigError("lens", given or "<none>", "exactly one of deflection, model, components")
    deflection, model, components = None, None, ()
    if "deflection" in t:
        dp = "lens.deflection"
        d = _table(t["deflection"], dp)
        _check_keys(d, dp, ("x", "y", "normalization"))
        norm_z = None
        if "normalization" in d:
            v = d["normalization"]
            np_ = _join(dp, "normalization")
            if isinstance(v, dict):
                _check_keys(v, np_, ("z_source",))
                norm_z = _float(v, "z_source", np_, lo=0, lo_open=True)
                if not norm_z > z_lens:
                    raise ConfigError(_join(np_, "z_source"), norm_z, f"> lens.z_lens = {z_lens}")
            elif v != "dls_ds":
                raise ConfigError(np_, v, '"dls_ds" or { z_source = <redshift the maps were made for> }')
        deflection = Deflection(x=_file(d, "x", dp, base_dir), y=_file(d, "y", dp, base_dir),
                                normalization_z_source=norm_z)
        if center is None:
            # The maps carry a WCS; the θ frame needs the sky position of its origin.
            raise ConfigError("lens.center_radec_deg", "<missing>",
                              "[RA, Dec] in degrees of the lens centre (required with deflection maps)")
    elif "model" in t:
        model = _choice(t, "model", p, LENS_MODELS)
    else:
        v = t["components"]
        if not isinstance(v, list) or not v:
            raise ConfigError("lens.components", v, "a non-empty list of tables { kind = ..., ... }")
        components = tuple(_lens_component(c, f"lens.components[{i}]") for i, c in enumerate(v))
    return Lens(z_lens=z_lens, center_radec_deg=center, deflection=deflection, model=model,
                components=components)


def _lens_component(c, p) -> LensComponent:
    c = _table(c, p)
    kind = _choice(c, "kind", p, tuple(LENS_COMPONENT_PARAMS))
    schema = LENS_COMPONENT_PARAMS[kind]
    _check_keys(c, p, ("kind",) + tuple(schema))
    params = {}
    for name, (required, vkind) in schema.items():
        default = _REQUIRED if required else _LENS_PARAM_DEFAULTS[name]
        if vkind == "pair":
            params[name] = _pair(c, name, p, default)
        elif vkind == "pos":
            params[name] = _float(c, name, p, default, lo=0, lo_open=True)
        elif vkind == "nonneg":
            params[name] = _float(c, name, p, default, lo=0)
        elif vkind == "q":
            params[name] = _float(c, name, p, default, lo=0, hi=1, lo_open=True)
        else:
            params[name] = _float(c, name, p, default)
    if kind == "dpie":
        if not params["rcore_arcsec"] < params["rcut_arcsec"]:
            raise ConfigError(_join(p, "rcut_arcsec"), params["rcut_arcsec"], "> rcore_arcsec")
        if (params["b0_arcsec"] is None) == (params["sigma0_kms"] is None):
            raise ConfigError(p, c, "exactly one of b0_arcsec (arcsec) or sigma0_kms (km/s)")
    params = {k: v for k, v in params.items() if v is not None}
    return LensComponent(kind=kind, params=params)


_RENDER_KEYS = ("source_pixel_arcsec", "lens_pixel_arcsec", "field_arcsec", "accuracy", "dtype")
_ACCURACY_KEYS = ("preset", "subsampling", "psf_oversampling", "source_mode",
                  "linearise_tolerance", "source_flux_fraction", "dtype")


def _render(t) -> Render:
    p = "render"
    t = _table(t, p)
    _check_keys(t, p, _RENDER_KEYS)
    fld = None
    if "field_arcsec" in t:
        fp = "render.field_arcsec"
        f = _table(t["field_arcsec"], fp)
        _check_keys(f, fp, ("x", "y"))
        fld = Field(x=_pair(f, "x", fp, increasing=True), y=_pair(f, "y", fp, increasing=True))
    dtype = _choice(t, "dtype", p, DTYPES, None)
    acc_value = t.get("accuracy", D.ACCURACY_PRESET)
    ap = "render.accuracy"
    if isinstance(acc_value, dict):
        a = acc_value
        _check_keys(a, ap, _ACCURACY_KEYS)
        preset = _choice(a, "preset", ap, tuple(ACCURACY_PRESETS), D.ACCURACY_PRESET)
        base = ACCURACY_PRESETS[preset]
        acc = Accuracy(
            preset=preset,
            subsampling=_int(a, "subsampling", ap, base["subsampling"], lo=1, hi=64),
            psf_oversampling=_int(a, "psf_oversampling", ap, base["psf_oversampling"], lo=1, hi=15),
            source_mode=_choice(a, "source_mode", ap, SOURCE_MODES, base["source_mode"]),
            linearise_tolerance=_float(a, "linearise_tolerance", ap, base["linearise_tolerance"],
                                       lo=0, expected="a fraction of a detector pixel >= 0 "
                                       "(0 ray-traces every clump)"),
            source_flux_fraction=_float(a, "source_flux_fraction", ap,
                                        base["source_flux_fraction"], lo=0.5, hi=1.0,
                                        hi_open=True, expected="a light fraction in [0.5, 1)"),
        )
        if acc.psf_oversampling % 2 == 0:
            raise ConfigError(f"{ap}.psf_oversampling", acc.psf_oversampling,
                              "an odd integer (detector pixel centres fall on sub-pixel centres)")
        acc_dtype = _choice(a, "dtype", ap, DTYPES, None)
        if acc_dtype is not None:
            if dtype is not None and dtype != acc_dtype:
                raise ConfigError("render.accuracy.dtype", acc_dtype, f'the same as render.dtype = "{dtype}"')
            dtype = acc_dtype
    else:
        preset = _choice(t, "accuracy", p, tuple(ACCURACY_PRESETS), D.ACCURACY_PRESET)
        acc = Accuracy(preset=preset, **ACCURACY_PRESETS[preset])
    return Render(
        source_pixel_arcsec=_float(t, "source_pixel_arcsec", p, D.SOURCE_PIXEL_ARCSEC, lo=0, lo_open=True),
        lens_pixel_arcsec=_float(t, "lens_pixel_arcsec", p, D.LENS_PIXEL_ARCSEC, lo=0, lo_open=True),
        field_arcsec=fld,
        accuracy=acc,
        dtype=dtype or D.DTYPE,
    )


_BAND_KEYS = ("instrument", "filter", "exptime_s", "sky_counts_per_s", "pixel_arcsec", "zeropoint_ab",
              "psf", "psf_pixel_arcsec", "psf_effective")


def _instrument_defaults(instrument: str, filter_name: str, setting: str) -> dict:
    """pixel_arcsec and zeropoint_ab from clumpylen_jax.instruments, if that module exists."""
    try:
        from .instruments import band_defaults
    except ImportError:
        return {}
    try:
        return dict(band_defaults(instrument, filter_name))
    except (KeyError, ConfigError) as exc:
        # Re-raise under the band's own key path, which the user can find in the file.
        raise ConfigError(setting, filter_name, f"a filter with a throughput curve for {instrument}"
                          " (or give pixel_arcsec and zeropoint_ab)") from exc


def _band(t, i: int, base_dir, noise: bool, path: str | None = None) -> Band:
    p = path or f"bands[{i}]"
    t = _table(t, p)
    _check_keys(t, p, _BAND_KEYS)
    instrument = _choice(t, "instrument", p, INSTRUMENTS)
    fp = _join(p, "filter")
    filt = _filter_name(_str(t, "filter", p), fp)
    if filt not in KNOWN_FILTERS[instrument]:
        near = difflib.get_close_matches(filt, KNOWN_FILTERS[instrument], n=1, cutoff=0.6)
        raise ConfigError(fp, t["filter"], f"a filter of {instrument}" + (f" (did you mean '{near[0]}'?)" if near else ""))
    # beyond these, counts/s variances (counts / t²) leave float32
    exptime = _float(t, "exptime_s", p, None, lo=1e-3, hi=1e9)
    if noise and exptime is None:
        _missing(t, "exptime_s", p, "an exposure time in s > 0 (needed for noise; or set output.noise = false)")
    psf = _str(t, "psf", p, "diffraction")
    if psf not in ("none", "diffraction"):
        psf = _existing_file(psf, _join(p, "psf"), base_dir)
    pixel = _float(t, "pixel_arcsec", p, None, lo=0, lo_open=True)
    zp = _float(t, "zeropoint_ab", p, None, lo=0, hi=50)
    if pixel is None or zp is None:
        dflt = _instrument_defaults(instrument, filt, fp)
        pixel = pixel if pixel is not None else dflt.get("pixel_arcsec")
        zp = zp if zp is not None else dflt.get("zeropoint_ab")
    return Band(
        instrument=instrument, filter=filt, exptime_s=exptime,
        sky_counts_per_s=_float(t, "sky_counts_per_s", p, 0.0, lo=0, hi=1e6),
        pixel_arcsec=None if pixel is None else float(pixel),
        zeropoint_ab=None if zp is None else float(zp),
        psf=psf,
        psf_pixel_arcsec=_float(t, "psf_pixel_arcsec", p, None, lo=0, lo_open=True),
        psf_effective=_bool(t, "psf_effective", p, False),
    )


_OUTPUT_KEYS = ("noise", "unlensed", "rgb", "hr_rgb_um", "hr")


def _output(t, band_names) -> Output:
    p = "output"
    t = _table(t, p)
    _check_keys(t, p, _OUTPUT_KEYS)
    if "rgb" in t and not isinstance(t["rgb"], list):
        raise ConfigError("output.rgb", t["rgb"], "a list of [R, G, B] filter triples")
    rgb = []
    for i, triple in enumerate(t.get("rgb", [])):
        tp = f"output.rgb[{i}]"
        if not isinstance(triple, list) or len(triple) != 3:
            raise ConfigError(tp, triple, '[R, G, B] filter names, e.g. ["F200W", "F150W", "F115W"]')
        names = tuple(_filter_name(x, tp) for x in triple)
        for x in names:
            if x not in band_names:
                raise ConfigError(tp, triple, "filters among the [[bands]]: " + ", ".join(band_names)
                                  + f" (no band {x})")
        rgb.append(names)
    hr_rgb = None
    if "hr_rgb_um" in t:
        v = t["hr_rgb_um"]
        if (not isinstance(v, list) or len(v) != 3
                or not all(_is_number(x) and math.isfinite(x) and x > 0 for x in v)):
            raise ConfigError("output.hr_rgb_um", v, "[red, green, blue] wavelengths in μm, each > 0")
        hr_rgb = tuple(float(x) for x in v)
    return Output(noise=_bool(t, "noise", p, True), unlensed=_bool(t, "unlensed", p, True),
                  rgb=tuple(rgb), hr_rgb_um=hr_rgb, hr=_bool(t, "hr", p, True))


_TOP_KEYS = ("scene", "source", "lens", "render", "bands", "output")
_SCENE_KEYS = ("name", "description", "seed", "z_source", "cosmology")


def scene_from_dict(d: dict, base_dir: str | os.PathLike | None = None, *, path: str | None = None) -> Scene:
    """Validate a parsed scene (nested dicts as from tomllib) and build a Scene.

    base_dir: the directory relative file paths resolve against (default: the
    current directory). Raises ConfigError naming the first bad setting.
    """
    d = _table(d, "<scene>")
    _check_keys(d, "", _TOP_KEYS)
    base_dir = None if base_dir is None else os.fspath(base_dir)
    if "scene" not in d:
        raise ConfigError("scene", "<missing>", "a [scene] table with z_source (required)")
    s = _table(d["scene"], "scene")
    _check_keys(s, "scene", _SCENE_KEYS)
    z_source = _float(s, "z_source", "scene", lo=0, hi=30, lo_open=True,
                      expected="a redshift in (0, 30]")
    cosmo = Cosmology()
    if "cosmology" in s:
        c = _table(s["cosmology"], "scene.cosmology")
        _check_keys(c, "scene.cosmology", ("H0", "Om0"))
        cosmo = Cosmology(H0=_float(c, "H0", "scene.cosmology", 70.0, lo=0, lo_open=True),
                          Om0=_float(c, "Om0", "scene.cosmology", 0.3, lo=0, hi=1, lo_open=True))

    # Bands first: magnitudes, rgb and catalogue checks refer to their names.
    out_t = _table(d.get("output", {}), "output")
    noise = _bool(out_t, "noise", "output", True)
    bands_v = d.get("bands")
    if not isinstance(bands_v, list) or not bands_v:
        raise ConfigError("bands", "<missing>" if bands_v is None else bands_v,
                          "at least one [[bands]] table (required)")
    bands = tuple(_band(b, i, base_dir, noise) for i, b in enumerate(bands_v))
    seen = {}
    for i, b in enumerate(bands):
        if b.filter in seen:
            raise ConfigError(f"bands[{i}].filter", b.filter,
                              f"a filter not already used by bands[{seen[b.filter]}] (output files are named by filter)")
        seen[b.filter] = i
    band_names = tuple(seen)

    if "source" not in d:
        raise ConfigError("source", "<missing>", "a [source] table with a bulge, disk or clumps (required)")
    source = _source(d["source"], base_dir, band_names)
    lens = parse_lens(d["lens"], z_source, base_dir) if "lens" in d else None
    render = _render(d.get("render", {}))
    output = _output(out_t, band_names)

    name = _str(s, "name", "scene", None)
    if name is None:
        name = os.path.splitext(os.path.basename(path))[0] if path else "scene"
    return Scene(
        name=name, description=_str(s, "description", "scene", ""),
        seed=_int(s, "seed", "scene", 0, lo=0, hi=SEED_MAX), z_source=z_source, cosmology=cosmo,
        source=source, lens=lens, render=render, bands=bands, output=output,
        path=path, base_dir=base_dir,
    )


# ----------------------------------------------------------------------------
# Loading and built-in scenes
# ----------------------------------------------------------------------------


def _builtin_dir():
    return resources.files("clumpylen_jax") / "scenes"


def _builtin_names() -> list[str]:
    return sorted(p.name[:-5] for p in _builtin_dir().iterdir() if p.name.endswith(".toml"))


def builtin_scene_text(name: str) -> str:
    """The TOML text (with its comments) of a built-in scene."""
    if name not in _builtin_names():
        raise _unknown_scene(name)
    return (_builtin_dir() / f"{name}.toml").read_text(encoding="utf-8")


def _unknown_scene(name: str) -> ConfigError:
    names = _builtin_names()
    near = difflib.get_close_matches(name, names, n=1, cutoff=0.5)
    exp = "a built-in scene (" + ", ".join(names) + ") or a path to a .toml file"
    if near:
        exp += f"; did you mean '{near[0]}'?"
    return ConfigError("scene", name, exp)


def _scene_text(data: bytes, name: str) -> str:
    """A scene file's bytes as text: UTF-8 (TOML's encoding), with a leading BOM dropped."""
    if data.startswith(b"\xef\xbb\xbf"):   # editors on Windows write one; TOML has none
        data = data[3:]
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise ConfigError("scene file", name, f"UTF-8 text (byte 0x{data[exc.start]:02x} on line "
                          f"{line} is not UTF-8: save the file as UTF-8)") from exc


def load_scene(name_or_path: str | os.PathLike) -> Scene:
    """Load a scene: an existing file path, else a built-in scene name.

    Raises FileNotFoundError for a path (something with a '/' or '.toml')
    that does not exist, ConfigError for an unknown built-in name or an
    invalid scene, tomllib.TOMLDecodeError for a syntax error (message with line
    and column).
    """
    arg = os.fspath(name_or_path)
    if os.path.isfile(arg):
        path = os.path.abspath(arg)
        with open(path, "rb") as fh:
            d = tomllib.loads(_scene_text(fh.read(), arg))
        return scene_from_dict(d, base_dir=os.path.dirname(path), path=path)
    looks_like_path = os.sep in arg or "/" in arg or arg.endswith(".toml")
    if arg in _builtin_names():
        res = _builtin_dir() / f"{arg}.toml"
        d = tomllib.loads(res.read_text(encoding="utf-8"))
        with resources.as_file(res) as real:
            real = os.fspath(real)
            return scene_from_dict(d, base_dir=os.path.dirname(real), path=real)
    if looks_like_path:
        raise FileNotFoundError(f"scene file not found: {arg}")
    raise _unknown_scene(arg)


def list_builtin_scenes() -> list[tuple[str, str]]:
    """(name, one-line description) of each built-in scene, sorted by name."""
    out = []
    for name in _builtin_names():
        d = tomllib.loads((_builtin_dir() / f"{name}.toml").read_text(encoding="utf-8"))
        out.append((name, str(d.get("scene", {}).get("description", "")).strip()))
    return out


# ----------------------------------------------------------------------------
# Resolved view, TOML, stages, overrides
# ----------------------------------------------------------------------------


def _plain(obj):
    """Dataclass/tuple tree -> dicts and lists, None dropped (TOML has no null)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)
                if getattr(obj, f.name) is not None}
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj


def resolved_dict(scene: Scene) -> dict:
    """The scene in the file format with every default filled (TOML- and JSON-serialisable).

    Feeding it back to scene_from_dict gives an equal Scene. Settings that are
    unset (None: e.g. a zero point no module could supply) are left out.
    """
    out: dict[str, Any] = {
        "scene": {"name": scene.name, "description": scene.description, "seed": scene.seed,
                  "z_source": scene.z_source, "cosmology": _plain(scene.cosmology)},
    }
    src = {"center_arcsec": list(scene.source.center_arcsec)}
    for key in ("bulge", "disk"):
        comp = getattr(scene.source, key)
        if comp is not None:
            c = _plain(comp)
            if not comp.magnitudes:
                c.pop("magnitudes")
            src[key] = c
    if scene.source.clumps is not None:
        src["clumps"] = _plain(scene.source.clumps)
    out["source"] = src
    if scene.lens is not None:
        lens = scene.lens
        ld: dict[str, Any] = {"z_lens": lens.z_lens}
        if lens.center_radec_deg is not None:
            ld["center_radec_deg"] = list(lens.center_radec_deg)
        if lens.deflection is not None:
            dz = lens.deflection.normalization_z_source
            ld["deflection"] = {"x": lens.deflection.x, "y": lens.deflection.y,
                                "normalization": "dls_ds" if dz is None else {"z_source": dz}}
        elif lens.model is not None:
            ld["model"] = lens.model
        else:
            ld["components"] = [{"kind": c.kind, **_plain(c.params)} for c in lens.components]
        out["lens"] = ld
    r = _plain(scene.render)
    out["render"] = r
    out["bands"] = [_plain(b) for b in scene.bands]
    o = _plain(scene.output)
    out["output"] = o
    return out


_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")
# Tables written as [sections] even when nested; everything else small is inline.
_SECTION_KEYS = {"bulge", "disk", "arms", "texture", "clumps"}


def _toml_key(k: str) -> str:
    return k if _BARE_KEY.match(k) else _toml_str(k)


def _toml_str(s: str) -> str:
    out = []
    for ch in s:
        if ch in '"\\':
            out.append("\\" + ch)
        elif ch == "\n":
            out.append("\\n")
        elif ch == "\t":
            out.append("\\t")
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _toml_float(v: float) -> str:
    """Shortest round-tripping text; large and small magnitudes in exponent form (1.0e7)."""
    if v == 0 or 1e-4 <= abs(v) < 1e5:
        return repr(v)
    for digits in range(17):
        text = f"{v:.{digits}e}"
        if float(text) == v:
            break
    mantissa, exponent = text.split("e")
    if "." not in mantissa:
        mantissa += ".0"
    return f"{mantissa}e{int(exponent)}"


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return _toml_float(v)
    if isinstance(v, str):
        return _toml_str(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }" if v else "{}"
    if hasattr(v, "item"):  # numpy scalar
        return _toml_value(v.item())
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _is_table_array(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _emit_table(d: dict, path: list[str], lines: list[str], top: bool) -> None:
    # Plain keys first: after a [header] they would belong to the sub-table.
    # Headers ([sections] and [[arrays]]) then follow in the dict's order.
    inline, headers = [], []
    for k, v in d.items():
        if v is None:
            continue
        if isinstance(v, dict) and (top or k in _SECTION_KEYS):
            headers.append((k, v, False))
        elif _is_table_array(v) and top:
            headers.append((k, v, True))
        else:
            inline.append((k, v))
    for k, v in inline:
        lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
    for k, v, is_array in headers:
        sub = path + [k]
        name = ".".join(_toml_key(x) for x in sub)
        for item in (v if is_array else [v]):
            lines.append("")
            lines.append(f"[[{name}]]" if is_array else f"[{name}]")
            _emit_table(item, sub, lines, top=False)


def to_toml(scene_or_dict) -> str:
    """TOML text for a Scene (its resolved form) or for a nested dict.

    Top-level tables and source components become [sections], lists of tables
    at the top level become [[arrays]], smaller tables are written inline.
    """
    d = resolved_dict(scene_or_dict) if isinstance(scene_or_dict, Scene) else scene_or_dict
    lines: list[str] = []
    _emit_table(d, [], lines, top=True)
    return "\n".join(lines).lstrip("\n") + "\n"


def _uses_sps(scene: Scene) -> bool:
    """True if some band's flux must come from stellar-population synthesis."""
    names = set(scene.band_names)
    for comp in (scene.source.bulge, scene.source.disk):
        if comp is not None and not names <= set(comp.magnitudes):
            return True
    cl = scene.source.clumps
    if cl is not None:
        if cl.catalog is None:
            return True
        from astropy.table import Table

        cols = set(Table.read(cl.catalog).colnames)
        if any(f"mag_{b}" not in cols for b in names):
            return True
    return False


def stages(scene: Scene) -> list[str]:
    """The stages a simulation of this scene runs, in order.

    Names: "population" (clump sampling), "catalog" (clumps read from a file),
    "photometry" (SPS magnitudes), "lensing" (ray tracing), "render:<F>",
    "psf:<F>" (bands with a PSF), "noise", "unlensed", "rgb:<R>-<G>-<B>", "hr".
    """
    out = []
    cl = scene.source.clumps
    if cl is not None:
        out.append("catalog" if cl.catalog else "population")
    if _uses_sps(scene) or (scene.output.hr and scene.output.hr_rgb_um):
        out.append("photometry")
    if scene.lens is not None:
        out.append("lensing")
    for b in scene.bands:
        out.append(f"render:{b.filter}")
        if b.psf != "none":
            out.append(f"psf:{b.filter}")
    if scene.output.noise:
        out.append("noise")
    if scene.output.unlensed and scene.lens is not None:
        out.append("unlensed")
    out += [f"rgb:{'-'.join(t)}" for t in scene.output.rgb]
    if scene.output.hr:
        out.append("hr")
    return out


def with_overrides(scene: Scene, *, seed: int | None = None, bands=None, noise: bool | None = None) -> Scene:
    """A copy of `scene` with command-line overrides applied and checked.

    bands: filter names (any case) to keep, in the scene's order; RGB
    composites that need a dropped band are dropped.
    """
    if seed is not None:
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= SEED_MAX:
            raise ConfigError("--seed", seed, f"an integer in [0, 2**63 - 1 = {SEED_MAX}]")
        scene = dataclasses.replace(scene, seed=seed)
    if noise is not None:
        if noise and any(b.exptime_s is None for b in scene.bands):
            raise ConfigError("noise", noise, "bands with exptime_s (needed for noise)")
        scene = dataclasses.replace(scene, output=dataclasses.replace(scene.output, noise=bool(noise)))
    if bands is not None:
        if isinstance(bands, str):
            bands = [x for x in bands.split(",") if x.strip()]
        wanted = [str(x).strip().upper() for x in bands]
        if not wanted:
            raise ConfigError("--bands", ",".join(bands), "at least one filter name")
        for w in wanted:
            if w not in scene.band_names:
                near = difflib.get_close_matches(w, scene.band_names, n=1, cutoff=0.6)
                raise ConfigError("--bands", ",".join(bands), "filters of this scene: " + ", ".join(scene.band_names)
                                  + (f" (no {w}; did you mean {near[0]}?)" if near else f" (no {w})"))
        keep = tuple(b for b in scene.bands if b.filter in wanted)
        names = {b.filter for b in keep}
        rgb = tuple(t for t in scene.output.rgb if set(t) <= names)
        scene = dataclasses.replace(scene, bands=keep, output=dataclasses.replace(scene.output, rgb=rgb))
    return scene
