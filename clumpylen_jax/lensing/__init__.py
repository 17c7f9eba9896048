"""Lenses: anything with ``deflection(theta1, theta2) -> (alpha1, alpha2)``.

The protocol of the imaging core: a lens returns the deflection, in arcsec, for
the scene's source redshift (any D_ls/D_s scaling already applied), at lens-plane
positions θ in arcsec relative to the lens centre (DESIGN.md conventions). The
lens equation is then β = θ − α(θ) (`clumpylen_jax.lensing.raytrace`).

Modules: grid (DeflectionGrid), fits (HFF maps), analytic (SIS, SIE, NFW, DPIE,
ExternalShear, MassSheet, LensSum), derived (κ, γ, μ, critical curves,
caustics, rasterize), images (find_images, lens_plane_region), clusters
(built-in look-alike clusters), plots (diagnostic figure).
"""

from .analytic import DPIE, NFW, SIE, SIS, ExternalShear, LensSum, MassSheet, with_scale
from .derived import (LensingMaps, caustics, critical_curves, grid_lensing_quantities, lens_maps,
                      lensing_quantities, magnification, rasterize)
from .grid import DeflectionGrid
from .images import Images, find_images, lens_plane_region, refine_images
from .raytrace import trace

__all__ = [
    "DPIE", "NFW", "SIE", "SIS", "ExternalShear", "LensSum", "MassSheet", "with_scale",
    "LensingMaps", "caustics", "critical_curves", "grid_lensing_quantities", "lens_maps",
    "lensing_quantities", "magnification", "rasterize", "DeflectionGrid", "Images",
    "find_images", "lens_plane_region", "refine_images", "trace",
]
