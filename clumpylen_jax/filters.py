"""Filter throughput curves: the twelve paper bands and user-supplied curves.

Built-in curves are astro-sedpy's shipped total-system throughputs (telescope +
instrument + detector; wavelengths in Å): ``acs_wfc_*.par`` (STScI ACS
throughputs, retrieved 2017), ``wfc3_ir_*.par`` and ``jwst_f*.par`` (NIRCam
modA/modB mean, filters + DBS + QE + OTE, post-flight May 2024). Any HST/ACS-WFC,
HST/WFC3-IR or JWST/NIRCam curve that sedpy ships can be named; the twelve bands
of the paper are always available.

Names are case-insensitive: ``"F200W"``, ``"JWST/NIRCam F200W"``,
``"HST/ACS/F435W"``, ``"wfc3_ir_f160w"``. A path to an existing text (two
columns: Å, throughput) or ECSV file loads a user curve.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import importlib.util
import os
import pathlib
import re

import numpy as np

from .errors import ConfigError

PAPER_BANDS = (
    "F435W", "F606W", "F814W",                       # HST/ACS-WFC
    "F105W", "F125W", "F160W",                       # HST/WFC3-IR
    "F115W", "F150W", "F200W", "F277W", "F356W", "F444W",  # JWST/NIRCam
)

# sedpy file prefix -> instrument name used across the package (instruments.py).
_PREFIX_TO_INSTRUMENT = {"acs_wfc_": "HST/ACS", "wfc3_ir_": "HST/WFC3-IR", "jwst_": "JWST/NIRCam"}
_INSTRUMENT_ALIASES = {
    "hst/acs": "HST/ACS", "acs": "HST/ACS", "acs/wfc": "HST/ACS", "hst/acs/wfc": "HST/ACS",
    "acs_wfc": "HST/ACS",
    "hst/wfc3-ir": "HST/WFC3-IR", "hst/wfc3/ir": "HST/WFC3-IR", "wfc3-ir": "HST/WFC3-IR",
    "wfc3/ir": "HST/WFC3-IR", "wfc3_ir": "HST/WFC3-IR", "wfc3ir": "HST/WFC3-IR",
    "jwst/nircam": "JWST/NIRCam", "nircam": "JWST/NIRCam", "jwst": "JWST/NIRCam",
}


@dataclasses.dataclass(frozen=True, eq=False)
class Filter:
    """A filter's total-system throughput.

    wavelength_aa: strictly increasing wavelengths (Å, observed frame);
    throughput: dimensionless photon-to-electron efficiency (≥ 0);
    instrument: "HST/ACS", "HST/WFC3-IR", "JWST/NIRCam" or None for user curves.
    """

    name: str
    wavelength_aa: np.ndarray
    throughput: np.ndarray
    instrument: str | None = None
    source: str = ""

    @property
    def pivot_wavelength_aa(self) -> float:
        """Pivot wavelength sqrt(∫Tλ dλ / ∫T/λ dλ): converts <f_ν> and <f_λ> exactly."""
        lam, t = self.wavelength_aa, self.throughput
        return float(np.sqrt(np.trapezoid(t * lam, lam) / np.trapezoid(t / lam, lam)))

    def support_aa(self, frac: float = 1e-3) -> tuple[float, float]:
        """Wavelength range where the throughput exceeds `frac` of its peak."""
        on = np.nonzero(self.throughput > frac * self.throughput.max())[0]
        return float(self.wavelength_aa[on[0]]), float(self.wavelength_aa[on[-1]])

    def __repr__(self):
        return (f"Filter({self.name!r}, instrument={self.instrument!r}, "
                f"pivot={self.pivot_wavelength_aa:.1f} Å, n={len(self.wavelength_aa)})")


def _sedpy_filter_dir() -> pathlib.Path:
    # located, not imported: `import sedpy` loads its observate module (~0.5 s), and only
    # its data files are read here
    spec = importlib.util.find_spec("sedpy")
    if spec is None or not spec.submodule_search_locations:  # pragma: no cover - a dependency
        raise ConfigError("filter", "built-in", "the astro-sedpy package to be installed")
    return pathlib.Path(spec.submodule_search_locations[0]) / "data" / "filters"


@functools.lru_cache(maxsize=1)
def _builtin_index() -> dict[tuple[str, str], pathlib.Path]:
    """(instrument, band) -> sedpy .par file for every supported instrument."""
    index = {}
    for path in sorted(_sedpy_filter_dir().glob("*.par")):
        stem = path.stem.lower()
        for prefix, inst in _PREFIX_TO_INSTRUMENT.items():
            band = stem[len(prefix):].upper()
            if stem.startswith(prefix) and re.fullmatch(r"F\d{3,4}[A-Z0-9]*", band):
                # jwst_f1000w etc. are MIRI, not NIRCam: NIRCam bands are F0xx-F4xx.
                if inst == "JWST/NIRCam" and len(band) != 5:
                    continue
                index[(inst, band)] = path
    return index


def available_filters() -> list[str]:
    """Names ("INSTRUMENT/BAND") of every built-in curve."""
    return [f"{inst}/{band}" for inst, band in sorted(_builtin_index())]


def _parse_name(name: str) -> tuple[str | None, str]:
    """Split "JWST/NIRCam F200W", "acs_wfc_f435w", "F200W" into (instrument|None, band)."""
    s = name.strip()
    m = re.search(r"(f\d{3,4}[a-z0-9]*)$", s, flags=re.IGNORECASE)
    if m is None:
        return None, s.upper()
    band = m.group(1).upper()
    head = s[: m.start()].strip(" /_:-").lower()
    if not head:
        return None, band
    inst = _INSTRUMENT_ALIASES.get(head)
    return (inst if inst is not None else "?" + head), band


def _read_par(path: pathlib.Path) -> tuple[np.ndarray, np.ndarray]:
    data = np.loadtxt(path, comments="#", usecols=(0, 1), ndmin=2)
    return data[:, 0], data[:, 1]


def validate_curve(name: str, wavelength_aa, throughput) -> tuple[np.ndarray, np.ndarray]:
    """Check a throughput curve; return float64 copies. Raises ConfigError."""
    lam = np.asarray(wavelength_aa, dtype=float)
    t = np.asarray(throughput, dtype=float)
    setting = f"filter {name!r}"
    if lam.ndim != 1 or t.shape != lam.shape or lam.size < 2:
        raise ConfigError(setting, f"shape {lam.shape}/{t.shape}", "two 1-D columns of equal length ≥ 2")
    if not (np.all(np.isfinite(lam)) and np.all(np.isfinite(t))):
        raise ConfigError(setting, "NaN/inf values", "finite wavelengths and throughputs")
    if np.any(np.diff(lam) <= 0):
        raise ConfigError(setting, "non-increasing wavelengths", "strictly increasing wavelengths (Å)")
    if lam[0] <= 0:
        raise ConfigError(setting, f"wavelength {lam[0]}", "positive wavelengths (Å)")
    if np.any(t < 0):
        raise ConfigError(setting, f"throughput min {t.min()}", "throughput ≥ 0")
    if not np.any(t > 0):
        raise ConfigError(setting, "all-zero throughput", "some positive throughput")
    return lam, t


def filter_from_arrays(name: str, wavelength_aa, throughput, instrument: str | None = None) -> Filter:
    """A Filter from arrays (Å, throughput), validated."""
    lam, t = validate_curve(name, wavelength_aa, throughput)
    return Filter(name=name, wavelength_aa=lam, throughput=t, instrument=instrument, source="arrays")


def filter_from_file(path, name: str | None = None, instrument: str | None = None) -> Filter:
    """Load a user curve: ECSV (first two columns) or whitespace text (Å, throughput)."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise ConfigError("filter", str(path), "an existing throughput file")
    try:
        if path.suffix.lower() == ".ecsv":
            from astropy.table import Table

            tab = Table.read(path, format="ascii.ecsv")
            lam = np.asarray(tab.columns[0], dtype=float)
            t = np.asarray(tab.columns[1], dtype=float)
        else:
            data = np.loadtxt(path, comments="#", usecols=(0, 1), ndmin=2)
            lam, t = data[:, 0], data[:, 1]
    except ConfigError:
        raise
    except Exception as exc:
        raise ConfigError("filter", str(path), f"a two-column (Å, throughput) table ({exc})") from exc
    name = name or path.stem
    lam, t = validate_curve(name, lam, t)
    return Filter(name=name, wavelength_aa=lam, throughput=t, instrument=instrument, source=str(path))


