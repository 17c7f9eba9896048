"""Renderers of the clumps: unlensed on each band's sub-grid (Sérsic stamps, or separable
mixtures of round Gaussians: `clump_pixels = "round_gaussian"`, "exponential_mog"); in a
lensed scene analytic at every ray (`source_mode = "analytic"`), or ray-traced through a tiled
source-plane grid and, away from caustics, linearised (`"grid"`, `"hybrid"`)."""

from __future__ import annotations

import dataclasses
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import gaussian_mixtures, profiles, render, tiles
from ..errors import ConfigError
from ..lensing.linearised import ClumpImages, image_magnifications, lensed_clumps
from ..pixels import Grid
from ..source import Source
from .lensplane import LensPlane
from .renderer import BandStack, Renderer, SeparableLight, n_bands


def _unlensed_clump_groups(source: Source, pixel_arcsec: float, accuracy):
    """Stamp groups [((side, strip), indices)] of an unlensed source's clumps on a grid of
    this pixel: the exact strip for thin clumps with light beyond the exact core."""
    cl = source.clumps
    if cl is None or cl.count == 0:
        return []
    if not accuracy.thin_strip:
        return [((side, False), idx) for side, idx in render.stamp_groups(
            cl.re_arcsec, cl.n, pixel_arcsec, flux_fraction=accuracy.stamp_flux_fraction)]
    return render.strip_groups(cl.re_arcsec, cl.n, pixel_arcsec, accuracy.exact_core, q=cl.q,
                               flux_fraction=accuracy.stamp_flux_fraction)


class UnlensedClumps(Renderer):
    """Clump stamps integrated over each sub-grid's pixels: per band, stamp groups
    ((side, strip) and clump indices) on its sub-grid."""

    sides: tuple = eqx.field(static=True)
    index: tuple
    order: int = eqx.field(static=True)
    core: int = eqx.field(static=True)

    @classmethod
    def build(cls, source: Source, layouts, accuracy):
        groups = [_unlensed_clump_groups(source, lay.sub_pixel_arcsec, accuracy)
                  for lay in layouts]
        return cls(tuple(tuple(key for key, _ in g) for g in groups),
                   tuple(tuple(jnp.asarray(i) for _, i in g) for g in groups),
                   accuracy.source_order, accuracy.exact_core)

    def subgrid_light(self, source: Source, subgrids):
        cl = source.clumps
        if cl is None or cl.count == 0:
            return {}
        # every band and every sub-grid at once: one exact-pixel kernel, and bands on the
        # same grid share the stamps
        targets = [(g, tuple((side, idx, strip) for (side, strip), idx
                             in zip(self.sides[k], self.index[k]))) for g, k in subgrids.items()]
        images = render.clumps_images(cl, targets, cl.flux, order=self.order, core=self.core)
        return {g: BandStack([img], cl.flux.dtype) for (g, _), img in zip(targets, images)}

    def subgrid_light_and_grid(self, source: Source, subgrids, grid: Grid, groups, flux):
        """(`subgrid_light(source, subgrids)`, the clumps' light [ny, nx, C] on one more
        `grid` with these stamp `groups` and fluxes `flux` [N, C] (0.0 without groups)),
        their stamps made by one call: one exact-pixel kernel for both (the high-resolution
        source plane beside the unlensed bands)."""
        cl = source.clumps
        if cl is None or cl.count == 0:
            return {}, 0.0
        targets = [(g, tuple((side, idx, strip) for (side, strip), idx
                             in zip(self.sides[k], self.index[k]))) for g, k in subgrids.items()]
        stamps = render.grouped_stamps_on(cl, targets + [(grid, groups)], order=self.order,
                                          core=self.core)
        light = {g: BandStack([render.scatter_grouped(st, cl.flux, g)], cl.flux.dtype)
                 for st, (g, _) in zip(stamps, targets)}
        return light, render.scatter_grouped(stamps[-1], flux, grid)

    def magnifications(self, source: Source):
        cl = source.clumps
        return jnp.zeros(cl.count, cl.re_arcsec.dtype)


