"""Renderers of the host (bulge and disk): unlensed on each band's sub-grid, or through the
traced lens plane with an exact integral near the images of its centre."""

from __future__ import annotations

from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import profiles, render
from ..lensing import tracing
from ..source import Source
from .lensplane import LensPlane
from .renderer import HostStack, Renderer, UnitImages


def _host_strips(source: Source, pixel_arcsec: float, core: int):
    """(bulge, disk): whether each host component needs the exact strip on a grid of this
    pixel (thin, with light beyond the exact core; the disk only when a plain Sérsic)."""
    def need(s, q):
        return bool(render.strip_needed(np.asarray(s.re_arcsec), np.asarray(s.n), pixel_arcsec,
                                        core, q=np.asarray(q)))
    disk = source.disk
    return (source.bulge is not None and need(source.bulge, source.bulge.q),
            disk is not None and disk.arms is None and disk.texture is None
            and need(disk.sersic, disk.q_projected))


class UnlensedHosts(Renderer):
    """Bulge and disk integrated over each sub-grid's pixels (exact core, and the exact strip
    where a thin component needs it)."""

    strips: tuple = eqx.field(static=True)   # per band: (bulge, disk) need the exact strip
    order: int = eqx.field(static=True)
    core: int = eqx.field(static=True)

    @classmethod
    def build(cls, source: Source, layouts, accuracy):
        strips = tuple(_host_strips(source, lay.sub_pixel_arcsec, accuracy.exact_core)
                       if accuracy.thin_strip else (False, False) for lay in layouts)
        return cls(strips, accuracy.source_order, accuracy.exact_core)

    def unit_light(self, source: Source, subgrids, modulation_mean=None, extra_grids=()):
        """Per sub-grid of `subgrids` (in its order): the unit-flux images (bulge, disk) on it,
        None for a component the source lacks; the disk's as `render.disk_image_values`
        (`subgrid_light` scales it, so that held values give the same bits).
        modulation_mean: the disk's `render.disk_modulation_mean`, computed before (a
        program of its own), or None (computed here). extra_grids: more grids (no exact
        strip), their images after the sub-grids' (the high-resolution source plane: one
        program for both)."""
        # every sub-grid at once: one compiled profile and one exact-pixel kernel per
        # component, not one per sub-grid
        grids = list(subgrids) + list(extra_grids)
        strips = [self.strips[k] for k in subgrids.values()] + [(False, False)] * len(extra_grids)
        bulge = disk = [None] * len(grids)
        if source.bulge is not None:
            bulge = render.sersic_images(source.bulge, grids, order=self.order, core=self.core,
                                         strips=[s[0] for s in strips])
        if source.disk is not None:
            disk = render.disk_images_values(source.disk, grids, order=self.order,
                                             core=self.core, strips=[s[1] for s in strips],
                                             modulation_mean=modulation_mean)
        return tuple(zip(bulge, disk))

    def subgrid_light(self, source: Source, subgrids, units=None):
        """units: `unit_light(source, subgrids)` computed before (`HeldHosts`), or None."""
        units = self.unit_light(source, subgrids) if units is None else units
        out = {}
        for g, (bulge, disk) in zip(subgrids, units):
            parts = []
            if bulge is not None:
                parts.append((source.bulge.flux, bulge))
            if disk is not None:
                scale = render.disk_image_scale(source.disk, g)
                parts.append((source.disk.sersic.flux, disk if scale == 1.0 else disk * scale))
            if parts:
                out[g] = UnitImages(parts)
        return out


@jax.jit
def _footprint_mean_brightness(b1, b2, inv_area, kw):
    """Mean brightness of a unit-flux Sérsic over footprints [K, S, 4] split in S parts."""
    return jnp.mean(profiles.sersic_quad_flux_exact(b1, b2, flux=1.0, **kw) * inv_area, -1)


class HostCore(eqx.Module):
    """Traced pixels near the images of a host component's centre (`index` into the traced
    pixels), their sub-pixels' source-plane footprints' corners [K, S, 4] relative to
    `origin`, and 1 / their areas (`tracing.host_core_footprints` says which and why)."""

    index: jnp.ndarray
    b1: jnp.ndarray
    b2: jnp.ndarray
    inv_area: jnp.ndarray
    origin: tuple = eqx.field(static=True)

    @classmethod
    def build(cls, source: Source, corner_b1, corner_b2, rows, cols, footprint_index,
              exact_core: int, dtype) -> Optional["HostCore"]:
        comps = [{k: np.asarray(v, float) for k, v in kw.items()} for kw in
                 ([render._sersic_kw(source.bulge)] if source.bulge is not None else [])
                 + ([render._disk_kw(source.disk)] if source.disk is not None else [])]
        found = tracing.host_core_footprints([(kw["center1"], kw["center2"]) for kw in comps],
                                             corner_b1, corner_b2, rows, cols, footprint_index,
                                             exact_core)
        if found is None:
            return None
        idx, v1, v2, area = found
        origin = (float(comps[0]["center1"]), float(comps[0]["center2"]))
        return cls(jnp.asarray(idx), jnp.asarray(v1 - origin[0], dtype),
                   jnp.asarray(v2 - origin[1], dtype), jnp.asarray(1.0 / area, dtype), origin)

    def apply(self, brightness, kw, modulation=None):
        """Host brightness [M] at the traced pixels with, near the images of its centre, the
        mean over each pixel instead of a sample: the exact integral of the Sérsic over the
        pixel's source-plane footprint (a quadrilateral) divided by its area (a sample
        misses or invents the light of a cusp: +3 % of an n = 4 host of R_e 4 lens pixels).
        modulation: the disk's arms × texture factor [K] at those pixels, or None."""
        # corners relative to a point near the host (sub-pixel edges of 1e-4" would lose
        # two digits next to β ~ 10" in float32)
        kw = dict(kw, center1=kw["center1"] - self.origin[0],
                  center2=kw["center2"] - self.origin[1])
        exact = _footprint_mean_brightness(self.b1, self.b2, self.inv_area, kw)
        if modulation is not None:
            exact = exact * modulation
        return brightness.at[self.index].set(exact.astype(brightness.dtype))