@functools.lru_cache(maxsize=256)
def _load_builtin(inst: str, band: str) -> Filter:
    path = _builtin_index()[(inst, band)]
    lam, t = _read_par(path)
    # Some shipped curves repeat a wavelength or carry tiny negative noise; keep
    # the first of duplicates and clip to 0 so they pass the user-curve checks.
    keep = np.concatenate([[True], np.diff(lam) > 0])
    lam, t = lam[keep], np.clip(t[keep], 0.0, None)
    lam, t = validate_curve(band, lam, t)
    return Filter(name=band, wavelength_aa=lam, throughput=t, instrument=inst, source=f"sedpy:{path.name}")


def load_filter(name) -> Filter:
    """Return a Filter by name, by path, or pass a Filter through.

    Bare band names ("F200W") map to the paper's instrument for that band
    (ACS for F435W–F814W, WFC3-IR for F105W–F160W, NIRCam for the JWST bands).
    Unknown names raise ConfigError that suggests the nearest valid name.
    """
    if isinstance(name, Filter):
        return name
    looks_like_path = isinstance(name, str) and (os.path.sep in name or "." in name)
    if isinstance(name, os.PathLike) or (looks_like_path and pathlib.Path(name).is_file()):
        return filter_from_file(name)
    if not isinstance(name, str) or not name.strip():
        raise ConfigError("filter", name, "a filter name such as 'F200W' or a throughput file")
    inst, band = _parse_name(name)
    index = _builtin_index()
    if inst is not None and inst.startswith("?"):
        raise ConfigError("filter", name, "an instrument prefix among HST/ACS, HST/WFC3-IR, JWST/NIRCam")
    matches = [(i, b) for (i, b) in index if b == band and (inst is None or i == inst)]
    if not matches:
        valid = [f"{i}/{b}" for i, b in index] + [b for _, b in index]
        near = difflib.get_close_matches(name.strip().upper(), [v.upper() for v in valid], n=3, cutoff=0.5)
        hint = f" (did you mean {', '.join(near)}?)" if near else ""
        raise ConfigError("filter", name, f"one of the built-in bands, e.g. {', '.join(PAPER_BANDS)}{hint}")
    # Bare names are unique among ACS / WFC3-IR / NIRCam curves; prefer the paper's order if not.
    order = {"HST/ACS": 0, "HST/WFC3-IR": 1, "JWST/NIRCam": 2}
    inst, band = sorted(matches, key=lambda m: order[m[0]])[0]
    return _load_builtin(inst, band)


def load_filters(names) -> tuple[Filter, ...]:
    """load_filter over a name, a Filter, or a sequence of them."""
    if isinstance(names, (str, Filter, os.PathLike)):
        names = [names]
    out = tuple(load_filter(n) for n in names)
    if not out:
        raise ConfigError("filters", names, "at least one filter")
    return out
