"""A cutout file as JWST/HST products lay it out, for the observation tests."""

from clumpylen_jax.observations.products import write_cutout

__all__ = ["write_cutout"]
