"""The source as pytrees: host components and clumps, with fluxes per band.

Fluxes are in counts/s (the detector's unit) with a trailing band axis: a
component's `flux` has shape [B], the clumps' `flux` shape [N, B], so one source
object drives every band of a scene. Geometry is in arcsec and radians in the
source plane (β frame of DESIGN.md). Every continuous field is a JAX array and
can be differentiated; switches and counts are static.
"""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .errors import ConfigError


def _check_range(name, value, lo, hi, lo_open=False, hi_open=False, expected=None):
    v = np.asarray(value, dtype=float)
    bad = ~np.isfinite(v)
    bad |= (v <= lo) if lo_open else (v < lo)
    bad |= (v >= hi) if hi_open else (v > hi)
    if np.any(bad):
        first = v[bad].flat[0] if v.ndim else float(v)
        raise ConfigError(name, float(first), expected or
                          f"a number in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}")


class Sersic(eqx.Module):
    """An elliptical Sérsic component parametrised by total flux.

    flux: [B] total flux per band, counts/s.   re_arcsec: half-light radius along the major axis.
    n: Sérsic index (0.2–10).   q: axis ratio b/a in (0, 1].
    pa_rad: major-axis angle counter-clockwise from +β1.   center_arcsec: [2] β of the centre.
    """

    flux: jnp.ndarray
    re_arcsec: jnp.ndarray
    n: jnp.ndarray
    q: jnp.ndarray
    pa_rad: jnp.ndarray
    center_arcsec: jnp.ndarray

    def validate(self, name="sersic"):
        """Raise ConfigError for out-of-range parameters (concrete arrays only)."""
        _check_range(f"{name}.flux", self.flux, 0, np.inf, expected="a flux ≥ 0")
        _check_range(f"{name}.re_arcsec", self.re_arcsec, 0, np.inf, lo_open=True,
                     expected="a radius > 0 arcsec")
        _check_range(f"{name}.n", self.n, 0.2, 10.0)
        _check_range(f"{name}.q", self.q, 0, 1, lo_open=True)
        _check_range(f"{name}.pa_rad", self.pa_rad, -np.inf, np.inf, lo_open=True, hi_open=True,
                     expected="a finite angle")
        _check_range(f"{name}.center_arcsec", self.center_arcsec, -np.inf, np.inf, lo_open=True,
                     hi_open=True, expected="finite coordinates")
        return self


class SpiralArms(eqx.Module):
    """Spiral modulation of a disk (Metcalf et al. 2019, the paper's Eq. for I(β, ϑ)).

    count: N_a (static int ≥ 1).  amplitude: A in [0, 1] (arm contrast).
    winding: α.  phase_rad: φ_d.  scale_arcsec: R_h.  orientation_rad: tilt of the pattern.
    """

    count: int = eqx.field(static=True)
    amplitude: jnp.ndarray
    winding: jnp.ndarray
    phase_rad: jnp.ndarray
    scale_arcsec: jnp.ndarray
    orientation_rad: jnp.ndarray

    def validate(self, name="arms"):
        if not (isinstance(self.count, (int, np.integer)) and self.count >= 1):
            raise ConfigError(f"{name}.count", self.count, "an integer ≥ 1")
        _check_range(f"{name}.amplitude", self.amplitude, 0, 1)
        _check_range(f"{name}.scale_arcsec", self.scale_arcsec, 0, np.inf, lo_open=True,
                     expected="a scale > 0 arcsec")
        return self


class Texture(eqx.Module):
    """Perlin-noise perturbation of a disk, evaluated in the source plane.

    amplitude: T ≥ 0 (brightness × max(0, 1 + T·noise)).  scale_arcsec: lattice spacing of
    the first octave.  octaves: static int.  seed: uint32 array choosing the noise field.
    """

    amplitude: jnp.ndarray
    scale_arcsec: jnp.ndarray
    octaves: int = eqx.field(static=True)
    seed: jnp.ndarray

    def validate(self, name="texture"):
        _check_range(f"{name}.amplitude", self.amplitude, 0, np.inf)
        _check_range(f"{name}.scale_arcsec", self.scale_arcsec, 0, np.inf, lo_open=True,
                     expected="a scale > 0 arcsec")
        if not (isinstance(self.octaves, (int, np.integer)) and 1 <= self.octaves <= 12):
            raise ConfigError(f"{name}.octaves", self.octaves, "an integer in [1, 12]")
        return self


class Disk(eqx.Module):
    """A Sérsic disk seen at `inclination_rad` (the minor axis shrinks by cos i), with optional arms and texture."""

    sersic: Sersic
    inclination_rad: jnp.ndarray
    arms: Optional[SpiralArms] = None
    texture: Optional[Texture] = None

    def validate(self, name="disk"):
        self.sersic.validate(name)
        _check_range(f"{name}.inclination_rad", self.inclination_rad, 0, np.pi / 2, hi_open=True,
                     expected="an angle in [0, π/2) rad")
        if self.arms is not None:
            self.arms.validate(f"{name}.arms")
        if self.texture is not None:
            self.texture.validate(f"{name}.texture")
        return self

    @property
    def q_projected(self):
        """Apparent axis ratio: intrinsic q times cos(inclination)."""
        return self.sersic.q * jnp.cos(self.inclination_rad)


class Clumps(eqx.Module):
    """N Sérsic clumps as a struct of arrays.

    center_arcsec: [N, 2] β of the centres.  flux: [N, B] counts/s per band.
    re_arcsec, n, q, pa_rad: [N].
    """

    center_arcsec: jnp.ndarray
    flux: jnp.ndarray
    re_arcsec: jnp.ndarray
    n: jnp.ndarray
    q: jnp.ndarray
    pa_rad: jnp.ndarray

    @property
    def count(self):
        return self.re_arcsec.shape[0]

    def validate(self, name="clumps"):
        n = np.shape(self.re_arcsec)[0]
        for field, shape in (("center_arcsec", (n, 2)), ("re_arcsec", (n,)), ("n", (n,)),
                             ("q", (n,)), ("pa_rad", (n,))):
            if np.shape(getattr(self, field)) != shape:
                raise ConfigError(f"{name}.{field} (shape)", np.shape(getattr(self, field)),
                                  f"shape {shape}")
        if np.ndim(self.flux) != 2 or np.shape(self.flux)[0] != n:
            raise ConfigError(f"{name}.flux (shape)", np.shape(self.flux), f"shape ({n}, bands)")
        Sersic(self.flux, self.re_arcsec, self.n, self.q, self.pa_rad,
               self.center_arcsec).validate(name)
        return self


class Source(eqx.Module):
    """A source: any of bulge, disk and clumps (absent components are None)."""

    bulge: Optional[Sersic] = None
    disk: Optional[Disk] = None
    clumps: Optional[Clumps] = None

    def validate(self):
        if self.bulge is not None:
            self.bulge.validate("source.bulge")
        if self.disk is not None:
            self.disk.validate("source.disk")
        if self.clumps is not None:
            self.clumps.validate("source.clumps")
        return self

    def astype(self, dtype):
        """The same source with every floating array cast to `dtype`."""
        import jax

        def cast(x):
            if isinstance(x, (jnp.ndarray, np.ndarray)) and jnp.issubdtype(x.dtype, jnp.floating):
                return jnp.asarray(x, dtype)
            return x

        return jax.tree_util.tree_map(cast, self)
