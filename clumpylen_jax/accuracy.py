"""Accuracy knobs of the model and their presets (pure data: no JAX, so that scene files
can be parsed and validated without importing it). `model` re-exports these names."""

from __future__ import annotations

import dataclasses

import numpy as np

from .errors import require

SOURCE_MODES = ("hybrid", "grid", "analytic")
CLUMP_PIXELS = ("sersic", "round_gaussian", "exponential_mog")


@dataclasses.dataclass(frozen=True)
class Accuracy:
    """Accuracy knobs. Presets in `ACCURACY_PRESETS`; benchmarks/ measure what each costs.

    lens_subsampling: Gauss–Legendre order per lens-plane pixel (rays per pixel = its square).
    source_order: Gauss–Legendre order per pixel when a profile is integrated on a grid.
    exact_core: side (pixels) of the block around each Sérsic centre integrated exactly;
        0: no exact pixels at all.
    thin_strip: an unlensed profile with light beyond the core where it is thin (beyond a
        pixel from its centre, minor axis below a pixel: q·r < 1 pixel,
        `render.strip_needed`) has instead the pixels along its major axis integrated
        exactly (3 per row or column of its stamp or grid, + exact_core²), as have
        linearised clump images with light beyond the core. False: the core only
        (faster for many small elongated clumps; sampling errors of % on thin ones).
    psf_oversampling: odd factor of the grid, finer than the detector, on which the PSF acts.
    source_mode: "hybrid" (each clump image far enough from a caustic is the clump seen
        through the local linear lens map, integrated over detector pixels with no rays;
        the others as in "grid"), "grid" (clumps on a source-plane grid, bilinear at each
        ray) or "analytic" (every clump evaluated at every ray: the converged reference,
        cost rays × clumps).
    linearise_tolerance: "hybrid" linearises a clump when, on each of its images, the
        linear map misplaces the image of its 99 %-light rim by less than this fraction of
        the finest detector pixel (and no caustic crosses its stamp); 0 traces every clump.
    stamp_flux_fraction: light fraction of the largest clump its stamp must hold.
    source_flux_fraction: light fraction of each host component inside the traced region.
    gaussian_noise_above: expected counts above which noise is drawn as a Gaussian (None: never).
    host_subsampling: evaluate host components at every ray (True) or at each lens-plane
        pixel's centre only (False: they vary little across a pixel's source-plane footprint).
    clump_pixels: how unlensed clumps are integrated over pixels. "sersic": any Sérsic
        index and shape, on stamps (Gauss–Legendre sampled, exact core or strip);
        "round_gaussian": only clumps with n = 0.5 and q = 1 (round Gaussians, the paper's
        clumps), exactly and with no stamps, as separable Φ differences
        (`model.clumps.RoundGaussianClumps`; `build_model` refuses other clumps and lensed
        scenes); "exponential_mog": only clumps with n = 1 and q = 1 (round exponentials),
        each as a fixed mixture of 8 round Gaussians integrated the same way
        (`gaussian_mixtures.EXPONENTIAL`): an approximation, per pixel within 8.4e-4 of
        the exact peak pixel and 3e-4 of the flux for R_e 1e-3 to 30 pixels, with or
        without a PSF (benchmarks/results/mog_accuracy.md), 8 times the cost of a
        Gaussian clump and no stamps. The clump fits choose these two for their round
        n = 0.5 and n = 1 clumps (`inference.auto.fit_clump_pixels`).
    ray_footprint: with source_mode "analytic", clumps (all Sérsic n = 0.5) are evaluated as
        their mean over each ray's source-plane cell (rays at the centres of equal cells tiling
        each lens pixel; the cell's second moment from the local lens map added to the
        clump's covariance: `render.gaussian_clumps_cell_brightness`) instead of at the
        Gauss–Legendre points: no aliasing of clumps narrower than the ray spacing. The
        lensed clump fits use it (`inference.auto_run.make_model_factory`).
    """

    lens_subsampling: int = 4
    source_order: int = 3
    exact_core: int = 5
    thin_strip: bool = True
    psf_oversampling: int = 5
    source_mode: str = "hybrid"
    linearise_tolerance: float = 0.05
    stamp_flux_fraction: float = 0.9999
    source_flux_fraction: float = 0.99
    gaussian_noise_above: float | None = 1.0e4
    host_subsampling: bool = False
    clump_pixels: str = "sersic"
    ray_footprint: bool = False

    def validate(self, name="render.accuracy"):
        for key in ("lens_subsampling", "source_order", "psf_oversampling"):
            v = getattr(self, key)
            require(isinstance(v, (int, np.integer)) and 1 <= v <= 16, f"{name}.{key}", v,
                    "an integer in [1, 16]")
        require(self.psf_oversampling % 2 == 1, f"{name}.psf_oversampling",
                self.psf_oversampling, "an odd integer (detector centres on sub-pixel centres)")
        require(isinstance(self.exact_core, (int, np.integer)) and 0 <= self.exact_core <= 31,
                f"{name}.exact_core", self.exact_core, "an integer in [0, 31]")
        require(self.source_mode in SOURCE_MODES, f"{name}.source_mode",
                self.source_mode, " or ".join(f'"{m}"' for m in SOURCE_MODES))
        require(self.clump_pixels in CLUMP_PIXELS, f"{name}.clump_pixels", self.clump_pixels,
                " or ".join(f'"{m}"' for m in CLUMP_PIXELS))
        require(isinstance(self.ray_footprint, (bool, np.bool_)), f"{name}.ray_footprint",
                self.ray_footprint, "true or false")
        require(np.isfinite(self.linearise_tolerance) and self.linearise_tolerance >= 0,
                f"{name}.linearise_tolerance", self.linearise_tolerance, "a fraction ≥ 0")
        for key in ("stamp_flux_fraction", "source_flux_fraction"):
            v = getattr(self, key)
            require(0.5 <= v < 1, f"{name}.{key}", v, "a fraction in [0.5, 1)")
        return self


# Chosen from benchmarks/results/accuracy.md (error against time, measured in one run):
# the lens-plane ray density dominates the clump flux error of ray-traced clumps
# (per-clump error with 2.5 mas lens pixels: 2–9 % at 3 rays per axis, 0.3–3 % at 4,
# 0.01–1 % at 6), so "hybrid" traces only the clumps near caustics and integrates the
# others exactly through the local lens map (benchmarks/results/lenstronomy*.md: 4× smaller
# error than grid mode at 30 clumps, and the paper scene renders 9 bands in 3.7 s warm);
# the exact core is what makes sub-pixel Sérsics converge; PSF oversampling 3/5/7 gives
# 10/3/1.6 σ.
ACCURACY_PRESETS = {
    "fast": Accuracy(lens_subsampling=2, source_order=2, exact_core=5, psf_oversampling=3,
                     stamp_flux_fraction=0.999, source_flux_fraction=0.98),
    "default": Accuracy(),  # the class defaults are the default preset (one place)
    "high": Accuracy(lens_subsampling=8, source_order=4, exact_core=7, psf_oversampling=7,
                     source_mode="analytic", stamp_flux_fraction=0.99999,
                     source_flux_fraction=0.999, host_subsampling=True),
}
