"""Distances against independent closed forms / known values."""

import numpy as np
import pytest

from clumpylen_jax import cosmology as cosmo
from clumpylen_jax.errors import ConfigError


def test_distance_modulus_matches_luminosity_distance():
    d_l = cosmo.luminosity_distance_cm(3.98)
    pc = 3.0856775814913673e18
    assert cosmo.distance_modulus(3.98) == pytest.approx(5 * np.log10(d_l / (10 * pc)), abs=1e-9)


def test_paper_redshift_difference():
    # the paper quotes ~1.1 mag between z = 3.98 and z = 6.145
    d = cosmo.distance_modulus(6.145) - cosmo.distance_modulus(3.98)
    assert d == pytest.approx(1.1, abs=0.05)


def test_arcsec_per_pc_and_dls_ds():
    # flat LCDM, z=6.145: D_A ≈ 1.13 Gpc → 1 pc ≈ 1.8e-4 arcsec
    a = cosmo.arcsec_per_pc(6.145)
    assert 1.5e-4 < a < 2.2e-4
    r = cosmo.dls_ds(0.396, 6.145)
    assert 0.7 < r < 0.9
    assert cosmo.dls_ds(0.396, 1e3) > r


def test_bad_inputs():
    with pytest.raises(ConfigError):
        cosmo.dls_ds(1.0, 0.5)
    with pytest.raises(ConfigError):
        cosmo.distance_modulus(-1.0)
    with pytest.raises(ConfigError):
        cosmo.make_cosmology(H0=-3)
