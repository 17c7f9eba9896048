"""The public API (clumpylen_jax.__all__) and float64 as the caller's choice."""

import subprocess
import sys

import jax
import jax.numpy as jnp
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
