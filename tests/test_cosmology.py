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


def test_flat_lcdm_distances_kept_in_folder_bit_for_bit(tmp_path):
    """A FlatLCDM with a folder gives astropy's values exactly, computed once: the second
    call reads the file (here replaced, to see that it is read) instead of astropy."""
    kept = cosmo.FlatLCDM(68.0, 0.31, tmp_path)
    plain = cosmo.make_cosmology(68.0, 0.31)
    for name, args in (("dls_ds", (0.4, 2.1)), ("arcsec_per_pc", (2.1,)),
                       ("luminosity_distance_cm", (2.1,))):
        fn = getattr(cosmo, name)
        value = fn(*args, kept)
        assert value == fn(*args, plain) and type(value) is float
        (path,) = tmp_path.glob(f"{name}-*.txt")
        path.write_text(repr(value * 2))
        assert fn(*args, kept) == value * 2
    assert cosmo.arcsec_per_pc(2.1, cosmo.FlatLCDM(68.0, 0.31)) == cosmo.arcsec_per_pc(2.1, plain)
    np.testing.assert_array_equal(cosmo.arcsec_per_pc(np.array([1.0, 2.1]), kept),
                                  cosmo.arcsec_per_pc(np.array([1.0, 2.1]), plain))
    with pytest.raises(ConfigError):
        cosmo.FlatLCDM(-1.0, 0.3)


def test_importing_the_pipeline_leaves_astropy_cosmology_unimported():
    """astropy.cosmology and scipy.integrate (~0.7 s of CPU) load only when a distance is
    computed, not with the package (a warm simulate reads its distances from the cache)."""
    import subprocess
    import sys
    code = ("import sys, clumpylen_jax.pipeline, clumpylen_jax.cli, clumpylen_jax.photometry; "
            "print('astropy.cosmology' in sys.modules, 'scipy.integrate' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]
