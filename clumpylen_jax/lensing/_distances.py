"""D_ls/D_s for scaling deflections (private helper of the lensing layer).

Uses `clumpylen_jax.cosmology.dls_ds` when that module exists (the project's
single place for cosmology); otherwise falls back to astropy's flat ΛCDM with
H0 = 70 km/s/Mpc, Ωm = 0.3 (the paper's and the HFF models' cosmology).
`cosmology` may be None (the default), an astropy cosmology, or a mapping
{"H0": ..., "Om0": ...} for a flat ΛCDM.
"""

from __future__ import annotations

from ..errors import ConfigError


def _astropy_cosmology(cosmology):
    from astropy.cosmology import FlatLambdaCDM

    if cosmology is None:
        return FlatLambdaCDM(H0=70.0, Om0=0.3)
    if isinstance(cosmology, dict):
        try:
            return FlatLambdaCDM(H0=float(cosmology["H0"]), Om0=float(cosmology["Om0"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError("cosmology", cosmology, "{H0 = <km/s/Mpc>, Om0 = <0..1>}") from exc
    return cosmology


def dls_ds(z_lens: float, z_source: float, cosmology=None) -> float:
    """D_ls/D_s (angular-diameter distances) for a lens at z_lens and source at z_source.

    Zero when the source is not behind the lens (no deflection).
    """
    try:
        from ..cosmology import dls_ds as project_dls_ds  # the project's cosmology, when present
    except ImportError:
        project_dls_ds = None
    if not (z_lens >= 0 and z_source > 0):
        raise ConfigError("redshifts", (z_lens, z_source), "z_lens >= 0 and z_source > 0")
    if z_source <= z_lens:
        return 0.0
    if project_dls_ds is not None:
        return float(project_dls_ds(z_lens, z_source, cosmology))
    cosmo = _astropy_cosmology(cosmology)
    try:  # astropy >= 7.1 takes (z1, z2); older versions only have the _z1z2 method
        d_ls = cosmo.angular_diameter_distance(z_lens, z_source)
    except TypeError:
        d_ls = cosmo.angular_diameter_distance_z1z2(z_lens, z_source)
    d_s = cosmo.angular_diameter_distance(z_source)
    return float((d_ls / d_s).decompose().value)
