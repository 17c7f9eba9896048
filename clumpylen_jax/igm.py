"""Mean intergalactic-medium transmission: the analytic model of Inoue et al. (2014).

Inoue, Shimizu, Iwata & Tanaka 2014, MNRAS 442, 1805 ("An updated analytic
model for attenuation by the intergalactic medium"). The optical depth is the
sum of four terms, each a piecewise power law in observed wavelength:
Lyman-series absorption by the Lyα forest (LAF) and by damped Lyα systems (DLA),
eqs. (21)–(22) with the coefficients of their Table 2, and Lyman-continuum
absorption by the LAF and the DLA, eqs. (25)–(29). Implemented here from the
published equations and coefficients.

Transmission is a property of the observed-frame wavelength and the source
redshift only; it is evaluated with numpy once per (filter, z) configuration,
not differentiated.
"""

from __future__ import annotations

import numpy as np

LYMAN_LIMIT_AA = 911.8

# Inoue et al. (2014) Table 2: for the Lyman series j = 2..40, the rest
# wavelength λ_j (Å) and the coefficients A^LAF_{j,1..3}, A^DLA_{j,1..2}.
_TABLE2 = np.array([
    [1215.67, 1.690e-02, 2.354e-03, 1.026e-04, 1.617e-04, 5.390e-05],
    [1025.72, 4.692e-03, 6.536e-04, 2.849e-05, 1.545e-04, 5.151e-05],
    [972.537, 2.239e-03, 3.119e-04, 1.360e-05, 1.498e-04, 4.992e-05],
    [949.743, 1.319e-03, 1.837e-04, 8.010e-06, 1.460e-04, 4.868e-05],
    [937.803, 8.707e-04, 1.213e-04, 5.287e-06, 1.429e-04, 4.763e-05],
    [930.748, 6.178e-04, 8.606e-05, 3.752e-06, 1.402e-04, 4.672e-05],
    [926.226, 4.609e-04, 6.421e-05, 2.799e-06, 1.377e-04, 4.590e-05],
    [923.150, 3.569e-04, 4.971e-05, 2.167e-06, 1.355e-04, 4.516e-05],
    [920.963, 2.843e-04, 3.960e-05, 1.726e-06, 1.335e-04, 4.448e-05],
    [919.352, 2.318e-04, 3.229e-05, 1.407e-06, 1.316e-04, 4.385e-05],
    [918.129, 1.923e-04, 2.679e-05, 1.168e-06, 1.298e-04, 4.326e-05],
    [917.181, 1.622e-04, 2.259e-05, 9.847e-07, 1.281e-04, 4.271e-05],
    [916.429, 1.385e-04, 1.929e-05, 8.410e-07, 1.265e-04, 4.218e-05],
    [915.824, 1.196e-04, 1.666e-05, 7.263e-07, 1.250e-04, 4.168e-05],
    [915.329, 1.043e-04, 1.453e-05, 6.334e-07, 1.236e-04, 4.120e-05],
    [914.919, 9.174e-05, 1.278e-05, 5.571e-07, 1.222e-04, 4.075e-05],
    [914.576, 8.128e-05, 1.132e-05, 4.936e-07, 1.209e-04, 4.031e-05],
    [914.286, 7.251e-05, 1.010e-05, 4.403e-07, 1.197e-04, 3.989e-05],
    [914.039, 6.505e-05, 9.062e-06, 3.950e-07, 1.185e-04, 3.949e-05],
    [913.826, 5.868e-05, 8.174e-06, 3.563e-07, 1.173e-04, 3.910e-05],
    [913.641, 5.319e-05, 7.409e-06, 3.230e-07, 1.162e-04, 3.872e-05],
    [913.480, 4.843e-05, 6.746e-06, 2.941e-07, 1.151e-04, 3.836e-05],
    [913.339, 4.427e-05, 6.167e-06, 2.689e-07, 1.140e-04, 3.800e-05],
    [913.215, 4.063e-05, 5.660e-06, 2.467e-07, 1.130e-04, 3.766e-05],
    [913.104, 3.738e-05, 5.207e-06, 2.270e-07, 1.120e-04, 3.732e-05],
    [913.006, 3.454e-05, 4.811e-06, 2.097e-07, 1.110e-04, 3.700e-05],
    [912.918, 3.199e-05, 4.456e-06, 1.943e-07, 1.101e-04, 3.668e-05],
    [912.839, 2.971e-05, 4.139e-06, 1.804e-07, 1.091e-04, 3.637e-05],
    [912.768, 2.766e-05, 3.853e-06, 1.680e-07, 1.082e-04, 3.607e-05],
    [912.703, 2.582e-05, 3.596e-06, 1.568e-07, 1.073e-04, 3.578e-05],
    [912.645, 2.415e-05, 3.364e-06, 1.466e-07, 1.065e-04, 3.549e-05],
    [912.592, 2.263e-05, 3.153e-06, 1.375e-07, 1.056e-04, 3.521e-05],
    [912.543, 2.126e-05, 2.961e-06, 1.291e-07, 1.048e-04, 3.493e-05],
    [912.499, 2.000e-05, 2.785e-06, 1.214e-07, 1.040e-04, 3.466e-05],
    [912.458, 1.885e-05, 2.625e-06, 1.145e-07, 1.032e-04, 3.440e-05],
    [912.420, 1.779e-05, 2.479e-06, 1.080e-07, 1.024e-04, 3.414e-05],
    [912.385, 1.682e-05, 2.343e-06, 1.022e-07, 1.017e-04, 3.389e-05],
    [912.353, 1.593e-05, 2.219e-06, 9.673e-08, 1.009e-04, 3.364e-05],
    [912.324, 1.510e-05, 2.103e-06, 9.169e-08, 1.002e-04, 3.339e-05],
])


