"""The lens of an observation fit, as the answers need it: β, A = ∂β/∂θ and μ at each clump.

The fit itself is in the image plane (each clump's observed ellipse); a lens maps the answers
to the source plane. Two kinds, one interface (`source_plane(theta)`, θ [N, 2] arcsec in the
fit's θ frame: West, North, from the first observation's centre):

- `LocalLens` (config): one A over the cutout, β = A θ.
- `PlacedLens`: a lens model (deflection maps with their own WCS — HFF and Lenstool — a built-in
  model or analytic components, as a simulation scene's `[lens]`) and the map θ_L = θ_L(θ) from
  the fit frame to the lens's θ frame (origin the lens centre). β = θ_L − α(θ_L),
  A = I − ∂α/∂θ_L: forward-mode derivatives of an analytic deflection (exact); for a map,
  central differences over one map pixel (second order, where the bilinear interpolant's
  own derivative is piecewise constant: first order, off by ~h |∂²α| / 2). The fit frame
  and the lens frame are both gnomonic West/North frames; over a cluster field (arcminutes)
  their relative rotation is ~1e-4 rad, below what a clump's position angle is measured
  to, so A is used as it is.

`place_lens` builds it, and checks before any fit that a map covers every corner of the
cutout with finite deflections: a cutout off the map is a ConfigError naming the setting.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple, Optional

import equinox as eqx
import numpy as np

from ..errors import ConfigError
from .config import LensModel, LocalLens


class SourcePlane(NamedTuple):
    """β [N, 2] (arcsec, lens frame), A [N, 2, 2] = ∂β/∂θ, μ [N] = 1/det A (signed)."""

    beta: np.ndarray
    A: np.ndarray
    mu: np.ndarray


def local_source_plane(lens: LocalLens, theta) -> SourcePlane:
    theta = np.atleast_2d(np.asarray(theta, float))
    A = np.asarray(lens.matrix, float)
    n = len(theta)
    return SourcePlane(theta @ A.T, np.broadcast_to(A, (n, 2, 2)).copy(),
                       np.full(n, lens.magnification))


@dataclasses.dataclass(frozen=True)
class PlacedLens:
    """A lens model and the way from the fit's θ to the lens's θ_L (arcsec): through the sky
    (`radec_center`: RA, Dec of the fit frame's origin; the lens centre is the model's
    `center_radec_deg`), or a shift (`offset_arcsec`: θ_L of the fit frame's origin)."""

    lens: object
    model: LensModel
    radec_center: Optional[tuple] = None
    offset_arcsec: Optional[tuple] = None

    def lens_theta(self, theta) -> np.ndarray:
        theta = np.atleast_2d(np.asarray(theta, float))
        if self.offset_arcsec is not None:
            return theta + np.asarray(self.offset_arcsec, float)
        from ..io import radec_to_theta, theta_to_radec
        ra, dec = theta_to_radec(theta[:, 0], theta[:, 1], self.radec_center)
        t1, t2 = radec_to_theta(ra, dec, self.model.spec.center_radec_deg)
        return np.stack([np.asarray(t1, float), np.asarray(t2, float)], -1)

    def deflection(self, theta_lens):
        """α (arcsec) [N, 2] and ∂α/∂θ [N, 2, 2] at θ_L [N, 2] (float64)."""
        tl = np.asarray(theta_lens, float)
        n = len(tl)
        size = max(8, 1 << (n - 1).bit_length())     # a few padded sizes: a few compiles
        pad = np.zeros((size, 2))
        pad[:n] = tl
        alpha, jac = _deflection_and_jacobian(self.lens, pad)
        return np.asarray(alpha, float)[:n], np.asarray(jac, float)[:n]

    def source_plane(self, theta) -> SourcePlane:
        tl = self.lens_theta(theta)
        alpha, jac = self.deflection(tl)
        A = np.eye(2) - jac
        with np.errstate(divide="ignore"):
            mu = 1.0 / np.linalg.det(A)
        return SourcePlane(tl - alpha, A, mu)

    def describe(self) -> dict:
        L = self.model.spec
        kind = "deflection maps" if L.deflection is not None else (
            f"built-in model {L.model}" if L.model is not None else "analytic components")
        out = {"kind": kind, "z_lens": L.z_lens,
               "center_radec_deg": None if L.center_radec_deg is None else list(L.center_radec_deg),
               "cutout_center_lens_theta_arcsec": self.lens_theta([[0.0, 0.0]])[0].tolist()}
        if L.deflection is not None:
            out["maps"] = [L.deflection.x, L.deflection.y]
        return out


@eqx.filter_jit
def _deflection_and_jacobian(lens, theta_lens):
    """α [N, 2] and ∂α/∂θ [N, 2, 2] (module doc: AD for analytic lenses, central differences
    over one pixel for maps) at θ_L [N, 2] arcsec, one program for all of it."""
    import jax.numpy as jnp

    from ..lensing.derived import deflection_jacobian
    t1 = jnp.asarray(theta_lens[:, 0], jnp.float64)
    t2 = jnp.asarray(theta_lens[:, 1], jnp.float64)
    alpha = jnp.stack(lens.deflection(t1, t2), -1)
    h = getattr(lens, "pixel_arcsec", None)       # a map: its grid spacing
    if h is None:
        d = deflection_jacobian(lens, t1, t2)
        return alpha, jnp.stack([jnp.stack(d[:2], -1), jnp.stack(d[2:], -1)], -2)
    cols = [(jnp.stack(lens.deflection(t1 + e1, t2 + e2), -1)
             - jnp.stack(lens.deflection(t1 - e1, t2 - e2), -1)) / (2 * h)
            for e1, e2 in ((h, 0.0), (0.0, h))]
    return alpha, jnp.stack(cols, -1)


def source_plane(lens, theta) -> SourcePlane:
    """β, A, μ at θ [N, 2] (arcsec, fit frame) for a LocalLens or a PlacedLens."""
    if isinstance(lens, LocalLens):
        return local_source_plane(lens, theta)
    return lens.source_plane(theta)


def describe(lens) -> Optional[dict]:
    """The lens as summary.json reports it."""
    if lens is None:
        return None
    if isinstance(lens, LocalLens):
        return {"convergence": lens.convergence, "shear": list(lens.shear),
                "magnification": lens.magnification}
    return lens.describe()


def _corners_theta(frame) -> np.ndarray:
    """θ (arcsec, fit frame) of the first observation's four corner pixel centres."""
    ny, nx = frame.reference.shape
    xy = np.array([[0.0, 0.0], [nx - 1.0, 0.0], [0.0, ny - 1.0], [nx - 1.0, ny - 1.0]])
    return frame.theta(frame.phi_of_pixel(xy, 0))


def place_lens(scene, frame):
    """The scene's lens ready for `source_plane` (LocalLens as it is; a LensModel loaded and
    placed), or None. ConfigError, before any fit, when the cutout cannot be placed or a map
    does not cover it."""
    model = scene.lens
    if model is None or isinstance(model, LocalLens):
        return model
    from ..cosmology import FlatLCDM
    from ..pipeline import lens_object
    L = model.spec
    wcs_center = frame.center_radec()
    if model.cutout_center_arcsec is not None:
        placed = dict(offset_arcsec=model.cutout_center_arcsec)
    elif model.cutout_center_radec_deg is not None:
        if wcs_center is not None:
            raise ConfigError("lens.cutout_center_radec_deg", list(model.cutout_center_radec_deg),
                              "not given: the observations' celestial WCS places the cutout")
        placed = dict(radec_center=model.cutout_center_radec_deg)
    elif wcs_center is not None and L.center_radec_deg is not None:
        placed = dict(radec_center=wcs_center)
    else:
        missing = "lens.center_radec_deg" if wcs_center is not None else \
            "lens.cutout_center_radec_deg"
        raise ConfigError(missing, "<missing>", "where the cutout lies in the lens model: "
                          "cutout_center_arcsec (θ of the first observation's centre from the "
                          "lens centre), or the sky positions of both (a celestial WCS or "
                          "cutout_center_radec_deg, and lens.center_radec_deg)")
    lens = lens_object(L, scene.z_source, FlatLCDM(*scene.cosmology))
    out = PlacedLens(lens, model, **placed)
    tl = out.lens_theta(_corners_theta(frame))
    if hasattr(lens, "contains"):      # a map: the cutout must lie on it
        import jax.numpy as jnp
        inside = np.asarray(lens.contains(jnp.asarray(tl[:, 0]), jnp.asarray(tl[:, 1])))
        alpha, _ = out.deflection(tl)
        if not (inside.all() and np.isfinite(alpha).all()):
            raise ConfigError("lens.deflection", f"maps {L.deflection.x}, {L.deflection.y}",
                              "maps that cover the cutout with finite deflections: its corners "
                              f"lie at θ = {np.round(tl, 2).tolist()} arcsec from the lens centre")
    return out
