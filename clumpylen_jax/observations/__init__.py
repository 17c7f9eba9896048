"""Observed images in: read, check and place real JWST/HST cutouts for `clumpylen fit`.

    units     image units → the AB zero point of one data unit per pixel
    frame     one fit frame φ for every band's pixel grid; θ and RA/Dec of φ
    read      one band: image, σ², mask, PSF, units (ObservationSpec → Observation)
    config    [[observations]], [fit], [lens.local] from a scene file
    fit       the joint host + clumps fit on the data's pixels (fit_observations)
    sample    its posterior sampled from the optimum (NUTS, emcee): [fit] method
    answers   physical answers: positions, sizes, magnitudes, masses, intrinsic values
    outputs   fit.ecsv, residuals_<FILTER>.fits, clumps.reg, summary.json, fit.png
    products  a cutout written as JWST i2d / HST drz products (mocks in real formats)
"""

from .config import FitOptions, LocalLens, ObservationScene, load_observation_scene
from .frame import FitFrame, fit_frame
from .products import write_cutout
from .read import Observation, ObservationSpec, read_observation
from .units import resolve_units, zeropoint_mjy_sr, zeropoint_photflam

__all__ = ["FitFrame", "FitOptions", "LocalLens", "Observation", "ObservationScene",
           "ObservationSpec", "fit_frame", "load_observation_scene", "read_observation",
           "resolve_units", "write_cutout", "zeropoint_mjy_sr", "zeropoint_photflam"]
