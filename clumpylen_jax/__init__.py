"""clumpylen_jax: a differentiable JAX simulator of strongly lensed, clumpy galaxies.

The public API is what ``__all__`` lists (the modules behind it are free to change):

    import clumpylen_jax as cl
    cl.enable_float64()                  # float64 is the caller's choice (see below)
    scene = cl.load_scene("cosmic-archipelago")
    cl.simulate(scene, "out")            # or: prep = cl.prepare(scene); prep.model ...

Precision: the simulator's reference precision is float64 (DESIGN.md, "Accuracy"),
which JAX gives only with its 64-bit mode on. Importing this package does not change
JAX's global configuration; call `enable_float64()` once, before building models (the
`clumpylen` command does). A float64 model or scene run with the 64-bit mode off raises
a ConfigError naming the dtype setting instead of silently computing in float32.
Arrays built in float32 stay float32; every kernel computes in the dtype of its inputs.

Names are imported on first use (PEP 562), so ``import clumpylen_jax`` stays cheap.
"""

import importlib

__version__ = "0.1.0"


def enable_float64(enabled: bool = True) -> None:
    """Turn JAX's 64-bit mode on (or off): float64 arrays, the simulator's default dtype.

    Call it once at the start of a program, before any array is made. It sets JAX's
    process-wide ``jax_enable_x64`` flag (it is JAX's setting, not this package's).
    """
    import jax

    jax.config.update("jax_enable_x64", bool(enabled))


def float64_enabled() -> bool:
    """True when JAX's 64-bit mode is on (float64 arrays are possible)."""
    import jax

    return bool(jax.config.read("jax_enable_x64"))


# public name -> module that defines it
_EXPORTS = {
    # source components
    "Source": "source", "Sersic": "source", "Disk": "source", "SpiralArms": "source",
    "Texture": "source", "Clumps": "source",
    # the model
    "Accuracy": "model", "ACCURACY_PRESETS": "model", "Band": "model", "build_model": "model",
    # bands and fluxes from names, magnitudes, masses and ages
    "make_band": "builders", "band_zeropoint_ab": "builders", "band_counts_per_s": "builders",
    "ab_magnitudes": "photometry",
    # lenses
    "SIS": "lensing", "SIE": "lensing", "NFW": "lensing", "DPIE": "lensing",
    "ExternalShear": "lensing", "MassSheet": "lensing", "LensSum": "lensing",
    "DeflectionGrid": "lensing", "lensing_quantities": "lensing",
    "builtin_lens": "lensing.clusters", "lens_from_components": "lensing.clusters",
    "load_deflection_maps": "lensing.fits",
    # scenes and the pipeline
    "load_scene": "scene", "prepare": "pipeline", "simulate": "pipeline",
    # fitting
    "run_fit": "inference.run",
    # errors
    "ConfigError": "errors",
}

__all__ = sorted(_EXPORTS) + ["__version__", "enable_float64", "float64_enabled"]


def __getattr__(name):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
