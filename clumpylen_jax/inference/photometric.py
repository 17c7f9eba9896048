"""Clump fluxes from stellar mass and age: fit physical clump properties directly.

flux[N, B] = mag_to_counts_per_s(ab_magnitudes(mass_msun, age_myr, filters, z, ...), zp_B)

`photometry.ab_magnitudes` is differentiable in mass and age, so gradients of
the likelihood reach them; the fluxes are intrinsic (source plane), the lens
model supplies the magnification when the source is rendered. Redshift,
metallicity, SFH, dust and IGM are configuration (static), as in photometry.py.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from ..errors import ConfigError


@dataclasses.dataclass(frozen=True)
class ClumpPhotometry:
    """Static map (mass, age) → counts/s per band; hashable so it can sit in a static field.

    filters: filter names in band order.  zeropoints_ab: AB magnitude giving 1 count/s, per band.
    z: source redshift.  options: extra keyword arguments of `photometry.ab_magnitudes`
    as a tuple of (name, value) pairs (e.g. (("sfh", "burst"), ("dust_av", 0.2))).
    """

    filters: tuple
    zeropoints_ab: tuple
    z: float
    options: tuple = ()

    def __post_init__(self):
        if len(self.filters) != len(self.zeropoints_ab) or not self.filters:
            raise ConfigError("photometry.zeropoints_ab", self.zeropoints_ab,
                              f"one zero point per filter ({len(self.filters)})")

    def magnitudes(self, mass_msun, age_myr):
        """AB magnitudes [N, B]."""
        from ..photometry import ab_magnitudes
        return ab_magnitudes(mass_msun, age_myr, filters=list(self.filters), z=float(self.z),
                             **dict(self.options))

    def counts_per_s(self, mass_msun, age_myr):
        """Intrinsic count rates [N, B] (counts/s)."""
        from ..photometry import mag_to_counts_per_s
        zp = jnp.asarray(self.zeropoints_ab)
        return mag_to_counts_per_s(self.magnitudes(mass_msun, age_myr), zp[None, :])
