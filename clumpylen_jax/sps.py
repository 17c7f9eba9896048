"""Simple-stellar-population (SSP) libraries and star-formation-history weights.

An `SSPLibrary` holds, per metallicity, rest-frame spectra L_λ (L☉/Å per M☉
*formed*) on an age grid (Myr) and a wavelength grid (Å), an optional nebular
component (continuum + lines, L☉/Å per M☉ formed) and the surviving stellar-mass
fraction. The built-in library (`default_library`) is a compact BC03 (2016,
MILES) table made by ``scripts/make_ssp_table.py``; see
``clumpylen_jax/data/README.md`` for its provenance and IMF.

Composite populations are linear in the SSP spectra, so a star-formation history
is a vector of weights over the age nodes: L_CSP = Σ_k w_k L_k (per M☉ formed).
`sfh_weights` builds that vector in JAX, smooth in the component's age:

* burst: the SSP at age t, interpolated linearly in ln(age) between nodes;
* constant: a constant SFR from age t back to age max(t − D, 0) (i.e. star
  formation began t ago and lasted D, or is still going on if t < D), the exact
  time-average of the same ln(age)-linear interpolant (L constant below the
  first node). d/dt of this average involves L at the interval ends only, so
  gradients in age are smooth and exact for the interpolant.

Mass normalisation follows the paper, F = F_SSP × M / M_SSP: with `mass_msun`
meaning *mass formed* (default) the weights are per M☉ formed; the surviving
stellar mass of the same population is `weights @ surviving_mass_fraction`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import pathlib
import re

import jax
import jax.numpy as jnp
import numpy as np

from .errors import ConfigError

L_SUN_ERG_S = 3.826e33  # the solar luminosity BC03 uses for its L☉ units
LYMAN_LIMIT_REST_AA = 911.8
DATA_DIR = pathlib.Path(__file__).parent / "data"
DEFAULT_TABLE = DATA_DIR / "ssp_bc03_miles.npz"


@dataclasses.dataclass(frozen=True, eq=False)
class SSPLibrary:
    """SSP spectra per unit mass formed.

    ages_myr: (n_age,) strictly increasing, > 0.
    wavelength_aa: (n_wave,) rest-frame wavelengths (bin centres), increasing.
    metallicities: (n_Z,) mass fractions Z (Z☉ ≈ 0.02 in BC03's scale).
    lum_lsun_per_aa: (n_Z, n_age, n_wave) stellar L_λ in L☉/Å per M☉ formed.
    lum_nebular_lsun_per_aa: same shape or None; added when nebular emission is
        asked for (it replaces the stellar ionising continuum it reprocesses).
    surviving_mass_fraction: (n_Z, n_age) or None (then taken as 1).
    """

    name: str
    ages_myr: np.ndarray
    wavelength_aa: np.ndarray
    metallicities: np.ndarray
    lum_lsun_per_aa: np.ndarray
    lum_nebular_lsun_per_aa: np.ndarray | None = None
    surviving_mass_fraction: np.ndarray | None = None
    imf: str = "unknown"
    notes: str = ""

    def __post_init__(self):
        a, w, z, lum = self.ages_myr, self.wavelength_aa, self.metallicities, self.lum_lsun_per_aa
        ok = (a.ndim == 1 and w.ndim == 1 and z.ndim == 1 and lum.shape == (z.size, a.size, w.size))
        if not ok:
            raise ConfigError("ssp library", self.name,
                              f"lum of shape (n_Z, n_age, n_wave) = ({z.size}, {a.size}, {w.size}), got {lum.shape}")
        if not (np.all(a > 0) and np.all(np.diff(a) > 0)):
            raise ConfigError("ssp library ages_myr", self.name, "strictly increasing ages > 0")
        if not (np.all(w > 0) and np.all(np.diff(w) > 0)):
            raise ConfigError("ssp library wavelength_aa", self.name, "strictly increasing wavelengths > 0")
        if not np.all(np.isfinite(lum)) or np.any(lum < 0):
            raise ConfigError("ssp library lum", self.name, "finite luminosities >= 0")
        if self.lum_nebular_lsun_per_aa is not None and self.lum_nebular_lsun_per_aa.shape != lum.shape:
            raise ConfigError("ssp library nebular", self.name, f"the stellar shape {lum.shape}")

    @property
    def age_range_myr(self) -> tuple[float, float]:
        """Ages a component may have: (0, oldest node]. Below the first node L is held fixed."""
        return 0.0, float(self.ages_myr[-1])

    @property
    def has_nebular(self) -> bool:
        return self.lum_nebular_lsun_per_aa is not None

    def metallicity_index(self, metallicity: float) -> int:
        """Index of `metallicity` in the table (relative tolerance 1e-3); ConfigError otherwise."""
        try:
            zval = float(metallicity)
        except (TypeError, ValueError):
            zval = np.nan
        if np.isfinite(zval):
            rel = np.abs(self.metallicities - zval) / self.metallicities
            if rel.min() < 1e-3:
                return int(rel.argmin())
        raise ConfigError("metallicity", metallicity,
                          f"one of the library's metallicities {[float(x) for x in self.metallicities]}")

    def spectra(self, metallicity: float, nebular: bool = True) -> np.ndarray:
        """(n_age, n_wave) L_λ (L☉/Å per M☉ formed) at one metallicity, float64."""
        k = self.metallicity_index(metallicity)
        lum = np.asarray(self.lum_lsun_per_aa[k], dtype=float)
        if nebular and self.has_nebular:
            neb = np.asarray(self.lum_nebular_lsun_per_aa[k], dtype=float)
            # Ionising photons of ages that have nebular emission were absorbed by the gas.
            reprocessed = np.any(neb > 0, axis=1)[:, None] & (self.wavelength_aa < LYMAN_LIMIT_REST_AA)[None, :]
            lum = np.where(reprocessed, 0.0, lum) + neb
        return lum

    def surviving_fraction(self, metallicity: float) -> np.ndarray:
        """(n_age,) surviving stellar mass per unit mass formed (1 if unknown)."""
        if self.surviving_mass_fraction is None:
            return np.ones(self.ages_myr.size)
        return np.asarray(self.surviving_mass_fraction[self.metallicity_index(metallicity)], dtype=float)


# ---------------------------------------------------------------- loaders

def load_library_npz(path, name: str | None = None) -> SSPLibrary:
    """Load a table written by scripts/make_ssp_table.py (or the same keys)."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise ConfigError("ssp library", str(path), "an existing .npz table")
    with np.load(path, allow_pickle=False) as d:
        neb = d["lum_nebular_lsun_per_aa"] if "lum_nebular_lsun_per_aa" in d else None
        surv = d["surviving_mass_fraction"] if "surviving_mass_fraction" in d else None
        meta = str(d["meta"]) if "meta" in d else ""
        try:
            imf = json.loads(meta).get("imf", "unknown") if meta else "unknown"
        except (ValueError, AttributeError):
            imf = "unknown"

        return SSPLibrary(
            name=name or path.stem,
            ages_myr=np.asarray(d["ages_myr"], dtype=float),
            wavelength_aa=np.asarray(d["wavelength_aa"], dtype=float),
            metallicities=np.asarray(d["metallicities"], dtype=float),
            lum_lsun_per_aa=np.asarray(d["lum_lsun_per_aa"]),
            lum_nebular_lsun_per_aa=None if neb is None else np.asarray(neb),
            surviving_mass_fraction=None if surv is None else np.asarray(surv),
            imf=imf,
            notes=meta,
        )


@functools.lru_cache(maxsize=1)
def default_library() -> SSPLibrary:
    """The built-in BC03 (2016, MILES) table: Z = 0.0004, 0.004, 0.008, 0.02; 0.1 Myr–14 Gyr."""
    return load_library_npz(DEFAULT_TABLE, name="bc03_miles")


def library_from_arrays(ages_myr, wavelength_aa, lum, *, metallicities=(0.004,), lum_unit="lsun_per_aa",
                        surviving_mass_fraction=None, name="user", imf="unknown") -> SSPLibrary:
    """A library from arrays: lum of shape (n_age, n_wave) or (n_Z, n_age, n_wave) per M☉ formed.

    lum_unit: "lsun_per_aa" (L☉/Å per M☉) or "erg_s_aa" (erg/s/Å per M☉).
    """
    lum = np.asarray(lum, dtype=float)
    zs = np.atleast_1d(np.asarray(metallicities, dtype=float))
    if lum.ndim == 2:
        lum = lum[None]
    if lum_unit == "erg_s_aa":
        lum = lum / L_SUN_ERG_S
    elif lum_unit != "lsun_per_aa":
        raise ConfigError("lum_unit", lum_unit, "'lsun_per_aa' or 'erg_s_aa'")
    surv = None if surviving_mass_fraction is None else np.atleast_2d(np.asarray(surviving_mass_fraction, float))
    return SSPLibrary(name=name, ages_myr=np.asarray(ages_myr, dtype=float),
                      wavelength_aa=np.asarray(wavelength_aa, dtype=float), metallicities=zs,
                      lum_lsun_per_aa=lum, surviving_mass_fraction=surv, imf=imf)


def load_table(path, *, metallicity=0.004, lum_unit="lsun_per_aa", name=None) -> SSPLibrary:
    """A generic (age_myr, wavelength_aa, L_λ) table in long form, one row per (age, λ).

    Text (three whitespace columns) or ECSV (columns age_myr, wavelength_aa and a
    third luminosity column). Every age must list the same wavelengths.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise ConfigError("ssp table", str(path), "an existing file")
    try:
        if path.suffix.lower() == ".ecsv":
            from astropy.table import Table

            t = Table.read(path, format="ascii.ecsv")
            cols = [np.asarray(t.columns[i], dtype=float) for i in range(3)]
        else:
            data = np.loadtxt(path, comments="#", ndmin=2)
            cols = [data[:, i] for i in range(3)]
    except Exception as exc:
        raise ConfigError("ssp table", str(path), f"three columns age_myr, wavelength_aa, L_lambda ({exc})") from exc
    ages = np.unique(cols[0])
    waves = np.unique(cols[1])
    if ages.size * waves.size != cols[0].size:
        raise ConfigError("ssp table", str(path), "a full grid: every age with the same wavelengths")
    order = np.lexsort((cols[1], cols[0]))
    lum = cols[2][order].reshape(ages.size, waves.size)
    return library_from_arrays(ages, waves, lum, metallicities=(metallicity,), lum_unit=lum_unit,
                               name=name or path.stem)


_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eEdD][-+]?\d+)?"


def load_yggdrasil(path, *, metallicity=0.004, name=None) -> SSPLibrary:
    """Load a Yggdrasil spectra file (Zackrisson et al. 2011 web output).

    The file is a sequence of blocks, one per age: a header line with the age
    ("Age (yr): 1.0E+06"), one with the stellar mass the spectrum refers to
    ("... mass ... (Msolar): 1.0E+06"), then rows "λ (Å)  F_λ (erg/s/Å)".
    Spectra are divided by that mass, so the library is per M☉ as in the
    paper's F_norm = F_Ygg M / M_Ygg. Yggdrasil tables can already include an
    SFH (e.g. constant SFR for 10 Myr): use them with ``sfh="burst"`` then.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise ConfigError("yggdrasil file", str(path), "an existing file")
    blocks = []
    cur = None
    for line in path.read_text(errors="replace").splitlines():
        low = line.lower()
        nums = re.findall(_NUM, line)
        if "age" in low and nums and not _is_data_row(line):
            age = float(nums[-1].replace("D", "E").replace("d", "e"))
            scale = 1.0 if "myr" in low else 1e-6
            cur = {"age_myr": age * scale, "mass": None, "rows": []}
            blocks.append(cur)
        elif cur is not None and "mass" in low and nums and not _is_data_row(line):
            cur["mass"] = float(nums[-1].replace("D", "E").replace("d", "e"))
        elif cur is not None and _is_data_row(line):
            cur["rows"].append([float(x.replace("D", "E").replace("d", "e")) for x in line.split()[:2]])
    blocks = [b for b in blocks if b["rows"]]
    if not blocks:
        raise ConfigError("yggdrasil file", str(path), "blocks of 'Age' header lines followed by (Å, F_λ) rows")
    blocks.sort(key=lambda b: b["age_myr"])
    wave = np.asarray(blocks[0]["rows"])[:, 0]
    lum = []
    for b in blocks:
        rows = np.asarray(b["rows"])
        flux = np.interp(wave, rows[:, 0], rows[:, 1]) if rows.shape[0] != wave.size or \
            np.any(rows[:, 0] != wave) else rows[:, 1]
        lum.append(flux / (b["mass"] if b["mass"] else 1.0))
    ages = np.array([b["age_myr"] for b in blocks])
    keep = ages > 0  # an age-0 block carries no information the first node does not
    return library_from_arrays(ages[keep], wave, np.asarray(lum)[keep], metallicities=(metallicity,),
                               lum_unit="erg_s_aa", name=name or path.stem)


def _is_data_row(line: str) -> bool:
    parts = line.split()
    return len(parts) >= 2 and all(re.fullmatch(_NUM, p) for p in parts[:2]) and len(parts) <= 3


# ---------------------------------------------------------------- SFH weights

@functools.lru_cache(maxsize=64)
def _node_integrals(ages_key: tuple) -> np.ndarray:
    """P[i, k] = ∫_0^{τ_i} h_k(τ) dτ for the ln(age)-linear hat functions h_k (Myr)."""
    tau = np.asarray(ages_key)
    n = tau.size
    p = np.zeros((n, n))
    p[0, 0] = tau[0]  # L constant = L_0 on [0, τ_0]
    for i in range(n - 1):
        du = np.log(tau[i + 1] / tau[i])
        q = tau[i + 1] * du - tau[i + 1] + tau[i]  # ∫_{τ_i}^{τ_i+1} (ln τ − u_i) dτ
        seg = np.zeros(n)
        seg[i] += (tau[i + 1] - tau[i]) - q / du
        seg[i + 1] += q / du
        p[i + 1] = p[i] + seg
    return p


def _cumulative_weights(tau, grid_myr: np.ndarray):
    """G(τ): weights over nodes with ∫_0^τ L dτ' = G(τ) · L_nodes, for the ln-linear interpolant."""
    grid = jnp.asarray(grid_myr, dtype=tau.dtype)
    p = jnp.asarray(_node_integrals(tuple(float(x) for x in grid_myr)), dtype=tau.dtype)
    n = grid_myr.size
    i = jnp.clip(jnp.searchsorted(grid, tau, side="right") - 1, 0, n - 2)
    tau_i = grid[i]
    du = jnp.log(grid[i + 1] / tau_i)
    safe_tau = jnp.where(tau > 0, tau, tau_i)
    q = safe_tau * (jnp.log(safe_tau) - jnp.log(tau_i)) - safe_tau + tau_i
    e_i = jax.nn.one_hot(i, n, dtype=tau.dtype)
    e_j = jax.nn.one_hot(i + 1, n, dtype=tau.dtype)
    inside = p[i] + e_i * (tau - tau_i)[..., None] + (e_j - e_i) * (q / du)[..., None]
    below = jax.nn.one_hot(jnp.zeros_like(i), n, dtype=tau.dtype) * tau[..., None]
    return jnp.where((tau < grid[0])[..., None], below, inside)


def _burst_weights(tau, grid_myr: np.ndarray):
    """Weights of the SSP at age τ, linear in ln(age) between nodes, held fixed below the first node."""
    grid = jnp.asarray(grid_myr, dtype=tau.dtype)
    n = grid_myr.size
    t = jnp.clip(tau, grid[0], grid[-1])
    i = jnp.clip(jnp.searchsorted(grid, t, side="right") - 1, 0, n - 2)
    f = jnp.log(t / grid[i]) / jnp.log(grid[i + 1] / grid[i])
    return (jax.nn.one_hot(i, n, dtype=tau.dtype) * (1 - f)[..., None]
            + jax.nn.one_hot(i + 1, n, dtype=tau.dtype) * f[..., None])


def sfh_weights(age_myr, grid_myr: np.ndarray, sfh: str = "constant", sfh_duration_myr: float = 100.0):
    """Weights (..., n_age) over the SSP age nodes for a population of total mass formed 1 M☉.

    sfh="burst": all mass formed `age_myr` ago. sfh="constant": formed at a
    constant rate between `age_myr` and max(age_myr − sfh_duration_myr, 0) ago.
    """
    tau = jnp.asarray(age_myr)
    if not jnp.issubdtype(tau.dtype, jnp.floating):
        tau = tau.astype(float)
    if sfh == "burst":
        return _burst_weights(tau, grid_myr)
    if sfh == "constant":
        dur = jnp.asarray(sfh_duration_myr, dtype=tau.dtype)
        start = jnp.maximum(tau - dur, 0.0)
        width = tau - start
        g = _cumulative_weights(tau, grid_myr) - _cumulative_weights(start, grid_myr)
        return g / width[..., None]
    raise ConfigError("sfh", sfh, "'burst' or 'constant'")
