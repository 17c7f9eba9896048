"""A smooth diffuse light per band, profiled out of the likelihood (variable projection).

An arc's or a ring's diffuse light is not a Sérsic: fitted with one, the rest of it is
left in the residual, where the clump finder takes it for clumps (RXJ1131's ring: 20
clumps, χ²/dof 21). Here each band's observed image may carry, besides host and clumps,

    D_b = B_b a_b          B_b [n_pix, K]: tensor-product cubic B-splines on nodes
                           `spacing_pix` apart (covering the image; they sum to 1, so a
                           constant background is in their span), a_b [K] free.

D is linear in a, so for any other parameters the best a is a weighted least-squares
solution, and the likelihood is profiled over it in closed form (Golub & Pereyra 1973):
with Ã = √m B / σ and r = √m (d − μ) / σ (the whitened residual),

    a* = (ÃᵀÃ + λ I)⁻¹ Ãᵀ r,     χ²_profiled = |r − Ã a*|² + λ |a*|²,

and the residual vector handed to the solvers is [r − Ã a*, √λ a*], whose squared norm is
exactly χ²_profiled; its Jacobian is the Schur-complement (marginal) one, so Fisher errors
of clump fluxes include the diffuse light's freedom. λ is a ridge 1e-6 × the mean diagonal
of ÃᵀÃ: it keeps nodes without data (masked or off the image) at 0, and changes nothing
where the data constrain a node.

The component lives in the observed image (it is not convolved with the PSF): with nodes
several PSF widths apart it is smooth on the PSF scale, and its span, not its shape, is
what matters for a nuisance. Nodes closer than a few PSF FWHM would take a clump's light:
`MIN_SPACING_PIX` bounds them from below.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from ..errors import require

MIN_SPACING_PIX = 4.0   # pixels: closer nodes would draw a PSF-sized clump
RIDGE = 1e-6            # λ relative to the mean diagonal of ÃᵀÃ


def require_spacing(spacing_arcsec: float, pixel_arcsecs, setting: str) -> None:
    """A ConfigError naming `setting` unless the nodes are at least MIN_SPACING_PIX pixels
    apart in every band (pixel_arcsecs: each band's pixel, arcsec)."""
    coarsest = max(pixel_arcsecs)
    require(np.isfinite(spacing_arcsec) and spacing_arcsec >= MIN_SPACING_PIX * coarsest,
            setting, spacing_arcsec, f"at least {MIN_SPACING_PIX:g} pixels of the coarsest band "
            f"(≥ {MIN_SPACING_PIX * coarsest:.3g} arcsec)")


def bspline_design_1d(n: int, spacing_pix: float) -> np.ndarray:
    """[n, K] cubic B-splines at pixel centres 0..n-1, knots `spacing_pix` apart, centred on
    the image, with the basis extended past both edges so the splines sum to 1 on it."""
    from scipy.interpolate import BSpline
    k = 3
    half = 0.5 * (n - 1)
    n_in = int(np.ceil((half + 0.5) / spacing_pix))
    knots = (np.arange(-n_in - k, n_in + k + 1) * spacing_pix) + half
    x = np.arange(n, dtype=float)
    return BSpline.design_matrix(x, knots, k).toarray()


def bspline_design(shape, spacing_pix: float) -> np.ndarray:
    """[ny·nx, Ky·Kx] dense tensor-product basis of an image (row-major like `ravel`; for
    checks: the fit uses the separable factors, `make_basis`)."""
    by, bx = _factors(shape, spacing_pix)
    return np.einsum("yi,xj->yxij", by, bx).reshape(shape[0] * shape[1], -1)


def _factors(shape, spacing_pix):
    """The 1-D designs along y and x, columns that touch no pixel dropped."""
    by, bx = bspline_design_1d(shape[0], spacing_pix), bspline_design_1d(shape[1], spacing_pix)
    return by[:, by.any(0)], bx[:, bx.any(0)]


class DiffuseBasis(eqx.Module):
    """One band's basis B = By ⊗ Bx (kept as its factors: B a = By A Bxᵀ with A = a as
    [Ky, Kx], never the [n_pix, K] matrix), the band's weights √m/σ, and the factored
    normal matrix.

    by: [ny, Ky], bx: [nx, Kx] (image units per coefficient).  weight: [ny, nx] √m / σ.
    chol: [K, K] lower Cholesky factor of ÃᵀÃ + λ I (Ã = weight · B).  sqrt_ridge: √λ.
    """

    by: jnp.ndarray
    bx: jnp.ndarray
    weight: jnp.ndarray
    chol: jnp.ndarray
    sqrt_ridge: jnp.ndarray

    @property
    def n_coefficients(self) -> int:
        return int(self.by.shape[1] * self.bx.shape[1])

    def image(self, a):
        """B a on the image [ny, nx]."""
        return self.by @ a.reshape(self.by.shape[1], self.bx.shape[1]) @ self.bx.T

    def white_transpose(self, r_white):
        """Ãᵀ r [K] for a whitened residual r (flat [n_pix])."""
        r = self.weight * r_white.reshape(self.weight.shape)
        return (self.by.T @ r @ self.bx).ravel()


def make_basis(shape, spacing_pix: float, variance, mask, dtype=jnp.float64) -> DiffuseBasis:
    """The DiffuseBasis of an image of `shape` with σ² `variance` and 0/1 `mask` (numpy)."""
    by, bx = _factors(shape, spacing_pix)
    w = np.sqrt(np.asarray(mask, float)) / np.sqrt(np.asarray(variance, float))
    # ÃᵀÃ[(i, j), (k, l)] = Σ_yx w² By[y, i] By[y, k] Bx[x, j] Bx[x, l], summed over y first
    t = np.einsum("yx,yi,yk->xik", w * w, by, by)
    normal = np.einsum("xik,xj,xl->ijkl", t, bx, bx).reshape(by.shape[1] * bx.shape[1], -1)
    lam = RIDGE * max(float(np.mean(np.diag(normal))), np.finfo(float).tiny)
    chol = np.linalg.cholesky(normal + lam * np.eye(normal.shape[0]))
    to = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    return DiffuseBasis(to(by), to(bx), to(w), to(chol), to(np.sqrt(lam)))


def coefficients(basis: DiffuseBasis, r_white):
    """a* [K] for the whitened residual r (flat [n_pix])."""
    return jsl.cho_solve((basis.chol, True), basis.white_transpose(r_white))


def profiled_residual(basis: DiffuseBasis, r_white):
    """[n_pix + K]: (r − Ã a*, √λ a*), whose squared norm is the χ² profiled over a."""
    return profiled_residual_and_light(basis, r_white)[0]


def profiled_residual_and_light(basis: DiffuseBasis, r_white):
    """(`profiled_residual`, the diffuse image B a* [ny, nx]) from one solve for a* (a caller
    that wants both would otherwise solve twice: `likelihood.chi2_and_images`)."""
    a = coefficients(basis, r_white)
    img = basis.image(a)
    fitted = (basis.weight * img).ravel()
    return jnp.concatenate([r_white - fitted, basis.sqrt_ridge * a]), img


def light(basis: DiffuseBasis, r_white, shape):
    """The fitted diffuse image B a* (image units) for the whitened residual r."""
    return basis.image(coefficients(basis, r_white)).reshape(shape)
