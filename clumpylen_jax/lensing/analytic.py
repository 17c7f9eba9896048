"""Analytic lenses, pure JAX. Deflections in arcsec for the scene's source redshift.

Each lens is an equinox Module with ``deflection(theta1, theta2)``; θ in arcsec
relative to the lens centre (DESIGN.md). Radii use safe forms so that a ray at
a lens centre gives a finite deflection and gradient.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp


def safe_hypot(x, y, floor=0.0):
    """sqrt(x² + y²) with a finite gradient at the origin (where it is set to 0)."""
    r2 = x * x + y * y
    ok = r2 > 0
    r = jnp.sqrt(jnp.where(ok, r2, 1.0))
    return jnp.where(ok, r, floor)


class SIS(eqx.Module):
    """Singular isothermal sphere: |α| = θ_E, pointing away from the centre.

    theta_e_arcsec: Einstein radius for the scene's source, arcsec.
    center_arcsec: (θ1, θ2) of the lens centre, arcsec.
    """

    theta_e_arcsec: jnp.ndarray
    center_arcsec: jnp.ndarray

    def deflection(self, theta1, theta2):
        dx = theta1 - self.center_arcsec[0]
        dy = theta2 - self.center_arcsec[1]
        r = safe_hypot(dx, dy)
        inv = jnp.where(r > 0, 1.0 / jnp.where(r > 0, r, 1.0), 0.0)
        return self.theta_e_arcsec * dx * inv, self.theta_e_arcsec * dy * inv
