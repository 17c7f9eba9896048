"""Bijections between unconstrained reals u and physical parameters x.

Optimisers and samplers move in u ∈ ℝ, so they can never step outside a
parameter's valid region; the model only ever sees x. Every transform is
elementwise, smooth and has a closed-form inverse and log-Jacobian.

| name        | x(u)                                   | used for (by default)                    |
|-------------|----------------------------------------|------------------------------------------|
| identity    | u                                      | centres, angles, background levels       |
| log         | exp(u)                                 | fluxes, radii, masses (x > 0)            |
| bounded     | lo + (hi − lo)·sigmoid(u)              | q ∈ [1e-3, 1], n ∈ [0.2, 10], inclination |
| log_bounded | exp(ln lo + (ln hi − ln lo)·sigmoid(u)) | ages (span decades, bounded by the SSPs) |

Inverses clip x a hair (`EDGE`, relative) inside a bounded interval so that a
start exactly on a bound (q = 1, the common case) maps to a finite u; for `log`
a start at x ≤ 0 maps to ln(`TINY`) (a clump at zero flux).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError

EDGE = 1e-6     # relative distance from a bound at which inverses clip
TINY = 1e-30    # smallest positive value `log` maps back (x ≤ 0 → ln TINY)
# |u| of a bounded kind at EDGE: the inverses' range, and where the LM stops (`u_range`)
U_EDGE = float(np.log((1.0 - EDGE) / EDGE))

Q_MIN = 1e-3    # lower bound of axis ratios: q → 0 is a line, never a useful fit
N_RANGE = (0.2, 10.0)  # Sérsic index range of profiles.py


@dataclasses.dataclass(frozen=True)
class Transform:
    """An elementwise bijection u → x named `kind`, with bounds for the bounded kinds."""

    kind: str = "identity"
    lo: float = 0.0      # a float, or a tuple: one bound per free element (hashable)
    hi: float = 1.0

    # scalar bounds stay Python floats (weakly typed: float32 inputs stay float32)
    @property
    def _lo(self):
        return np.asarray(self.lo, float) if isinstance(self.lo, tuple) else self.lo

    @property
    def _hi(self):
        return np.asarray(self.hi, float) if isinstance(self.hi, tuple) else self.hi

    def __post_init__(self):
        if self.kind not in ("identity", "log", "bounded", "log_bounded"):
            raise ConfigError("transform", self.kind, "identity, log, bounded or log_bounded")
        if self.kind in ("bounded", "log_bounded") and not np.all(np.asarray(self.hi) > np.asarray(self.lo)):
            raise ConfigError("transform bounds", (self.lo, self.hi), "lo < hi")
        if self.kind == "log_bounded" and not np.all(np.asarray(self.lo) > 0):
            raise ConfigError("transform bounds", (self.lo, self.hi), "0 < lo < hi")

    def forward(self, u):
        """Physical value x of unconstrained u."""
        if self.kind == "identity":
            return u
        if self.kind == "log":
            return jnp.exp(u)
        s = jax.nn.sigmoid(u)
        if self.kind == "bounded":
            return self._lo + (self._hi - self._lo) * s
        llo, lhi = np.log(self._lo), np.log(self._hi)
        return jnp.exp(llo + (lhi - llo) * s)

    def inverse(self, x):
        """Unconstrained u of physical x (clipped inside the domain, see module doc)."""
        x = jnp.asarray(x)
        if self.kind == "identity":
            return x
        if self.kind == "log":
            return jnp.log(jnp.maximum(x, TINY))
        if self.kind == "bounded":
            t = (x - self._lo) / (self._hi - self._lo)
        else:
            llo, lhi = np.log(self._lo), np.log(self._hi)
            t = (jnp.log(jnp.maximum(x, self._lo)) - llo) / (lhi - llo)
        t = jnp.clip(t, EDGE, 1.0 - EDGE)
        return jnp.log(t) - jnp.log1p(-t)

    def u_range(self) -> tuple:
        """(lo, hi) of the u the inverse produces: ±U_EDGE for the bounded kinds, u ≥ ln TINY
        for `log`. The LM keeps u there (`lm.levenberg_marquardt`): beyond it a bounded
        parameter is at its bound within EDGE anyway, while dx/du falls as e^−|u| until
        JᵀJ in u underflows (an unresolved clump's R_e reached u = −446, dx/du 1e-196) and
        its Fisher matrix in x comes back indefinite: flux and position errors of 3500 and
        78″ for a S/N 18 point source (`uncertainty.covariance_from_fisher_u`)."""
        if self.kind in ("bounded", "log_bounded"):
            return -U_EDGE, U_EDGE
        if self.kind == "log":
            return float(np.log(TINY)), np.inf
        return -np.inf, np.inf

    def log_abs_det_jacobian(self, u):
        """ln |dx/du| elementwise: the term a density flat in x gains in u."""
        if self.kind == "identity":
            return jnp.zeros_like(u)
        if self.kind == "log":
            return u
        # d sigmoid/du = s(1 − s); ln of it written with softplus for stability
        log_ds = -jax.nn.softplus(-u) - jax.nn.softplus(u)
        if self.kind == "bounded":
            return np.log(self._hi - self._lo) + log_ds
        llo, lhi = np.log(self._lo), np.log(self._hi)
        return jnp.log(self.forward(u)) + np.log(lhi - llo) + log_ds


IDENTITY = Transform("identity")
LOG = Transform("log")


def default_transform(path: str) -> Transform:
    """The transform a free parameter gets unless told otherwise, from its path's last name."""
    leaf = path.rsplit(".", 1)[-1]
    if leaf in ("flux", "re_arcsec", "scale_arcsec", "mass_msun", "winding"):
        return LOG
    if leaf == "q":
        return Transform("bounded", Q_MIN, 1.0)
    if leaf == "n":
        return Transform("bounded", *N_RANGE)
    if leaf == "inclination_rad":
        return Transform("bounded", 0.0, float(np.pi / 2))
    if leaf == "amplitude" and ".arms" in path:
        return Transform("bounded", 0.0, 1.0)
    if leaf == "amplitude":
        return LOG
    if leaf == "age_myr":
        from ..sps import default_library
        return Transform("log_bounded", 0.1, default_library().age_range_myr[1])
    return IDENTITY
