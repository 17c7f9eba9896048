"""Cosmological distances (astropy), the only place the package builds a cosmology.

The default is the paper's flat ΛCDM (H0 = 70 km/s/Mpc, Ωm = 0.3). Every
function takes an optional astropy cosmology or a `FlatLCDM`; ``None`` means the
default. Results are plain floats / numpy arrays: distances are configuration, not
differentiated quantities. astropy.cosmology (with scipy.integrate, ~0.7 s of CPU on
a loaded 2-core host) is imported only when a distance is computed: a `FlatLCDM`
with a folder reads the distances it computed before from there.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from pathlib import Path
from typing import Optional

import numpy as np

from .constants import ARCSEC_PER_RAD
from .errors import require

_PC_PER_RAD_TO_ARCSEC = ARCSEC_PER_RAD


@functools.lru_cache(maxsize=32)
def make_cosmology(H0: float = 70.0, Om0: float = 0.3):
    """A flat ΛCDM cosmology, astropy's FlatLambdaCDM (cached, so equal parameters give
    the same object)."""
    from astropy.cosmology import FlatLambdaCDM

    _check_parameters(H0, Om0)
    return FlatLambdaCDM(H0=float(H0), Om0=float(Om0))


def _check_parameters(H0, Om0):
    require(np.isfinite(H0) and H0 > 0, "cosmology.H0", H0, "a positive number (km/s/Mpc)")
    require(np.isfinite(Om0) and 0 <= Om0 <= 1, "cosmology.Om0", Om0, "a number in [0, 1]")


@dataclasses.dataclass(frozen=True)
class FlatLCDM:
    """A flat ΛCDM by its parameters, for the functions of this module: its scalar
    distances are computed by astropy (`make_cosmology`) once and kept in `folder` (one
    file each, named by the function, the parameters, the redshifts, astropy's version
    and this module's source), so that a later process need not import astropy.cosmology.
    folder None: computed every time. The values are astropy's, bit for bit."""

    H0: float = 70.0
    Om0: float = 0.3
    folder: Optional[Path] = None

    def __post_init__(self):
        _check_parameters(self.H0, self.Om0)


def scene_cosmology(scene) -> FlatLCDM:
    """A scene's cosmology, its distances kept in the cache folder (`cache.cache_root`)
    unless the cache is off."""
    from .cache import cache_enabled, cache_root

    return FlatLCDM(scene.cosmology.H0, scene.cosmology.Om0,
                    cache_root() / "distances" if cache_enabled() else None)


def _cosmo(cosmology):
    if isinstance(cosmology, FlatLCDM):
        return make_cosmology(cosmology.H0, cosmology.Om0)
    return make_cosmology() if cosmology is None else cosmology


@functools.lru_cache(maxsize=1)
def _source_digest() -> str:
    return hashlib.sha256(Path(__file__).read_bytes()).hexdigest()


def _kept(name: str, cosmology, zs, compute):
    """compute(), read from / written to the folder of a `FlatLCDM` for scalar redshifts."""
    if (not isinstance(cosmology, FlatLCDM) or cosmology.folder is None
            or any(np.ndim(z) for z in zs)):
        return compute()
    import astropy

    from .io import atomic_write

    text = repr((name, float(cosmology.H0), float(cosmology.Om0), [float(z) for z in zs],
                 astropy.__version__, _source_digest()))
    path = Path(cosmology.folder) / f"{name}-{hashlib.sha256(text.encode()).hexdigest()[:40]}.txt"
    try:
        return float(path.read_text())
    except (OSError, ValueError):       # absent or unreadable: computed and (re)written
        pass
    value = compute()
    with atomic_write(path, "w") as fh:
        fh.write(repr(value))           # a float's repr reads back to the same float
    return value


def _check_z(z, name="z"):
    z_arr = np.asarray(z, dtype=float)
    require(bool(np.all(np.isfinite(z_arr)) and np.all(z_arr >= 0)), name, z, "a redshift >= 0")
    return z_arr


def dls_ds(z_lens: float, z_source: float, cosmology=None) -> float:
    """D_ls / D_s, the factor that scales deflections normalised to D_ls/D_s = 1."""
    zl = _check_z(z_lens, "z_lens")
    zs = _check_z(z_source, "z_source")
    require(bool(np.all(zs > zl)), "z_source", z_source, f"a redshift above z_lens = {z_lens}")

    def compute():
        c = _cosmo(cosmology)
        d_ls = (c.angular_diameter_distance(zl, zs) if _two_arg_da()
                else c.angular_diameter_distance_z1z2(zl, zs))
        d_s = c.angular_diameter_distance(zs)
        return _as_float(np.asarray((d_ls / d_s).decompose().value))

    return _kept("dls_ds", cosmology, (zl, zs), compute)


def arcsec_per_pc(z: float, cosmology=None) -> float:
    """Angle (arcsec) subtended by 1 pc at redshift z (angular-diameter distance)."""
    zz = _check_z(z)
    require(bool(np.all(zz > 0)), "z", z, "a redshift > 0")

    def compute():
        from astropy import units as u
        d_a_pc = _cosmo(cosmology).angular_diameter_distance(zz).to_value(u.pc)
        return _as_float(_PC_PER_RAD_TO_ARCSEC / d_a_pc)

    return _kept("arcsec_per_pc", cosmology, (zz,), compute)


def luminosity_distance_cm(z: float, cosmology=None) -> float:
    """Luminosity distance in cm."""
    zz = _check_z(z)
    require(bool(np.all(zz > 0)), "z", z, "a redshift > 0")

    def compute():
        from astropy import units as u
        return _as_float(_cosmo(cosmology).luminosity_distance(zz).to_value(u.cm))

    return _kept("luminosity_distance_cm", cosmology, (zz,), compute)


def distance_modulus(z: float, cosmology=None) -> float:
    """5 log10(D_L / 10 pc)."""
    zz = _check_z(z)
    require(bool(np.all(zz > 0)), "z", z, "a redshift > 0")
    return _as_float(_cosmo(cosmology).distmod(zz).value)


def _as_float(x):
    x = np.asarray(x, dtype=float)
    return float(x) if x.ndim == 0 else x


def _two_arg_da() -> bool:
    """astropy >= 7.1 takes (z1, z2) in angular_diameter_distance; older versions need _z1z2."""
    import inspect

    from astropy.cosmology import FlatLambdaCDM

    return len(inspect.signature(FlatLambdaCDM.angular_diameter_distance).parameters) > 2