class RoundGaussianClumps(Renderer):
    """Unlensed round clumps drawn as fixed mixtures of round Gaussians integrated exactly over
    each sub-grid's pixels, with no stamps: `accuracy.clump_pixels = "round_gaussian"`
    (Sérsic n = 0.5, one Gaussian: exact) or `"exponential_mog"` (n = 1 as
    `gaussian_mixtures.EXPONENTIAL`: an approximation of stated error).

    A round Gaussian is separable: its light in pixel (i, j) is the product of its 1-D
    fractions along x in column i and along y in row j (`render.gaussian_pixel_moments`:
    erfc differences, with the moments the PSF carries), so the image of N clumps of K
    components is rows [ny, N K] · diag(flux × amplitude) · cols [nx, N K]ᵀ. The cost is
    ~2 N K (nx + ny) erfc per sub-grid, at any R_e and any centre (off the grid included),
    and a clump that grows in a fit is never cut by a stamp.

    amplitudes, sigma_per_re: the mixture (light fraction and σ / R_e of each component).
    The source's n, q and PA are not read when rendering: `build` checks that every clump is
    round with the mixture's n, and a model renders sources of the build's structure.
    Lensed scenes are out of scope (their clumps are evaluated at rays through the lens,
    not on detector sub-grids): `build_model` refuses them.
    """

    amplitudes: tuple = eqx.field(static=True)
    sigma_per_re: tuple = eqx.field(static=True)
    any_count = True

    @classmethod
    def build(cls, source: Source, clump_pixels: str = "round_gaussian"):
        n_mix, amplitudes, sigma_per_re = gaussian_mixtures.round_mixture(clump_pixels)
        cl = source.clumps
        if cl is not None and cl.count > 0:
            n, q = np.asarray(cl.n, float), np.asarray(cl.q, float)
            bad = np.nonzero((n != n_mix) | (q != 1.0))[0]
            if bad.size:
                i = int(bad[0])
                raise ConfigError(
                    "render.accuracy.clump_pixels", clump_pixels,
                    f"clumps that are all round with Sérsic n = {n_mix:g}, q = 1: {bad.size} "
                    f"of {cl.count} are not (clump {i}: n = {n[i]:g}, q = {q[i]:g}); "
                    'use clump_pixels = "sersic" for them')
        return cls(amplitudes, sigma_per_re)

    def subgrid_light(self, source: Source, subgrids):
        cl = source.clumps
        if cl is None or cl.count == 0:
            return {}
        dtype = cl.re_arcsec.dtype
        s = jnp.asarray(self.sigma_per_re, dtype)
        a = jnp.asarray(self.amplitudes, dtype)
        # clump-major [N K]: component k of clump i is row i K + k
        sigma = (cl.re_arcsec[:, None] * s[None, :]).ravel()
        c1, c2 = (jnp.repeat(cl.center_arcsec[:, j], s.size) for j in (0, 1))
        flux = (cl.flux[:, None, :] * a[None, :, None]).reshape(-1, cl.flux.shape[1])
        out = {}
        for g in subgrids:
            cols = render.gaussian_pixel_moments(g.x_edges(), c1, sigma)
            rows = render.gaussian_pixel_moments(g.y_edges(), c2, sigma)
            out[g] = SeparableLight(jnp.stack(rows).swapaxes(1, 2),
                                    jnp.stack(cols).swapaxes(1, 2), flux)
        return out

    def magnifications(self, source: Source):
        cl = source.clumps
        return jnp.zeros(cl.count, cl.re_arcsec.dtype)


class AnalyticClumps(Renderer):
    """Clumps' Sérsic light evaluated at every ray of the lens plane (the reference); where the
    plane has the rays' cell moments (`Accuracy.ray_footprint`), Gaussian clumps averaged over
    each ray's source-plane cell (`render.gaussian_clumps_cell_brightness`)."""

    plane: LensPlane
    any_count = True

    def ray_values(self, source: Source):
        """Clump flux [B, P] of the pixels with rays (counts/s), or None."""
        if source.clumps is None or source.clumps.count == 0:
            return None
        p = self.plane
        if p.ray_cov is not None:
            vals = render.gaussian_clumps_cell_brightness(source.clumps, p.beta1, p.beta2,
                                                          p.ray_cov) @ p.ray_weights
        else:
            vals = render.clumps_brightness(source.clumps, p.beta1, p.beta2) @ p.ray_weights
        return vals * p.pixel_area

    def subgrid_light(self, source: Source, subgrids):
        vals = self.ray_values(source)
        if vals is None:
            return {}
        win = self.plane.window_image(vals)
        return {g: BandStack([self.plane.window_to_subgrid(win, k, g.shape)])
                for g, k in subgrids.items()}

    def add_lens_plane(self, source: Source, image):
        vals = self.ray_values(source)
        return image if vals is None else self.plane.add_window(image,
                                                                self.plane.window_image(vals))

    def magnifications(self, source: Source):
        """Magnification [N] as this path renders each clump: its unit-flux light summed
        over every ray (one clump at a time: the memory of one clump's rays)."""
        cl = source.clumps
        p = self.plane
        b = profiles.sersic_b(cl.n)

        def one(k):
            val = render.sersic_unit_brightness(
                p.beta1, p.beta2, re_arcsec=cl.re_arcsec[k], n=cl.n[k], q=cl.q[k],
                pa_rad=cl.pa_rad[k], center1=cl.center_arcsec[k, 0],
                center2=cl.center_arcsec[k, 1], b=b[k])
            return jnp.sum(val @ p.ray_weights) * p.pixel_area

        return jax.lax.map(one, jnp.arange(cl.count))


