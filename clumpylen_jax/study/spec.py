"""Study files: parsing and validation, all of it before any work is sent anywhere.

A study is base scenes × scene variants (`[vary]`: source redshift, lens model) ×
the clumps added to each sample or injected (`[clumps]`: mass, size, position) ×
one kind of task (`[study] kind`):

    [study]
    kind = "completeness"          # "simulate" | "completeness" | "fit"
    seed = 7                       # every random draw of the study derives from it
    scenes = ["single-sersic"]     # built-in names or paths (relative to this file)
    bands = ["F200W"]              # optional subset of the scenes' bands

    [vary]                         # optional; every combination is one scene variant
    z_source = [2.0, 3.0]
    lens = ["scene", "none"]       # "scene", "none", or a [lens] table as in SCENE.md

    [clumps]                       # the added / injected clumps
    mass_msun = { min = 1e5, max = 1e7, num = 5, scale = "log" }   # or a list of values
    re_pc = [10.0, 40.0]
    age_myr = 10.0                 # SSP age (burst) that turns mass into flux per band
    region_arcsec = 0.3            # source-plane positions: uniform in this disc around the host centre

    [completeness]                 # the section of the chosen kind (only that one)
    positions = 32

For `completeness` a value is a grid (a list, or min/max/num); for `simulate` and `fit`
it is a distribution (a list: drawn uniformly from it; min/max: uniform, or log-uniform
with scale = "log"). Unknown keys are named with the nearest valid one.
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from typing import Optional

import numpy as np

from ..errors import ConfigError
from ..scene import UnknownKeyError

KINDS = ("simulate", "completeness", "fit")

_KEYS = {
    "": ("study", "vary", "clumps", "simulate", "completeness", "fit"),
    "study": ("name", "kind", "seed", "scenes", "bands", "description"),
    "vary": ("z_source", "lens"),
    "clumps": ("mass_msun", "re_pc", "age_myr", "metallicity", "sersic_n", "q", "region_arcsec"),
    "simulate": ("samples", "clumps_per_sample", "buckets", "noise"),
    "completeness": ("positions", "positions_per_task", "nsigma", "npixels", "match_radius_pix",
                     "map_npix", "subtract_host"),
    "fit": ("samples", "clumps_per_sample", "start_scatter"),
    "range": ("min", "max", "num", "scale"),
}

#: defaults of every optional setting (one place)
DEFAULTS = {
    "clumps": {"mass_msun": [1e6], "re_pc": [20.0], "age_myr": 10.0, "metallicity": 0.004,
               "sersic_n": 1.0, "q": 1.0, "region_arcsec": 0.3},
    "simulate": {"samples": 16, "clumps_per_sample": [1, 8], "buckets": [4, 16, 64, 256],
                 "noise": True},
    "completeness": {"positions": 16, "positions_per_task": 8, "nsigma": 3.0, "npixels": 5,
                     "match_radius_pix": 2.0, "map_npix": 12, "subtract_host": True},
    "fit": {"samples": 8, "clumps_per_sample": 2, "start_scatter": 0.3},
}


@dataclasses.dataclass(frozen=True)
class Values:
    """A varied quantity: `values` (a grid or a list to draw from) or a range (min, max, scale)."""

    values: Optional[tuple] = None
    lo: float = 0.0
    hi: float = 0.0
    log: bool = False

    def grid(self) -> np.ndarray:
        return np.asarray(self.values, float)

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        if self.values is not None:
            return np.asarray(self.values, float)[rng.integers(0, len(self.values), n)]
        if self.log:
            return np.exp(rng.uniform(np.log(self.lo), np.log(self.hi), n))
        return rng.uniform(self.lo, self.hi, n)

    @property
    def max(self) -> float:
        return float(np.max(self.values)) if self.values is not None else self.hi


@dataclasses.dataclass(frozen=True)
class Study:
    """A validated study. `scenes`: resolved scene dicts; `variants`: (scene index, overrides)."""

    name: str
    kind: str
    seed: int
    scene_names: tuple
    scene_dicts: tuple          # parsed TOML of each base scene
    scene_dirs: tuple           # base directory of each (relative paths in it)
    bands: Optional[tuple]
    variants: tuple             # (scene index, z_source or None, lens override or None)
    mass_msun: Values
    re_pc: Values
    clumps: dict                # age_myr, metallicity, sersic_n, q, region_arcsec
    options: dict               # the [kind] section with defaults filled
    text: str = ""              # the study file, stored with the results

    def describe(self) -> str:
        return (f"study '{self.name}': {self.kind}, {len(self.variants)} scene variant(s), "
                f"seed {self.seed}")


def _check_keys(d: dict, path: str, section: str) -> None:
    allowed = _KEYS[section]
    for key in d:
        if key not in allowed:
            raise UnknownKeyError(f"{path}.{key}" if path else key, key, allowed)


def _table(v, path: str) -> dict:
    if not isinstance(v, dict):
        raise ConfigError(path, v, "a table")
    return v


def _number(v, path: str, *, lo=None, integer=False, positive=False) -> float:
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)
    if ok and integer:
        ok = float(v) == int(v)
    if ok and positive:
        ok = v > 0
    if ok and lo is not None:
        ok = v >= lo
    if not ok:
        what = "an integer" if integer else "a finite number"
        cond = " > 0" if positive else (f" >= {lo}" if lo is not None else "")
        raise ConfigError(path, v, what + cond)
    return int(v) if integer else float(v)


def _values(v, path: str, *, grid: bool) -> Values:
    """A list of positive numbers, or {min, max, num?, scale?}."""
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        v = [v]
    if isinstance(v, list):
        if not v:
            raise ConfigError(path, v, "a non-empty list of numbers > 0")
        return Values(tuple(_number(x, f"{path}[{i}]", positive=True) for i, x in enumerate(v)))
    t = _table(v, path)
    _check_keys(t, path, "range")
    for k in ("min", "max"):
        if k not in t:
            raise ConfigError(f"{path}.{k}", "<missing>", "a number > 0 (required in a range)")
    lo = _number(t["min"], f"{path}.min", positive=True)
    hi = _number(t["max"], f"{path}.max", positive=True)
    if hi < lo:
        raise ConfigError(f"{path}.max", hi, f"a number >= min ({lo})")
    scale = t.get("scale", "log")
    if scale not in ("log", "linear"):
        raise ConfigError(f"{path}.scale", scale, '"log" or "linear"')
    if grid:
        if "num" not in t:
            raise ConfigError(f"{path}.num", "<missing>", "the number of grid values (a completeness grid)")
        num = _number(t["num"], f"{path}.num", integer=True, positive=True)
        vals = np.geomspace(lo, hi, num) if scale == "log" else np.linspace(lo, hi, num)
        return Values(tuple(float(x) for x in vals))
    if "num" in t:
        raise ConfigError(f"{path}.num", t["num"], "no num: simulate and fit draw from the range")
    return Values(None, lo, hi, scale == "log")


def _scene_dict(name: str, base_dir: str, setting: str) -> tuple[dict, str]:
    """The parsed TOML of a built-in scene or a scene file, validated, and its base dir."""
    from .. import scene as sc

    path = name if os.path.isabs(name) else os.path.join(base_dir, name)
    if os.path.isfile(path):
        with open(path, "rb") as fh:
            d = tomllib.load(fh)
        sdir = os.path.dirname(os.path.abspath(path))
    elif name in dict(sc.list_builtin_scenes()):
        d = tomllib.loads(sc.builtin_scene_text(name))
        sdir = os.fspath(sc._builtin_dir())
    else:
        raise ConfigError(setting, name, "a built-in scene (clumpylen scenes) or an existing scene file")
    return d, sdir


def variant_scene_dict(study: Study, variant: int) -> tuple[dict, str]:
    """The scene dict of a variant: its base scene with the [vary] overrides applied."""
    import copy

    k, z, lens = study.variants[variant]
    d = copy.deepcopy(study.scene_dicts[k])
    if z is not None:
        d.setdefault("scene", {})["z_source"] = z
    if lens == "none":
        d.pop("lens", None)
    elif isinstance(lens, dict):
        d["lens"] = copy.deepcopy(lens)
    if study.bands is not None:
        d["bands"] = [b for b in d.get("bands", []) if str(b.get("filter", "")).upper() in study.bands]
    return d, study.scene_dirs[k]


def _variants(vary: dict, n_scenes: int) -> tuple:
    zs = vary.get("z_source", [None])
    if not isinstance(zs, list) or not zs:
        zs = [zs] if isinstance(zs, (int, float)) else None
    if zs is None:
        raise ConfigError("vary.z_source", vary.get("z_source"), "a list of redshifts > 0")
    zs = [None if z is None else _number(z, f"vary.z_source[{i}]", positive=True)
          for i, z in enumerate(zs)]
    lenses = vary.get("lens", ["scene"])
    if not isinstance(lenses, list) or not lenses:
        raise ConfigError("vary.lens", lenses, 'a list of "scene", "none" or [lens] tables')
    for i, ln in enumerate(lenses):
        if not (ln in ("scene", "none") or isinstance(ln, dict)):
            raise ConfigError(f"vary.lens[{i}]", ln, '"scene", "none" or a [lens] table (SCENE.md)')
    return tuple((k, z, ln) for k in range(n_scenes) for z in zs for ln in lenses)


def _options(d: dict, kind: str) -> dict:
    for other in KINDS:
        if other != kind and other in d:
            raise ConfigError(other, "<table>", f"only the [{kind}] section for kind = \"{kind}\"")
    t = _table(d.get(kind, {}), kind)
    _check_keys(t, kind, kind)
    opts = {**DEFAULTS[kind], **t}
    for key in ("samples", "positions", "positions_per_task", "npixels", "map_npix"):
        if key in opts:
            opts[key] = _number(opts[key], f"{kind}.{key}", integer=True, positive=True)
    for key in ("nsigma", "match_radius_pix", "start_scatter"):
        if key in opts:
            opts[key] = _number(opts[key], f"{kind}.{key}", positive=True)
    for key in ("noise", "subtract_host"):
        if key in opts and not isinstance(opts[key], bool):
            raise ConfigError(f"{kind}.{key}", opts[key], "true or false")
    if "buckets" in opts:
        b = opts["buckets"]
        if not isinstance(b, list) or not b:
            raise ConfigError(f"{kind}.buckets", b, "a list of clump counts, e.g. [4, 16, 64]")
        opts["buckets"] = sorted(_number(x, f"{kind}.buckets[{i}]", integer=True, positive=True)
                                 for i, x in enumerate(b))
    if "clumps_per_sample" in opts:
        c = opts["clumps_per_sample"]
        c = [c, c] if isinstance(c, int) and not isinstance(c, bool) else c
        if not (isinstance(c, list) and len(c) == 2):
            raise ConfigError(f"{kind}.clumps_per_sample", c, "N or [min, max]")
        lo, hi = (_number(x, f"{kind}.clumps_per_sample[{i}]", integer=True, lo=0)
                  for i, x in enumerate(c))
        if hi < lo or (kind == "fit" and lo < 1):
            raise ConfigError(f"{kind}.clumps_per_sample", c,
                              "[min, max] with min <= max" + (" and min >= 1" if kind == "fit" else ""))
        if kind == "simulate" and hi > max(opts["buckets"]):
            raise ConfigError("simulate.buckets", opts["buckets"],
                              f"a bucket >= the largest clump count ({hi})")
        opts["clumps_per_sample"] = (lo, hi)
    return opts


def study_from_dict(d: dict, base_dir: str = ".", text: str = "") -> Study:
    """Validate a parsed study (nested dicts) and its scenes. Raises ConfigError."""
    from .. import scene as sc

    d = _table(d, "<study>")
    _check_keys(d, "", "")
    s = _table(d.get("study"), "study") if "study" in d else None
    if s is None:
        raise ConfigError("study", "<missing>", "a [study] table with kind and scenes (required)")
    _check_keys(s, "study", "study")
    kind = s.get("kind")
    if kind not in KINDS:
        raise ConfigError("study.kind", kind, " or ".join(f'"{k}"' for k in KINDS))
    seed = _number(s.get("seed", 0), "study.seed", integer=True, lo=0)
    scenes = s.get("scenes")
    scenes = [scenes] if isinstance(scenes, str) else scenes
    if not isinstance(scenes, list) or not scenes or not all(isinstance(x, str) for x in scenes):
        raise ConfigError("study.scenes", scenes, "a scene name or path, or a list of them (required)")
    bands = s.get("bands")
    if bands is not None:
        if not isinstance(bands, list) or not bands or not all(isinstance(b, str) for b in bands):
            raise ConfigError("study.bands", bands, 'a list of filter names, e.g. ["F200W"]')
        bands = tuple(b.upper() for b in bands)
    dicts, dirs = [], []
    for i, name in enumerate(scenes):
        sd, sdir = _scene_dict(name, base_dir, f"study.scenes[{i}]")
        dicts.append(sd)
        dirs.append(sdir)
    vary = _table(d.get("vary", {}), "vary")
    _check_keys(vary, "vary", "vary")
    cl = _table(d.get("clumps", {}), "clumps")
    _check_keys(cl, "clumps", "clumps")
    grid = kind == "completeness"
    mass = _values(cl.get("mass_msun", DEFAULTS["clumps"]["mass_msun"]), "clumps.mass_msun", grid=grid)
    re_pc = _values(cl.get("re_pc", DEFAULTS["clumps"]["re_pc"]), "clumps.re_pc", grid=grid)
    fixed = {}
    for key in ("age_myr", "metallicity", "sersic_n", "q", "region_arcsec"):
        fixed[key] = _number(cl.get(key, DEFAULTS["clumps"][key]), f"clumps.{key}", positive=True)
    if fixed["q"] > 1:
        raise ConfigError("clumps.q", fixed["q"], "an axis ratio in (0, 1]")
    study = Study(name=str(s.get("name", "study")), kind=kind, seed=seed, scene_names=tuple(scenes),
                  scene_dicts=tuple(dicts), scene_dirs=tuple(dirs), bands=bands,
                  variants=_variants(vary, len(scenes)), mass_msun=mass, re_pc=re_pc,
                  clumps=fixed, options=_options(d, kind), text=text)
    # every variant must be a valid scene with the requested bands (cheap: no computation)
    for v in range(len(study.variants)):
        vd, vdir = variant_scene_dict(study, v)
        if bands is not None and not vd["bands"]:
            raise ConfigError("study.bands", list(bands), f"filters of scene {scenes[study.variants[v][0]]}")
        scene = sc.scene_from_dict(vd, base_dir=vdir)
        if bands is not None and set(bands) - set(scene.band_names):
            raise ConfigError("study.bands", list(bands),
                              f"filters of scene {scenes[study.variants[v][0]]}: {list(scene.band_names)}")
    return study


def load_study(path: str | os.PathLike) -> Study:
    """Read and validate a study file (TOML). Raises ConfigError / FileNotFoundError."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"study file not found: {path}")
    with open(path, encoding="utf-8") as fh:
        text = fh.read()
    try:
        d = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(path, "<file>", f"valid TOML ({exc})") from exc
    return study_from_dict(d, os.path.dirname(os.path.abspath(path)), text)