def _tau_lyman_series(lam_obs, z_s):
    """Lyman-series optical depth, LAF + DLA (Inoue+14 eqs. 21–22), summed over j."""
    lam = lam_obs[..., None]
    lam_j, a1, a2, a3, d1, d2 = (_TABLE2[:, k] for k in range(6))
    x = lam / lam_j
    # absorption only by clouds between us and the source: λ_j < λ_obs < λ_j (1 + z_s)
    inside = (lam > lam_j) & (lam < lam_j * (1.0 + z_s))
    laf = np.where(x < 2.2, a1 * x**1.2, np.where(x < 5.7, a2 * x**3.7, a3 * x**5.5))
    dla = np.where(x < 3.0, d1 * x**2.0, d2 * x**3.0)
    return np.sum(np.where(inside, laf + dla, 0.0), axis=-1)


def _tau_lyman_continuum_laf(lam_obs, z_s):
    """Lyman-continuum optical depth of the LAF (Inoue+14 eqs. 25–27)."""
    x = lam_obs / LYMAN_LIMIT_AA
    zp = 1.0 + z_s
    if z_s < 1.2:
        tau = 0.325 * (x**1.2 - zp**-0.9 * x**2.1)
    elif z_s < 4.7:
        tau = np.where(
            x < 2.2,
            2.55e-2 * zp**1.6 * x**2.1 + 0.325 * x**1.2 - 0.250 * x**2.1,
            2.55e-2 * (zp**1.6 * x**2.1 - x**3.7),
        )
    else:
        tau = np.where(
            x < 2.2,
            5.22e-4 * zp**3.4 * x**2.1 + 0.325 * x**1.2 - 3.14e-2 * x**2.1,
            np.where(
                x < 5.7,
                5.22e-4 * zp**3.4 * x**2.1 + 0.218 * x**2.1 - 2.55e-2 * x**3.7,
                5.22e-4 * (zp**3.4 * x**2.1 - x**5.5),
            ),
        )
    return np.where((x > 1.0) & (x < zp), tau, 0.0)


def _tau_lyman_continuum_dla(lam_obs, z_s):
    """Lyman-continuum optical depth of the DLA (Inoue+14 eqs. 28–29)."""
    x = lam_obs / LYMAN_LIMIT_AA
    zp = 1.0 + z_s
    if z_s < 2.0:
        tau = 0.211 * zp**2 - 7.66e-2 * zp**2.3 * x**-0.3 - 0.135 * x**2
    else:
        tau = np.where(
            x < 3.0,
            0.634 + 4.70e-2 * zp**3 - 1.78e-2 * zp**3.3 * x**-0.3 - 0.135 * x**2 - 0.291 * x**-0.3,
            4.70e-2 * zp**3 - 1.78e-2 * zp**3.3 * x**-0.3 - 2.92e-2 * x**3,
        )
    return np.where((x > 1.0) & (x < zp), tau, 0.0)


def igm_optical_depth(wavelength_obs_aa, z_source: float) -> np.ndarray:
    """Mean IGM optical depth τ(λ_obs, z_s) of Inoue et al. (2014)."""
    lam = np.asarray(wavelength_obs_aa, dtype=float)
    z_s = float(z_source)
    if z_s <= 0:
        return np.zeros_like(lam)
    tau = (_tau_lyman_series(lam, z_s) + _tau_lyman_continuum_laf(lam, z_s)
           + _tau_lyman_continuum_dla(lam, z_s))
    # The fitted polynomials can dip below zero at the edges of their ranges.
    return np.clip(tau, 0.0, None)


def igm_transmission(wavelength_obs_aa, z_source: float) -> np.ndarray:
    """Mean IGM transmission exp(−τ) at observed wavelengths (Å) for a source at z_source."""
    return np.exp(-igm_optical_depth(wavelength_obs_aa, z_source))
