"""Round Sérsic profiles as fixed mixtures of round Gaussians, for the separable clump
renderer (`model.clumps.RoundGaussianClumps`; `Accuracy.clump_pixels`).

A mixture is (light fractions, σ / R_e) of its components; the fractions sum to 1, so a
mixture conserves flux exactly. Each component's pixel integrals are exact
(`render.gaussian_pixel_fractions`); the only error is the mixture's own.

- n = 0.5 ("round_gaussian"): one Gaussian, σ = R_e / √(2 b(0.5)): exact.
- n = 1 ("exponential_mog"): EXPONENTIAL, fitted by scripts/fit_exponential_mog.py (cf.
  Hogg & Lang 2013, PASP 125, 719, who fit such mixtures to SDSS profiles; these are our
  own, for the untruncated exponential). The exponential has a cusp that no finite
  mixture reproduces, hence the error stated with the constants; in pixels, with and
  without a PSF, benchmarks/bench_mog_accuracy.py measures it (benchmarks/README.md).
"""

from __future__ import annotations

import jax
import numpy as np

# K = 8 (scripts/fit_exponential_mog.py): |ΔI(r)| ≤ EXP_ERR_PEAK × I(0) at every radius, and
# the enclosed light fraction within ±EXP_ERR_LIGHT at every radius. A later run of the script
# gave constants within 0.6 % of these and the same errors (7.34e-4,
# 6.21e-4): the least-squares path depends on rounding; these are the ones measured
# (benchmarks/results/mog_accuracy.md, fit_observations.json).
EXPONENTIAL = (
    (1.984508928418e-07, 1.584443604443e-05, 3.961190049645e-04, 5.582340158529e-03,
     5.160725553228e-02, 2.687087138727e-01, 5.007571711481e-01, 1.729323573964e-01),
    (0.00292421266, 0.01472950618, 0.046773784846, 0.120160187016, 0.271152963367,
     0.550745565275, 1.000290490574, 1.659600169796),
)
EXP_ERR_PEAK = 7.33e-4
EXP_ERR_LIGHT = 6.20e-4



def round_mixture(clump_pixels: str):
    """(Sérsic n it stands for, light fractions, σ / R_e) of the `clump_pixels` mixture."""
    if clump_pixels == "round_gaussian":
        from . import profiles   # b(0.5) as every other n = 0.5 path computes it
        with jax.ensure_compile_time_eval():   # a constant, also when called inside a trace
            b = float(profiles.sersic_b(0.5))
        return 0.5, (1.0,), (float(1.0 / np.sqrt(2.0 * b)),)
    if clump_pixels == "exponential_mog":
        a, s = EXPONENTIAL
        return 1.0, tuple(float(v) for v in np.asarray(a) / np.sum(a)), s   # Σ = 1 to rounding
    raise ValueError(f"no Gaussian mixture for clump_pixels = {clump_pixels!r}")
