"""Cosmological distances (astropy), the only place the package builds a cosmology.

The default is the paper's flat ΛCDM (H0 = 70 km/s/Mpc, Ωm = 0.3). Every
function takes an optional astropy cosmology; ``None`` means the default.
Results are plain floats / numpy arrays: distances are configuration, not
differentiated quantities.
"""

from __future__ import annotations

import functools

import numpy as np
from astropy import units as u
from astropy.cosmology import FlatLambdaCDM

from .constants import ARCSEC_PER_RAD
from .errors import require

_PC_PER_RAD_TO_ARCSEC = ARCSEC_PER_RAD


@functools.lru_cache(maxsize=32)
def make_cosmology(H0: float = 70.0, Om0: float = 0.3) -> FlatLambdaCDM:
    """A flat ΛCDM cosmology (cached, so equal parameters give the same object)."""
    require(np.isfinite(H0) and H0 > 0, "cosmology.H0", H0, "a positive number (km/s/Mpc)")
    require(np.isfinite(Om0) and 0 <= Om0 <= 1, "cosmology.Om0", Om0, "a number in [0, 1]")
    return FlatLambdaCDM(H0=float(H0), Om0=float(Om0))


def _cosmo(cosmology):
    return make_cosmology() if cosmology is None else cosmology


def _check_z(z, name="z"):
    z_arr = np.asarray(z, dtype=float)
    require(bool(np.all(np.isfinite(z_arr)) and np.all(z_arr >= 0)), name, z, "a redshift >= 0")
    return z_arr


def dls_ds(z_lens: float, z_source: float, cosmology=None) -> float:
    """D_ls / D_s, the factor that scales deflections normalised to D_ls/D_s = 1."""
    zl = _check_z(z_lens, "z_lens")
    zs = _check_z(z_source, "z_source")
    require(bool(np.all(zs > zl)), "z_source", z_source, f"a redshift above z_lens = {z_lens}")
    c = _cosmo(cosmology)
    d_ls = c.angular_diameter_distance(zl, zs) if _two_arg_da() else c.angular_diameter_distance_z1z2(zl, zs)
    d_s = c.angular_diameter_distance(zs)
    return _as_float(np.asarray((d_ls / d_s).decompose().value))


def arcsec_per_pc(z: float, cosmology=None) -> float:
    """Angle (arcsec) subtended by 1 pc at redshift z (angular-diameter distance)."""
    zz = _check_z(z)
    require(bool(np.all(zz > 0)), "z", z, "a redshift > 0")
    d_a_pc = _cosmo(cosmology).angular_diameter_distance(zz).to_value(u.pc)
    return _as_float(_PC_PER_RAD_TO_ARCSEC / d_a_pc)


def luminosity_distance_cm(z: float, cosmology=None) -> float:
    """Luminosity distance in cm."""
    zz = _check_z(z)
    require(bool(np.all(zz > 0)), "z", z, "a redshift > 0")
    return _as_float(_cosmo(cosmology).luminosity_distance(zz).to_value(u.cm))


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

    return len(inspect.signature(FlatLambdaCDM.angular_diameter_distance).parameters) > 2
