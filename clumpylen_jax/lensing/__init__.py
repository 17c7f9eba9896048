"""Lenses: anything with ``deflection(theta1, theta2) -> (alpha1, alpha2)``.

The protocol of the imaging core: a lens returns the deflection, in arcsec, for
the scene's source redshift (any D_ls/D_s scaling already applied), at lens-plane
positions θ in arcsec relative to the lens centre (DESIGN.md conventions). The
lens equation is then β = θ − α(θ) (`clumpylen_jax.lensing.raytrace`).
"""