class SourceGridClumps(eqx.Module):
    """Ray-traced clumps: stamps on a fine source-plane `grid` with a zero border of one
    pixel, stored only in the tiles some ray reads (`tiles`), read at every ray by bilinear
    interpolation. sides, index: stamp groups (side and clump indices)."""

    grid: Grid = eqx.field(static=True)
    sides: tuple = eqx.field(static=True)
    index: tuple
    slots: jnp.ndarray                          # slot of each tile of the bordered grid
    tile_layout: tiles.TileLayout = eqx.field(static=True)
    order: int = eqx.field(static=True)
    core: int = eqx.field(static=True)

    @classmethod
    def build(cls, clumps, traced, b1, b2, source_pixel_arcsec: float, accuracy):
        """The grid over the clumps `traced` (indices), tiles where the rays β (b1, b2, numpy)
        read; None without such clumps."""
        if not traced.size:
            return None
        sub = jax.tree_util.tree_map(lambda a: np.asarray(a)[traced], clumps)
        groups = [(side, traced[idx])
                  for side, idx in render.stamp_groups(sub.re_arcsec, sub.n, source_pixel_arcsec,
                                                       flux_fraction=accuracy.stamp_flux_fraction)]
        cc = np.asarray(clumps.center_arcsec, float)[traced]
        half = (max(side for side, _ in groups) / 2 + 2) * source_pixel_arcsec
        grid = Grid.covering((cc[:, 0].min() - half, cc[:, 0].max() + half),
                             (cc[:, 1].min() - half, cc[:, 1].max() + half), source_pixel_arcsec)
        # store only the tiles of the bordered grid that some ray reads
        p = grid.pixel_arcsec
        layout, slot_map = tiles.active_tiles((b1 - grid.x0_arcsec) / p + 1.0,
                                              (b2 - grid.y0_arcsec) / p + 1.0,
                                              (grid.ny + 2, grid.nx + 2))
        return cls(grid, tuple(side for side, _ in groups),
                   tuple(jax.device_put(i) for _, i in groups), jax.device_put(slot_map), layout,
                   accuracy.source_order, accuracy.exact_core)

    def groups(self):
        return tuple(zip(self.sides, self.index))

    def _store(self, stamps, flux):
        """Clump surface brightness [size, C] of C bands in the grid's stored tiles.

        The grid has a zero border of one pixel (rays beyond it read zero), hence +1.
        """
        store = None
        for st, i0, j0, idx in stamps:
            store = tiles.scatter_stamps(self.tile_layout, self.slots, st, i0 + 1, j0 + 1,
                                         flux[idx], store)
        return store / self.grid.pixel_arcsec**2

    def ray_positions(self, plane: LensPlane):
        """Rays' fractional pixel indices in the bordered grid: (x, y), [P, R] each."""
        g = self.grid
        return ((plane.beta1 - g.x0_arcsec) / g.pixel_arcsec + 1.0,
                (plane.beta2 - g.y0_arcsec) / g.pixel_arcsec + 1.0)

    def _band_chunk(self, nb: int) -> int:
        """Bands per source-plane grid: as many as fit in ~0.5 GB."""
        return int(max(1, min(nb, 5.0e8 // (8 * self.tile_layout.size))))

    def ray_values(self, source: Source, plane: LensPlane, stamps=None, block: int = 1 << 17):
        """Clump light [B, P] of the pixels with rays (surface brightness × ray weights).

        Sequential over groups of bands (one grid in memory at a time) and over blocks of
        pixels (bounded temporaries), so memory stays flat however many bands and rays a
        scene has. stamps: the clumps' unit-flux stamps on the grid, when already made.
        """
        nb = n_bands(source)
        w = plane.ray_weights
        m = plane.beta1.shape[0]
        step = self._band_chunk(nb)
        n_chunks = -(-nb // step)
        flux = jnp.pad(source.clumps.flux, ((0, 0), (0, n_chunks * step - nb)))
        flux = flux.reshape(flux.shape[0], n_chunks, step).transpose(1, 0, 2)
        n_blocks = -(-m // block)
        pad = n_blocks * block - m

        def blocks(x):
            return jnp.pad(x, ((0, pad), (0, 0))).reshape(n_blocks, block, -1)

        xs, ys = (blocks(x) for x in self.ray_positions(plane))

        # the stamps hold unit flux: made once, scattered with each group of bands' fluxes
        if stamps is None:
            stamps = render.grouped_stamps(source.clumps, self.grid, self.groups(),
                                           order=self.order, core=self.core)

        def one_chunk(f):
            store = self._store(stamps, f)

            def one_block(xy):
                vals = tiles.bilinear(self.tile_layout, self.slots, store, *xy)
                return jnp.einsum("mrc,r->mc", vals, w)

            return jax.lax.map(one_block, (xs, ys)).reshape(n_blocks * block, step)[:m]

        vals = jax.lax.map(one_chunk, flux)                      # [chunks, M, step]
        return vals.transpose(0, 2, 1).reshape(n_chunks * step, m)[:nb]

    def magnification_map(self, plane: LensPlane):
        """Lens-plane area landing on each stored source-grid pixel / that pixel's area.

        The adjoint of the ray-tracing interpolation applied to ones, in the tiled
        storage ([size]; pixels no ray reads hold 0): Σ over a clump's stamp of this
        map × its light is exactly the magnification the model gives that clump.
        """
        lay, slots = self.tile_layout, self.slots
        x, y = self.ray_positions(plane)

        def lensed_total(store):
            return jnp.sum(tiles.bilinear(lay, slots, store[:, None], x, y)[..., 0]
                           @ plane.ray_weights)

        zeros = jnp.zeros(lay.size, plane.beta1.dtype)
        grad = jax.grad(lensed_total)(zeros)
        return grad * (plane.grid.pixel_arcsec / self.grid.pixel_arcsec) ** 2

    def set_magnifications(self, out, clumps, plane: LensPlane, stamps=None):
        """out [N] with each ray-traced clump's magnification (light-weighted over its stamp).
        stamps: the clumps' unit-flux stamps on the grid, when already made."""
        mu = self.magnification_map(plane)
        if stamps is None:
            stamps = render.grouped_stamps(clumps, self.grid, self.groups(), order=self.order,
                                           core=self.core)
        # sums over each clump's stamp, which comes in tiles (`render.grouped_stamps_on`)
        lensed = jnp.zeros(out.shape, mu.dtype)
        total = jnp.zeros(out.shape, mu.dtype)
        for stamps, i0, j0, idx in stamps:
            k = jnp.arange(stamps.shape[1])
            rows = j0[:, None, None] + k[None, :, None] + 1      # +1: the grid's border
            cols = i0[:, None, None] + k[None, None, :] + 1
            at = tiles.flat_index(self.tile_layout, self.slots, rows, cols)
            lensed = lensed.at[idx].add(jnp.sum(stamps * mu[at], axis=(1, 2)))
            total = total.at[idx].add(jnp.sum(stamps, axis=(1, 2)))
        traced = jnp.concatenate(self.index)
        return out.at[traced].set(lensed[traced] / total[traced])


class LinearisedClumps(eqx.Module):
    """Clumps imaged through the local linear lens map (`lensing.linearised`), drawn straight
    on each band's sub-grid and on the lens-plane grid: their images and stamp groups
    ((side, strip) and indices) per band (`sides`, `index`) and on the lens plane."""

    images: ClumpImages
    sides: tuple = eqx.field(static=True)
    index: tuple
    hr_sides: tuple = eqx.field(static=True)
    hr_index: tuple

    @classmethod
    def build(cls, source: Source, images: ClumpImages, layouts, hr: Grid, accuracy):
        """None without images."""
        if images.count == 0:
            return None
        lensed = jax.jit(lensed_clumps)(
            jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), source.clumps),
            jax.tree_util.tree_map(lambda a: jnp.asarray(a), images))
        re = np.asarray(lensed.re_arcsec)
        n = np.asarray(lensed.n)

        def groups(pixel):
            # (side, strip) groups: the exact strip for images with light beyond the core
            g = render.strip_groups(re, n, pixel, accuracy.exact_core,
                                    flux_fraction=accuracy.stamp_flux_fraction)
            return tuple(k for k, _ in g), tuple(jax.device_put(i) for _, i in g)

        per_pixel = {}
        sides, index = [], []
        for lay in layouts:
            pix = lay.grid.pixel_arcsec / lay.oversampling
            if pix not in per_pixel:
                per_pixel[pix] = groups(pix)
            sides.append(per_pixel[pix][0])
            index.append(per_pixel[pix][1])
        hr_sides, hr_index = groups(hr.pixel_arcsec)
        return cls(images, tuple(sides), tuple(index), hr_sides, hr_index)

    def targets(self, grid: Grid, sides, index):
        return (grid, tuple((side, idx, strip) for (side, strip), idx in zip(sides, index)))


class LensedClumps(Renderer):
    """Clumps of a lensed scene in source_mode grid or hybrid: the ray-traced ones (`traced`)
    and the linearised ones (`linearised`, hybrid only). One Module for both because their
    stamps come from one exact-pixel kernel call (one compilation instead of two)."""

    plane: LensPlane
    traced: Optional[SourceGridClumps]
    linearised: Optional[LinearisedClumps]
    order: int = eqx.field(static=True)
    core: int = eqx.field(static=True)

    def _stamps(self, source: Source, grids, flux_sources=None):
        """Linearised clump images on each (grid, sides, index) of `grids` ([ny, nx, B] counts/s
        per pixel each; [] without linearised clumps) and the ray-traced clumps' stamps on the
        source grid (None without them), made in one call: one exact-pixel kernel for all.
        flux_sources: per entry of `grids`, the source (same geometry) whose clump fluxes
        that image takes; None: `source` for all."""
        cl = source.clumps
        traced = self.traced is not None and cl is not None and cl.count > 0
        lin = (lensed_clumps(cl, self.linearised.images)
               if self.linearised is not None and cl is not None else None)
        if lin is None and not traced:
            return [], None
        k = 0 if lin is None else lin.count
        sets = [c for c in (lin, cl if traced else None) if c is not None]
        both = sets[0] if len(sets) == 1 else jax.tree_util.tree_map(
            lambda a, b: jnp.concatenate([a, b]), *sets)
        targets = [] if lin is None else [self.linearised.targets(*g) for g in grids]
        if traced:   # exact cores, not strips (strip=False below)
            targets.append((self.traced.grid, tuple((side, idx + k) for side, idx
                                                    in self.traced.groups())))
        stamps = render.grouped_stamps_on(both, targets, order=self.order, core=self.core)
        if lin is not None and flux_sources is not None:
            fluxes = [lensed_clumps(s.clumps, self.linearised.images).flux for s in flux_sources]
        else:
            fluxes = [None if lin is None else lin.flux] * len(targets)
        images = ([] if lin is None else
                  [render.scatter_grouped(st, f, g) for st, (g, _), f
                   in zip(stamps, targets, fluxes)])
        return images, ([(st, i0, j0, idx - k) for st, i0, j0, idx in stamps[-1]]
                        if traced else None)

    def _window(self, source: Source, stamps):
        """Ray-traced clumps on the ray window of the lens plane [h, w, B], or None."""
        if source.clumps is None or source.clumps.count == 0 or self.traced is None:
            return None
        vals = self.traced.ray_values(source, self.plane, stamps) * self.plane.pixel_area
        return self.plane.window_image(vals)

    def _subgrid_stamps(self, source: Source, subgrids):
        """`_stamps` of the linearised clumps on the sub-grids `subgrids` ({sub-grid: index of
        its first band}) and of the ray-traced ones."""
        lin = self.linearised
        return self._stamps(source, [] if lin is None else [
            (g, lin.sides[k], lin.index[k]) for g, k in subgrids.items()])

    def subgrid_light(self, source: Source, subgrids):
        images, stamps = self._subgrid_stamps(source, subgrids)
        lin_images = dict(zip(subgrids, images))
        win = self._window(source, stamps)
        out = {}
        for g, k in subgrids.items():
            parts = ([] if win is None else [self.plane.window_to_subgrid(win, k, g.shape)])
            parts += [lin_images[g]] if g in lin_images else []
            if parts:
                out[g] = BandStack(parts)
        return out

    def add_lens_plane(self, source: Source, image):
        lin = self.linearised
        images, stamps = self._stamps(
            source, [(self.plane.grid, lin.hr_sides, lin.hr_index)]
            if lin is not None and lin.hr_sides else [])
        win = self._window(source, stamps)
        if win is not None:
            image = self.plane.add_window(image, win)
        return image + images[0] if images else image

    def light_lens_plane_and_magnifications(self, source: Source, subgrids, plane_source,
                                            image, magnify: bool):
        """(`subgrid_light(source, subgrids)`, `add_lens_plane(plane_source, image)` or None
        without plane_source, `magnifications(source)` or None without `magnify`), made
        together (plane_source: the source with other fluxes, same geometry): one stamp call
        for the sub-grids and the lens plane, whose ray-traced stamps serve all three, and
        one ray-traced pass for the bands' and the lens plane's fluxes (issue 20: each was a
        copy of its own in the band render's program)."""
        lin = self.linearised
        targets = [] if lin is None else [(g, lin.sides[k], lin.index[k])
                                          for g, k in subgrids.items()]
        sources = [source] * len(targets)
        on_plane = plane_source is not None and lin is not None and bool(lin.hr_sides)
        if on_plane:
            targets.append((self.plane.grid, lin.hr_sides, lin.hr_index))
            sources.append(plane_source)
        images, stamps = self._stamps(source, targets, sources)
        cl = source.clumps
        win = plane_win = None
        if cl is not None and cl.count > 0 and self.traced is not None:
            # the bands' and the lens plane's fluxes as one set of channels
            nb = n_bands(source)
            flux = cl.flux if plane_source is None else jnp.concatenate(
                [cl.flux, plane_source.clumps.flux.astype(cl.flux.dtype)], axis=1)
            both = Source(None, None, dataclasses.replace(cl, flux=flux))
            vals = self.traced.ray_values(both, self.plane, stamps) * self.plane.pixel_area
            win_all = self.plane.window_image(vals)
            win, plane_win = win_all[..., :nb], win_all[..., nb:]
        out = {}
        lin_images = dict(zip(subgrids, images[:len(subgrids)] if lin is not None else []))
        for g, k in subgrids.items():
            parts = ([] if win is None else [self.plane.window_to_subgrid(win, k, g.shape)])
            parts += [lin_images[g]] if g in lin_images else []
            if parts:
                out[g] = BandStack(parts)
        plane = None
        if plane_source is not None:
            plane = image if plane_win is None else self.plane.add_window(image, plane_win)
            plane = plane + images[-1] if on_plane else plane
        mags = None
        if magnify and cl is not None:
            mags = jnp.zeros(cl.count, cl.re_arcsec.dtype)
            if lin is not None:
                mags = mags.at[lin.images.clump_index].add(
                    image_magnifications(lin.images, mags.dtype))
            if self.traced is not None:
                mags = self.traced.set_magnifications(mags, cl, self.plane, stamps)
        return out, plane, mags

    def magnifications(self, source: Source, subgrids=None):
        """Magnification [N] of each clump within the field (light-weighted over its stamp).

        subgrids: the sub-grids of `subgrid_light` in the same program: the ray-traced
        clumps' stamps are then made as that makes them (`_subgrid_stamps`, the same
        computation, which XLA computes once for both), not by a kernel of their own."""
        cl = source.clumps
        out = jnp.zeros(cl.count, cl.re_arcsec.dtype)
        if self.linearised is not None:
            # a linearised clump: Σ |μ| over its images (each wholly inside the field)
            images = self.linearised.images
            out = out.at[images.clump_index].add(image_magnifications(images, out.dtype))
        if self.traced is None:
            return out
        stamps = None if subgrids is None else self._subgrid_stamps(source, subgrids)[1]
        return self.traced.set_magnifications(out, cl, self.plane, stamps)

    def source_magnification_map(self):
        return self.traced.magnification_map(self.plane)
