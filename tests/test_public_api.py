"""The public API (clumpylen_jax.__all__) and float64 as the caller's choice."""

import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clumpylen_jax as cl


def test_every_public_name_resolves():
    for name in cl.__all__:
        assert getattr(cl, name) is not None, name
    assert cl.build_model is __import__("clumpylen_jax.model", fromlist=["x"]).build_model
    with pytest.raises(AttributeError):
        cl.not_a_name  # noqa: B018


def test_import_leaves_jax_configuration_alone():
    code = "import jax, clumpylen_jax; print(jax.config.read('jax_enable_x64'))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_float64_with_x64_off_is_a_config_error_naming_render_dtype():
    src = cl.Source(bulge=cl.Sersic(jnp.array([1.0]), jnp.array(0.1), jnp.array(1.0), jnp.array(1.0),
                                    jnp.array(0.0), jnp.array([0.0, 0.0])))
    scene = cl.load_scene("single-sersic")
    jax.config.update("jax_enable_x64", False)
    try:
        assert not cl.float64_enabled()
        with pytest.raises(cl.ConfigError, match="render.dtype"):
            cl.build_model(src, [cl.Band("X", 0.03, 1.0)])
        with pytest.raises(cl.ConfigError, match="render.dtype"):
            cl.prepare(scene)
    finally:
        cl.enable_float64()
    assert cl.float64_enabled() and jnp.asarray(1.0).dtype == jnp.float64


def test_listing_scenes_does_not_import_jax():
    """`clumpylen scenes` / `show` and parsing a scene stay light: JAX is imported only by
    the commands that compute (cli.py's promise; scene.py reads the presets from the
    JAX-free accuracy.py)."""
    code = ("import sys; from clumpylen_jax.cli import main; from clumpylen_jax import scene; "
            "main(['scenes']); scene.load_scene('single-sersic'); print('jax' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "False"


def test_make_band_is_the_scene_band():
    """The Python route from an instrument and filter name to a Band goes through the scene
    parser: the same defaults (pixel scale, zero point, PSF) as a [[bands]] table."""
    from clumpylen_jax import pipeline, scene as scene_mod
    text = scene_mod.builtin_scene_text("single-sersic").replace('psf = "none"', 'psf = "diffraction"')
    scene = scene_mod.scene_from_dict(__import__("tomllib").loads(text))
    (ref,) = pipeline._bands(scene, pipeline._accuracy(scene))
    zps = pipeline._zeropoints(scene)
    band = cl.make_band("JWST/NIRCam", "F200W", exptime_s=1000.0, sky_counts_per_s=0.16,
                        accuracy=scene.render.accuracy.preset)
    assert band == ref and band.psf is not None
    assert np.array_equal(band.psf, ref.psf) and band.psf_pixel_arcsec == ref.psf_pixel_arcsec
    assert cl.band_zeropoint_ab(band) == zps["F200W"]
    with pytest.raises(cl.ConfigError, match="did you mean 'exptime_s'"):
        cl.make_band("JWST/NIRCam", "F200W", exptme_s=1.0)
    with pytest.raises(cl.ConfigError, match="F201W"):
        cl.make_band("JWST/NIRCam", "F201W")


def test_band_counts_per_s_from_magnitudes_and_from_masses():
    """Magnitudes → counts/s through the zero point (inf → no light); masses and ages through
    the SPS model give the same counts as their SPS magnitudes."""
    zp = cl.band_zeropoint_ab("F150W")
    counts = cl.band_counts_per_s(["F150W"], mag_ab=[[zp - 2.5], [np.inf]])
    assert counts.shape == (2, 1)
    assert counts[0, 0] == pytest.approx(10.0) and counts[1, 0] == 0.0
    masses, ages = np.array([1e5, 1e7]), np.array([5.0, 200.0])
    flux = cl.band_counts_per_s(["F150W", "F444W"], mass_msun=masses, age_myr=ages, z_source=3.0)
    mags = np.asarray(cl.ab_magnitudes(masses, ages, filters=["F150W", "F444W"], z=3.0))
    zps = [cl.band_zeropoint_ab("F150W"), cl.band_zeropoint_ab("F444W")]
    np.testing.assert_allclose(flux, 10.0 ** (-0.4 * (mags - np.array(zps))), rtol=1e-12)
    # light is linear in the mass at a fixed age; an older population is redder
    double = cl.band_counts_per_s(["F150W", "F444W"], mass_msun=2 * masses, age_myr=ages, z_source=3.0)
    np.testing.assert_allclose(double, 2 * flux, rtol=1e-9)
    assert flux[1, 1] / flux[1, 0] > flux[0, 1] / flux[0, 0]
    with pytest.raises(cl.ConfigError, match="either mag_ab"):
        cl.band_counts_per_s(["F150W"])
    with pytest.raises(cl.ConfigError, match="z_source"):
        cl.band_counts_per_s(["F150W"], mass_msun=[1e6], age_myr=[10.0])
