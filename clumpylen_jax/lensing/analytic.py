"""Analytic lenses, pure JAX. Deflections in arcsec for the scene's source redshift.

Each lens is an equinox Module with ``deflection(theta1, theta2)``; θ in arcsec
relative to the lens centre (DESIGN.md). Every lens has a ``scale`` field that
multiplies its deflection: parameters quoted for D_ls/D_s = 1 (or for a reference
source redshift) become those of a source at z_s with
``scale = D_ls/D_s(z_l, z_s) / D_ls/D_s(z_l, z_ref)`` (see `with_scale`).

Safety: radii use safe forms so that a ray at a lens centre, on the axis of a
round (q = 1) lens or at x = 1 of an NFW gives a finite deflection and a finite
gradient (the derivative is set to zero exactly at a singular centre, where the
true one diverges). Axis ratios enter only through e² = 1 − q², with series
expansions near q = 1, so derivatives in q are finite there too.

Ellipticity convention: ``q`` = b/a ≤ 1 of the convergence isodensity contours,
``pa_rad`` = angle of the major axis counter-clockwise from +θ1 (DESIGN.md).
Normalisations use the intermediate axis: κ depends on q·x'² + y'²/q, so an
elliptical lens encloses about the same mass as its round version.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..constants import ARCSEC_PER_RAD, C_KMS

# Below this e² = 1 − q², arctan(e u)/e and artanh(e u)/e use their series
# (error ~ e⁴ u⁵/5 < 1e-12 relative for |u| ≤ 1).
_E2_SERIES = 1e-6


def safe_hypot(x, y, floor=0.0):
    """sqrt(x² + y²) with a finite gradient at the origin (where it is set to 0)."""
    r2 = x * x + y * y
    ok = r2 > 0
    r = jnp.sqrt(jnp.where(ok, r2, 1.0))
    return jnp.where(ok, r, floor)


def _safe_div(num, den):
    """num / den, and 0 (with zero gradient) where den == 0."""
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _atan_e(e2, u):
    """arctan(e·u)/e with e = sqrt(e2) ≥ 0; → u at e = 0 (smooth in e2)."""
    big = e2 > _E2_SERIES
    e = jnp.sqrt(jnp.where(big, e2, 1.0))
    return jnp.where(big, jnp.arctan(e * u) / e, u - e2 * u ** 3 / 3.0)


def _atanh_e(e2, v):
    """artanh(e·v)/e with e = sqrt(e2) ≥ 0, |e·v| < 1; → v at e = 0 (smooth in e2)."""
    big = e2 > _E2_SERIES
    e = jnp.sqrt(jnp.where(big, e2, 1.0))
    return jnp.where(big, jnp.arctanh(e * v) / e, v + e2 * v ** 3 / 3.0)


def _to_frame(theta1, theta2, center, pa_rad):
    """Coordinates along the major (x) and minor (y) axes of a lens; returns (x, y, cos, sin)."""
    dx = theta1 - center[0]
    dy = theta2 - center[1]
    c, s = jnp.cos(pa_rad), jnp.sin(pa_rad)
    return c * dx + s * dy, -s * dx + c * dy, c, s


def _from_frame(ax, ay, c, s):
    """Rotate a vector from the lens frame back to θ axes."""
    return c * ax - s * ay, s * ax + c * ay


def softened_isothermal_deflection(x, y, b, core, q):
    """Deflection of κ = b / (2 sqrt(core² + x² + y²/q²)), in its own frame (x = major axis).

    The softened isothermal ellipsoid (Kassiola & Kovner 1993; closed form as in
    Keeton 2001, "A catalog of mass models", eq. for the cored SIE):
      ψ = sqrt(q²(core² + x²) + y²),
      α_x = b q/e · arctan(e x / (ψ + core)),
      α_y = b q/e · artanh(e y / (ψ + q² core)),   e = sqrt(1 − q²).
    core ≥ 0 (0 gives the SIE), 0 < q ≤ 1. Finite value and gradient at the centre.
    """
    e2 = 1.0 - q * q
    # ψ² = q² core² + q² x² + y², with a safe root at ψ = 0 (SIE centre).
    psi2 = q * q * (core * core + x * x) + y * y
    ok = psi2 > 0
    psi = jnp.where(ok, jnp.sqrt(jnp.where(ok, psi2, 1.0)), 0.0)
    u = _safe_div(x, psi + core)
    v = _safe_div(y, psi + q * q * core)
    return b * q * _atan_e(e2, u), b * q * _atanh_e(e2, v)


class _Lens(eqx.Module):
    """Shared helpers; subclasses define `_deflection` without the scale."""

    def deflection(self, theta1, theta2):
        """(α1, α2) in arcsec at θ (arcsec), times `scale`."""
        a1, a2 = self._deflection(theta1, theta2)
        return self.scale * a1, self.scale * a2


class SIS(_Lens):
    """Singular isothermal sphere: |α| = θ_E, pointing away from the centre.

    theta_e_arcsec: Einstein radius (for scale = 1), arcsec.
    center_arcsec: (θ1, θ2) of the lens centre, arcsec.
    scale: multiplies the deflection (D_ls/D_s ratio), dimensionless.
    """

    theta_e_arcsec: jnp.ndarray
    center_arcsec: jnp.ndarray
    scale: jnp.ndarray = 1.0

    def _deflection(self, theta1, theta2):
        dx = theta1 - self.center_arcsec[0]
        dy = theta2 - self.center_arcsec[1]
        r = safe_hypot(dx, dy)
        inv = _safe_div(1.0, r)
        return self.theta_e_arcsec * dx * inv, self.theta_e_arcsec * dy * inv

    def convergence(self, theta1, theta2):
        """κ = θ_E / (2r) (closed form, for tests)."""
        r = safe_hypot(theta1 - self.center_arcsec[0], theta2 - self.center_arcsec[1])
        return self.scale * 0.5 * self.theta_e_arcsec * _safe_div(1.0, r)


class SIE(_Lens):
    """Singular isothermal ellipsoid (Kormann, Schneider & Bartelmann 1994).

    κ = θ_E / (2 sqrt(q x'² + y'²/q)) in the lens frame (x' along the major axis):
    θ_E is the Einstein radius in the intermediate-axis convention (the κ = ½
    contour encloses an area π θ_E²); q → 1 gives the SIS with the same θ_E.
    theta_e_arcsec (arcsec), q (b/a, 0 < q ≤ 1), pa_rad (major axis, rad CCW from +θ1),
    center_arcsec (arcsec), scale (dimensionless).
    """

    theta_e_arcsec: jnp.ndarray
    q: jnp.ndarray
    pa_rad: jnp.ndarray
    center_arcsec: jnp.ndarray
    scale: jnp.ndarray = 1.0

    def _deflection(self, theta1, theta2):
        x, y, c, s = _to_frame(theta1, theta2, self.center_arcsec, self.pa_rad)
        # κ = b/(2 sqrt(x² + y²/q²)) with b = θ_E/sqrt(q) (intermediate-axis normalisation)
        b = self.theta_e_arcsec / jnp.sqrt(self.q)
        ax, ay = softened_isothermal_deflection(x, y, b, 0.0, self.q)
        return _from_frame(ax, ay, c, s)

    def convergence(self, theta1, theta2):
        """κ (closed form, for tests)."""
        x, y, _, _ = _to_frame(theta1, theta2, self.center_arcsec, self.pa_rad)
        return self.scale * 0.5 * self.theta_e_arcsec * _safe_div(
            1.0, safe_hypot(jnp.sqrt(self.q) * x, y / jnp.sqrt(self.q)))


def _nfw_g(x):
    """g(x) = arccosh(1/x)/sqrt(1−x²) (x < 1), arccos(1/x)/sqrt(x²−1) (x > 1), 1 at x = 1.

    A Taylor series (to d⁴, d = x − 1) is used for |d| < `_nfw_band(x)`, where
    both branches lose digits to cancellation.
    """
    d = x - 1.0
    near = jnp.abs(d) < _nfw_band(x)
    xs = jnp.where(near, 0.5, x)  # any value away from 1 for the unused branch
    lo = xs < 1.0
    xl = jnp.where(lo, xs, 0.5)
    xh = jnp.where(lo, 2.0, xs)
    g_lo = jnp.arccosh(1.0 / xl) / jnp.sqrt(1.0 - xl * xl)
    g_hi = jnp.arccos(1.0 / xh) / jnp.sqrt(xh * xh - 1.0)
    g_far = jnp.where(lo, g_lo, g_hi)
    g_near = 1.0 + d * (-2.0 / 3.0 + d * (7.0 / 15.0 + d * (-12.0 / 35.0 + d * 83.0 / 315.0)))
    return jnp.where(near, g_near, g_far)


def _nfw_band(x):
    """Half-width of the series band around x = 1: truncation (~d⁵) vs cancellation (~eps/d)."""
    return 1e-2 if jnp.result_type(x) == jnp.float32 else 1e-3


class NFW(_Lens):
    """Navarro–Frenk–White halo in projection (Bartelmann 1996; Wright & Brainerd 2000).

    kappa_s: κ_s = ρ_s r_s / Σ_cr (for scale = 1), dimensionless.
    rs_arcsec: scale radius r_s, arcsec.
    center_arcsec: (θ1, θ2) of the centre, arcsec. scale: dimensionless.
    With x = r/r_s: |α| = 4 κ_s r_s h(x)/x, h(x) = ln(x/2) + g(x) (see `_nfw_g`);
    for x < 1e-4 the series h ≈ x²/4 (2 ln(2/x) − 1) avoids cancellation.
    """

    kappa_s: jnp.ndarray
    rs_arcsec: jnp.ndarray
    center_arcsec: jnp.ndarray
    scale: jnp.ndarray = 1.0

    def _deflection(self, theta1, theta2):
        dx = theta1 - self.center_arcsec[0]
        dy = theta2 - self.center_arcsec[1]
        x = safe_hypot(dx, dy) / self.rs_arcsec
        tiny = x < 1e-4
        xs = jnp.where(tiny, 1e-4, x)
        h_over_x2 = (jnp.log(xs / 2.0) + _nfw_g(xs)) / (xs * xs)
        # series near the centre; x = 0 exactly is guarded by the `where` (log(0) unused)
        xt = jnp.where(x > 0, x, 1.0)
        series = 0.25 * (2.0 * jnp.log(2.0 / xt) - 1.0)
        f = jnp.where(tiny, jnp.where(x > 0, series, 0.0), h_over_x2)
        # α = 4 κ_s r_s h(x)/x · r̂ = 4 κ_s (h/x²) (dx, dy)
        return 4.0 * self.kappa_s * f * dx, 4.0 * self.kappa_s * f * dy

    def convergence(self, theta1, theta2):
        """κ = 2 κ_s (1 − g(x))/(x² − 1) (→ 2κ_s/3 at x = 1)."""
        x = safe_hypot(theta1 - self.center_arcsec[0], theta2 - self.center_arcsec[1]) / self.rs_arcsec
        xs = jnp.where(x > 0, x, 1e-8)
        d = xs - 1.0
        near = jnp.abs(d) < _nfw_band(xs)
        # (1 − g)/(x² − 1) = 1/3 − 2d/5 + 13d²/35 − 20d³/63 + …
        ratio = jnp.where(near, 1.0 / 3.0 + d * (-0.4 + d * (13.0 / 35.0 - d * 20.0 / 63.0)),
                          (1.0 - _nfw_g(xs)) / jnp.where(near, 1.0, xs * xs - 1.0))
        return self.scale * 2.0 * self.kappa_s * ratio


class DPIE(_Lens):
    """Dual pseudo-isothermal elliptical mass distribution (dPIE / PIEMD with a cut), as in Lenstool.

    Elíasdóttir et al. (2007, arXiv:0710.5636), the circular form
      κ(R) = (b0/2) · r_cut/(r_cut − r_core) · [1/sqrt(r_core² + R²) − 1/sqrt(r_cut² + R²)],
    made elliptical by replacing R² with q x'² + y'²/q (x' along the major axis):
    the difference of two cored isothermal ellipsoids (Kassiola & Kovner 1993).
    Lenstool's ellipticity ε = (a−b)/(a+b) of the isodensity contours maps to q = (1−ε)/(1+ε).

    b0_arcsec: E0 = 6π (σ0/c)² D_ls/D_s in arcsec (the Einstein radius of the SIS
        limit r_core → 0, r_cut → ∞); see `DPIE.from_sigma`.
    rcore_arcsec, rcut_arcsec: core and cut radii, arcsec (0 ≤ r_core < r_cut).
    q, pa_rad, center_arcsec, scale: as for SIE.
    Total mass is finite: M = π Σ_cr b0 r_cut (in arcsec² units of Σ_cr).
    """

    b0_arcsec: jnp.ndarray
    rcore_arcsec: jnp.ndarray
    rcut_arcsec: jnp.ndarray
    q: jnp.ndarray
    pa_rad: jnp.ndarray
    center_arcsec: jnp.ndarray
    scale: jnp.ndarray = 1.0

    @staticmethod
    def from_sigma(sigma0_kms, rcore_arcsec, rcut_arcsec, q, pa_rad, center_arcsec, dls_ds=1.0):
        """Build from Lenstool's fiducial velocity dispersion σ0 (km/s): b0 = 6π (σ0/c)² D_ls/D_s."""
        b0_rad = 6.0 * jnp.pi * (jnp.asarray(sigma0_kms) / C_KMS) ** 2
        b0 = b0_rad * ARCSEC_PER_RAD
        return DPIE(b0, rcore_arcsec, rcut_arcsec, q, pa_rad, jnp.asarray(center_arcsec), dls_ds)

    def _deflection(self, theta1, theta2):
        x, y, c, s = _to_frame(theta1, theta2, self.center_arcsec, self.pa_rad)
        q = self.q
        sq = jnp.sqrt(q)
        # In Keeton's form κ = b/(2 sqrt(s² + x² + y²/q²)): b = b0/sqrt(q), s = r/sqrt(q).
        b = self.b0_arcsec / sq
        w = self.rcut_arcsec / (self.rcut_arcsec - self.rcore_arcsec)
        ax1, ay1 = softened_isothermal_deflection(x, y, b, self.rcore_arcsec / sq, q)
        ax2, ay2 = softened_isothermal_deflection(x, y, b, self.rcut_arcsec / sq, q)
        return _from_frame(w * (ax1 - ax2), w * (ay1 - ay2), c, s)

    def convergence(self, theta1, theta2):
        """κ (closed form, for tests)."""
        x, y, _, _ = _to_frame(theta1, theta2, self.center_arcsec, self.pa_rad)
        r2 = self.q * x * x + y * y / self.q
        a, s = self.rcore_arcsec, self.rcut_arcsec
        return self.scale * 0.5 * self.b0_arcsec * s / (s - a) * (
            1.0 / jnp.sqrt(a * a + r2) - 1.0 / jnp.sqrt(s * s + r2))


class ExternalShear(_Lens):
    """External shear: α = (γ1 Δθ1 + γ2 Δθ2, γ2 Δθ1 − γ1 Δθ2) about `center_arcsec`.

    gamma1, gamma2: shear components (for scale = 1), dimensionless; the shear
    angle is ½ arctan2(γ2, γ1) from +θ1. center_arcsec: the point of zero
    deflection, arcsec (it only adds a constant deflection, i.e. a source shift).
    """

    gamma1: jnp.ndarray
    gamma2: jnp.ndarray
    center_arcsec: jnp.ndarray = (0.0, 0.0)
    scale: jnp.ndarray = 1.0

    def _deflection(self, theta1, theta2):
        dx = theta1 - self.center_arcsec[0]
        dy = theta2 - self.center_arcsec[1]
        return self.gamma1 * dx + self.gamma2 * dy, self.gamma2 * dx - self.gamma1 * dy


class MassSheet(_Lens):
    """Uniform convergence sheet: α = κ (θ − centre). kappa (for scale = 1), center_arcsec."""

    kappa: jnp.ndarray
    center_arcsec: jnp.ndarray = (0.0, 0.0)
    scale: jnp.ndarray = 1.0

    def _deflection(self, theta1, theta2):
        return self.kappa * (theta1 - self.center_arcsec[0]), self.kappa * (theta2 - self.center_arcsec[1])


class LensSum(eqx.Module):
    """The sum of several lenses (any objects with `deflection`), times `scale`.

    lenses: a tuple of lenses (analytic, DeflectionGrid, other LensSums).
    scale: multiplies the total deflection, dimensionless.
    """

    lenses: tuple
    scale: jnp.ndarray = 1.0

    def __init__(self, lenses, scale=1.0):
        self.lenses = tuple(lenses)
        self.scale = scale

    def deflection(self, theta1, theta2):
        # Components of one kind and shape are stacked and vmapped: one traced
        # deflection per kind instead of one per halo, which keeps compile times
        # of many-halo clusters (and everything built on them) short.
        groups = {}
        for lens in self.lenses:
            leaves, treedef = jax.tree_util.tree_flatten(lens)
            key = (type(lens), treedef, tuple(jnp.shape(x) for x in leaves))
            groups.setdefault(key, []).append(lens)
        a1 = a2 = 0.0
        for members in groups.values():
            if len(members) == 1:
                b1, b2 = members[0].deflection(theta1, theta2)
            else:
                stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *members)
                b1, b2 = jax.vmap(lambda l: l.deflection(theta1, theta2))(stacked)
                b1, b2 = jnp.sum(b1, axis=0), jnp.sum(b2, axis=0)
            a1 = a1 + b1
            a2 = a2 + b2
        return self.scale * a1, self.scale * a2


def with_scale(lens, factor):
    """The same lens with its deflection multiplied by `factor` (e.g. a D_ls/D_s ratio).

    Works for any lens with a `scale` field (all lenses of this package,
    DeflectionGrid and LensSum); returns a new Module.
    """
    return eqx.tree_at(lambda m: m.scale, lens, lens.scale * factor)


def convergence_from_jacobian(lens, theta1, theta2):
    """κ at scalar θ from jax.jacfwd of the deflection (used by derived.py and tests)."""
    def alpha(t):
        a1, a2 = lens.deflection(t[0], t[1])
        return jnp.stack([a1, a2])

    jac = jax.jacfwd(alpha)(jnp.stack([theta1, theta2]))
    return 0.5 * (jac[0, 0] + jac[1, 1])
