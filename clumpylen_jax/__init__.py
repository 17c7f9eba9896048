"""clumpylen_jax: a differentiable JAX simulator of strongly lensed, clumpy galaxies.

Importing the package enables JAX's 64-bit mode: float64 is the default
precision of the simulator (DESIGN.md, "Accuracy"). Arrays built in float32 stay
float32; every kernel computes in the dtype of its inputs.
"""

import jax

jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"