class LensPlaneHosts(Renderer):
    """Bulge and disk sampled at the traced lens-plane pixels (one ray per pixel, its centre,
    unless host_subsampling), exact near the images of their centres (`HostCore`)."""

    plane: LensPlane
    core: Optional[HostCore]
    host_subsampling: bool = eqx.field(static=True)

    def _exact(self, brightness, kw, modulation=None):
        return brightness if self.core is None else self.core.apply(brightness, kw, modulation)

    def unit_light(self, source: Source, subgrids=None, modulation_mean=None):
        """Host light per unit flux at every traced pixel [M, C] (times the pixel area), one
        column per host component (bulge, then disk); None without a host. Each component is
        achromatic, so every band is a linear combination of these C ≤ 2 lens-plane images.
        subgrids: unused (the light is the same for every sub-grid). modulation_mean: the
        disk's `render.disk_modulation_mean`, computed before, or None (computed here)."""
        p = self.plane
        # host components vary slowly across a lens-plane pixel's footprint: one ray per
        # pixel (its centre) unless host_subsampling asks for all of them
        if self.host_subsampling:
            h1, h2, hw = p.beta1, p.beta2, p.ray_weights
        else:
            h1, h2, hw = p.beta1_center[:, None], p.beta2_center[:, None], jnp.ones(1, p.dtype)
        units = []
        if source.bulge is not None:
            kw = render._sersic_kw(source.bulge)
            units.append(self._exact(render.sersic_unit_brightness(h1, h2, **kw) @ hw, kw))
        if source.disk is not None:
            d = source.disk
            u = render.disk_unit_brightness(d, h1, h2, modulation_mean) @ hw
            if d.arms is None and d.texture is None:
                u = self._exact(u, render._disk_kw(d))
            elif self.core is not None:
                # arms × texture vary slowly: the sampled modulation times the exact Sérsic
                kw = render._disk_kw(d)
                i = self.core.index
                smooth = render.sersic_unit_brightness(h1[i], h2[i], **kw) @ hw
                u = self._exact(u, kw, modulation=u[i] / jnp.maximum(
                    smooth, jnp.finfo(smooth.dtype).tiny))
            units.append(u)
        return jnp.stack(units, -1) * p.pixel_area if units else None

    def values(self, source: Source, units=None):
        """Host light at every traced pixel: (units [M, C] per unit flux, fluxes [C, B]), or
        (None, None) without a host. units: `unit_light(source)` computed before, or None."""
        units = self.unit_light(source) if units is None else units
        if units is None:
            return None, None
        fluxes = ([source.bulge.flux] if source.bulge is not None else []) + (
            [source.disk.sersic.flux] if source.disk is not None else [])
        return units, jnp.stack(fluxes, 0)

    def subgrid_light(self, source: Source, subgrids, units=None):
        units, fluxes = self.values(source, units)
        if units is None:
            return {}
        hosts = self.plane.scatter(units)
        return {g: HostStack(self.plane.to_subgrid(hosts, k, g.shape), fluxes)
                for g, k in subgrids.items()}

    def add_lens_plane(self, source: Source, image, units=None):
        """The lens-plane image [ny, nx, B] with the host set at the traced pixels."""
        units, fluxes = self.values(source, units)
        if units is None:
            return image
        return image.at[self.plane.rows, self.plane.cols].set(units @ fluxes)


class HeldHosts(Renderer):
    """A host renderer (`hosts`) with its light per unit flux (`hosts.unit_light`) computed
    before and held as data (`units`): the same images as `hosts` for any host fluxes,
    without evaluating the host profiles again. For a run that reads that light back from
    the cache folder (`lightcache`); not differentiable in the host's geometry."""

    hosts: Renderer
    units: object

    def subgrid_light(self, source: Source, subgrids):
        return self.hosts.subgrid_light(source, subgrids, self.units)

    def add_lens_plane(self, source: Source, image):
        return self.hosts.add_lens_plane(source, image, self.units)
