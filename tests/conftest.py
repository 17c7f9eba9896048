"""Shared pytest configuration: hypothesis profiles.

"ci" (the default): few examples, no deadline (JAX compiles on first use),
derandomized so that runs are reproducible. "thorough": many examples, to run by
hand (``HYPOTHESIS_PROFILE=thorough pytest tests/test_hard_cases.py``).
"""

import os

import clumpylen_jax

# float64 is the caller's choice (clumpylen_jax.enable_float64); the tests run with it on
clumpylen_jax.enable_float64()


def _share_compiled_programs_between_workers():
    """Under pytest-xdist both workers import the same test modules and compile many of the
    same programs (module-level models, shared scenes): one persistent compilation cache for
    the run (keyed by the run's id, in the temporary folder) lets the second worker load
    what the first compiled. A run without xdist compiles as before."""
    run_id = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if run_id:
        import tempfile
        from pathlib import Path

        from clumpylen_jax.cache import enable_compilation_cache
        enable_compilation_cache(True, Path(tempfile.gettempdir()) / f"clumpylen-tests-jax-{run_id}")


_share_compiled_programs_between_workers()

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
