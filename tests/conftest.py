"""Shared pytest configuration: hypothesis profiles.

"ci" (the default): few examples, no deadline (JAX compiles on first use),
derandomized so that runs are reproducible. "thorough": many examples, to run by
hand (``HYPOTHESIS_PROFILE=thorough pytest tests/test_hard_cases.py``).
"""

import os

import clumpylen_jax

# float64 is the caller's choice (clumpylen_jax.enable_float64); the tests run with it on
clumpylen_jax.enable_float64()

try:
    from hypothesis import HealthCheck, settings
except ImportError:  # hypothesis is a test extra; tests that need it skip
    settings = None

if settings is not None:
    settings.register_profile("ci", max_examples=5, deadline=None, derandomize=True,
                              suppress_health_check=[HealthCheck.too_slow])
    settings.register_profile("thorough", max_examples=300, deadline=None,
                              suppress_health_check=[HealthCheck.too_slow])
    settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
