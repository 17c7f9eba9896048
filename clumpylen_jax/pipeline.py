"""From a scene to images on disk: the `clumpylen simulate` job.

`prepare(scene)` makes everything the model needs (clump catalogue, fluxes per
band, lens, PSFs, the compiled-on-first-use `SceneModel`); `run(prepared)`
evaluates it; `simulate(scene, out_dir)` does both and writes the outputs of
SCENE.md. Stochastic parts use the scene's seed only: NumPy's generator for the
population, `jax.random.key(seed)` for noise; the same seed gives the same files.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import __version__, cosmology as cosmo_mod, io, model as model_mod, modelcache, photometry
from . import programcache
from . import profiles, render, rgbimage, rundir, scene as scene_mod
from .builders import model_band
from .cache import cache_enabled, cache_root, read_ahead
from .errors import ConfigError
from .model.clumps import UnlensedClumps
from .model.renderer import first_band_per_subgrid
from .source import Clumps, Disk, Sersic, Source, SpiralArms, Texture
from .timing import StageClock


# ------------------------------------------------------------------ progress


class _Progress:
    """A one-line progress display on a terminal; silent otherwise."""

    def __init__(self, enabled: bool, total: int):
        self.enabled = enabled and sys.stderr.isatty()
        self.total = max(total, 1)
        self.done = 0
        self.timings: dict[str, float] = {}
        self.clock = StageClock()       # each stage's compile / run split

    def stage(self, name: str):
        progress = self

        class _Stage:
            def __enter__(self):
                self.clocked = progress.clock.stage(name)
                self.clocked.__enter__()
                self.t0 = time.perf_counter()
                if progress.enabled:
                    bar = "#" * int(30 * progress.done / progress.total)
                    sys.stderr.write(f"\r[{bar:<30}] {name:<40}")
                    sys.stderr.flush()

            def __exit__(self, *exc):
                progress.timings[name] = round(time.perf_counter() - self.t0, 4)
                self.clocked.__exit__(*exc)
                progress.done += 1
                if progress.enabled and progress.done >= progress.total:
                    sys.stderr.write("\r" + " " * 75 + "\r")
                    sys.stderr.flush()

        return _Stage()


# ------------------------------------------------------------------ the prepared scene


@dataclasses.dataclass
class Prepared:
    """Everything a scene needs, made once: see `prepare`."""

    scene: scene_mod.Scene
    source: Source
    catalog: object                 # astropy Table of clumps (possibly empty)
    lens: object                    # lens object or None
    bands: list                     # model.Band per scene band
    zeropoints: dict                # filter -> ZP (AB)
    field_arcsec: Optional[tuple]
    model: model_mod.SceneModel
    accuracy: model_mod.Accuracy
    dtype: object
    host_masses_msun: dict
    timings: dict
    programs: object = None         # programs folder, a programcache.ReadAhead of it, or None
    # the textured disk's `render.disk_modulation_mean` (float64; None: no textured disk),
    # computed once by `prepare` and given to every host-light program
    modulation_mean: object = None
    # writes cache files in the background (`modelcache.pickled`'s submit), or None
    cache_submit: object = None


def _cosmology(scene):
    return cosmo_mod.scene_cosmology(scene)


def _accuracy(scene) -> model_mod.Accuracy:
    a = scene.render.accuracy
    base = model_mod.ACCURACY_PRESETS[a.preset]
    return dataclasses.replace(base, lens_subsampling=a.subsampling,
                               psf_oversampling=a.psf_oversampling, source_mode=a.source_mode,
                               linearise_tolerance=a.linearise_tolerance,
                               source_flux_fraction=a.source_flux_fraction)


def build_lens(scene, cosmology=None):
    """The scene's lens object (None for an unlensed scene)."""
    if scene.lens is None:
        return None
    return lens_object(scene.lens, scene.z_source, cosmology or _cosmology(scene))


def lens_object(L, z_source: float, cosmology):
    """The lens object (`deflection(θ1, θ2)`, arcsec) of a parsed `scene.Lens` for a source at
    z_source: a built-in model, deflection maps placed about L.center_radec_deg, or the sum of
    analytic components."""
    if L.model is not None:
        from .lensing.clusters import builtin_lens
        return builtin_lens(L.model, z_source, cosmology=cosmology)
    if L.deflection is not None:
        from .lensing.fits import load_deflection_maps
        norm = ("dls_ds" if L.deflection.normalization_z_source is None
                else {"z_source": L.deflection.normalization_z_source})
        return load_deflection_maps(L.deflection.x, L.deflection.y,
                                    lens_center_radec_deg=L.center_radec_deg, z_lens=L.z_lens,
                                    z_source=z_source, normalization=norm,
                                    cosmology=cosmology)
    from .lensing.analytic import LensSum
    from .lensing.clusters import lens_component
    # a dpie given by σ0 takes the scene's D_ls/D_s (DPIE.from_sigma)
    ratio = (cosmo_mod.dls_ds(L.z_lens, z_source, cosmology)
             if any("sigma0_kms" in c.params for c in L.components) else 1.0)
    lenses = [lens_component({"kind": c.kind, **c.params}, f"lens.components[{i}]", dls_ds_ratio=ratio)
              for i, c in enumerate(L.components)]
    return lenses[0] if len(lenses) == 1 else LensSum(tuple(lenses))


def _f(x, dtype):
    return jnp.asarray(x, dtype)


def _host_pytrees(scene, dtype):
    """Unit-geometry host pytrees (flux placeholder 1) for positions and extents."""
    src = scene.source
    c = _f(src.center_arcsec, dtype)
    bulge = disk = None
    if src.bulge is not None:
        b = src.bulge
        bulge = Sersic(_f([1.0], dtype), _f(b.re_arcsec, dtype), _f(b.n, dtype), _f(b.q, dtype),
                       _f(b.pa_rad, dtype), c)
    if src.disk is not None:
        d = src.disk
        arms = tex = None
        if d.arms is not None:
            a = d.arms
            arms = SpiralArms(int(a.count), _f(a.amplitude, dtype), _f(a.winding, dtype),
                              _f(a.phase_rad, dtype), _f(a.scale_arcsec, dtype),
                              _f(a.orientation_rad, dtype))
        if d.texture is not None:
            t = d.texture
            tex = Texture(_f(t.amplitude, dtype), _f(t.scale_arcsec, dtype), int(t.octaves),
                          # seeds up to 2**63: fold to 32 bits (those below 2**32 unchanged)
                          jnp.asarray((scene.seed ^ (scene.seed >> 32)) & 0xFFFFFFFF, jnp.uint32))
        disk = Disk(Sersic(_f([1.0], dtype), _f(d.re_arcsec, dtype), _f(d.n, dtype),
                           _f(d.q, dtype), _f(d.pa_rad, dtype), c),
                    _f(d.inclination_rad, dtype), arms, tex)
    return bulge, disk


def _component_mags(comp, mass_msun, filters, zps, scene, cosmology):
    """AB magnitude per band of a host component: given magnitudes first, SPS for the rest."""
    mags = {}
    need = [f for f in filters if f not in comp.magnitudes]
    for f in filters:
        if f in comp.magnitudes:
            mags[f] = float(comp.magnitudes[f])
    if need:
        if mass_msun is None:
            raise ConfigError("source component magnitudes", sorted(comp.magnitudes),
                              f"magnitudes for every band ({', '.join(filters)}) or a mass_msun")
        if mass_msun <= 0:
            for f in need:
                mags[f] = math.inf
        else:
            m = photometry.ab_magnitudes(mass_msun, comp.age_myr, filters=need, z=scene.z_source,
                                         metallicity=comp.metallicity, sfh=comp.sfh.kind,
                                         sfh_duration_myr=comp.sfh.duration_myr or 0.0,
                                         cosmology=cosmology)
            for f, v in zip(need, np.asarray(m)):
                mags[f] = float(v)
    return mags


def _chunked_calls(programs, name, fun, baked, chunk=1 << 16):
    """A numpy function (x, y) -> fun(baked, x, y), evaluated in zero-padded chunks of one
    shape by one program (`programcache.function`), loaded or compiled once."""
    pad = jnp.zeros(chunk, jnp.float64)
    # "light": its runs (the population's few chunks) cost next to nothing
    fn = programcache.function(name, fun, pad, pad, folder=programs, baked=baked,
                               quick_compile="light")

    def call(x, y):
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        flat_x, flat_y = x.ravel(), y.ravel()
        out = np.empty(flat_x.size)
        for s in range(0, flat_x.size, chunk):
            n = min(chunk, flat_x.size - s)
            px = np.zeros(chunk)
            py = np.zeros(chunk)
            px[:n] = flat_x[s:s + n]
            py[:n] = flat_y[s:s + n]
            out[s:s + n] = np.asarray(fn(jnp.asarray(px), jnp.asarray(py)))[:n]
        return out.reshape(x.shape)
    return call


def _disk_brightness(baked, x, y):
    disk, mean = baked
    return render.disk_unit_brightness(disk, x, y, mean)


def _sample_catalog(scene, bulge, disk, cosmology, programs, modulation_mean):
    """The clump catalogue (astropy Table) and the host masses left after clumps
    (modulation_mean: the disk's, `_modulation_mean`)."""
    from . import population
    src = scene.source
    cl = src.clumps
    masses = {"bulge": src.bulge.mass_msun if src.bulge is not None else None,
              "disk": src.disk.mass_msun if src.disk is not None else None}
    if cl is None:
        return None, masses
    scale = cosmo_mod.arcsec_per_pc(scene.z_source, cosmology)
    if cl.catalog is not None:
        table = population.read_clump_catalog(cl.catalog, arcsec_per_pc=scale,
                                              bands=list(scene.band_names),
                                              sersic_n_default=cl.sersic_n)
        return table, masses
    host_name = cl.host
    host_tree = disk if host_name == "disk" else bulge
    host_cfg = src.disk if host_name == "disk" else src.bulge
    if host_tree is None or host_cfg is None:
        raise ConfigError("source.clumps.host", host_name, "a component present in the source")
    if host_cfg.mass_msun is None:
        raise ConfigError(f"source.{host_name}.mass_msun", None,
                          "the host's mass (clumps take mass_fraction of it)")
    # programs kept in the cache folder (`_program`): a warm run neither traces nor lowers
    # them. The host's arrays are baked into the brightness, as a jit's closure has them.
    if host_name == "disk":
        brightness = _chunked_calls(programs, "population.disk_brightness", _disk_brightness,
                                    (host_tree, modulation_mean))
        geo = host_tree.sersic
    else:
        brightness = _chunked_calls(programs, "population.sersic_brightness",
                                    render.sersic_component_brightness, host_tree)
        geo = host_tree
    radius = float(profiles.sersic_radius_enclosing_np(0.999, geo.re_arcsec, geo.n))
    c = np.asarray(geo.center_arcsec, float)
    bbox = ((c[0] - radius, c[0] + radius), (c[1] - radius, c[1] + radius))
    rng = np.random.default_rng(scene.seed)
    config = population.clump_config_from_scene(dataclasses.asdict(cl))
    table = population.sample_clumps(
        rng, host_mass_msun=float(host_cfg.mass_msun), mass_fraction=float(cl.mass_fraction),
        host_brightness=brightness,
        bbox_arcsec=bbox, arcsec_per_pc=scale, config=config)
    masses[host_name] = float(table.meta["host_mass_remaining_msun"])
    return table, masses


def _clump_mags(scene, table, filters, cosmology):
    """[N, B] AB magnitudes of the clumps: catalogue columns first, SPS for the rest."""
    cl = scene.source.clumps
    n = len(table)
    mags = np.full((n, len(filters)), np.nan)
    for k, f in enumerate(filters):
        col = f"mag_{f}"
        if col in table.colnames:
            mags[:, k] = np.asarray(table[col], float)
    missing = [k for k in range(len(filters)) if np.any(np.isnan(mags[:, k]))]
    if missing and n:
        need = [filters[k] for k in missing]
        m = photometry.ab_magnitudes(np.asarray(table["mass_msun"], float),
                                     np.asarray(table["age_myr"], float), filters=need,
                                     z=scene.z_source, metallicity=cl.metallicity, sfh=cl.sfh.kind,
                                     sfh_duration_myr=cl.sfh.duration_myr or 0.0,
                                     cosmology=cosmology)
        m = np.asarray(m)
        for j, k in enumerate(missing):
            fill = np.isnan(mags[:, k])
            mags[fill, k] = m[fill, j]
    return mags


def _bands(scene, accuracy):
    """model.Band per scene band, with PSFs resolved."""
    return [model_band(b, accuracy, base_dir=scene.base_dir, setting=f"bands[{i}]")
            for i, b in enumerate(scene.bands)]


def _bands_stage(scene, accuracy, progress):
    with progress.stage("bands and PSFs"):
        return _bands(scene, accuracy)


def _zeropoints(scene) -> dict:
    """filter -> zero point (AB) of the scene's bands."""
    return {b.filter: float(b.zeropoint_ab) for b in scene.bands}


def _field(scene, lens, source, accuracy):
    """The lens-plane field: the scene's, or where the source lands (lensed scenes)."""
    f = scene.render.field_arcsec
    if f is not None:
        return (tuple(f.x), tuple(f.y))
    if lens is None:
        return None
    from .lensing.images import lens_plane_region
    center, radius = model_mod.source_extent(source, accuracy.source_flux_fraction,
                                             accuracy.stamp_flux_fraction)
    reach = 60.0 + abs(center[0]) + abs(center[1])
    return lens_plane_region(lens, center, radius,
                             search_field=((-reach, reach), (-reach, reach)),
                             pixel_arcsec=0.25, margin_arcsec=0.5)


def _population_and_photometry(scene, filters, zps, cosmology, dtype, progress, programs):
    """The clump catalogue, the host masses left after clumps, the source with its
    fluxes per band and the disk's modulation mean (`_modulation_mean`)."""
    bulge_t, disk_t = _host_pytrees(scene, jnp.float64)
    with progress.stage("population"):
        mean = _modulation_mean(programs, disk_t)
        table, host_masses = _sample_catalog(scene, bulge_t, disk_t, cosmology, programs, mean)
    with progress.stage("photometry"):
        src = scene.source
        bulge = disk = clumps = None
        if src.bulge is not None:
            mags = _component_mags(src.bulge, host_masses["bulge"], filters, zps, scene, cosmology)
            flux = photometry.mags_to_counts_per_s_or_zero([mags[f] for f in filters], [zps[f] for f in filters])
            bulge = dataclasses.replace(bulge_t, flux=jnp.asarray(flux, jnp.float64))
        if src.disk is not None:
            mags = _component_mags(src.disk, host_masses["disk"], filters, zps, scene, cosmology)
            flux = photometry.mags_to_counts_per_s_or_zero([mags[f] for f in filters], [zps[f] for f in filters])
            disk = dataclasses.replace(
                disk_t, sersic=dataclasses.replace(disk_t.sersic, flux=jnp.asarray(flux, jnp.float64)))
        if table is not None and len(table):
            cm = _clump_mags(scene, table, filters, cosmology)
            for k, f in enumerate(filters):
                table[f"mag_{f}"] = cm[:, k]
            flux = photometry.mags_to_counts_per_s_or_zero(cm, [zps[f] for f in filters])
            clumps = Clumps(
                jnp.asarray(np.stack([table["beta1_arcsec"], table["beta2_arcsec"]], axis=1), float),
                jnp.asarray(flux), jnp.asarray(np.asarray(table["re_arcsec"], float)),
                jnp.asarray(np.asarray(table["sersic_n"], float)),
                jnp.asarray(np.asarray(table["q"], float)),
                jnp.asarray(np.asarray(table["pa_rad"], float)))
        source = Source(bulge, disk, clumps).astype(dtype)
    return table, host_masses, source, mean


def prepare(scene: scene_mod.Scene, *, progress: Optional[_Progress] = None,
            programs=None, on_source=None, cache_submit=None) -> Prepared:
    """Population, photometry, lens, PSFs and the model of a scene (no rendering yet).

    programs: where compiled programs are kept (`programcache`: a folder or a `ReadAhead`
    of it); None: the cache folder's programs/ unless the cache is off.
    on_source: called with a `Prepared` whose lens, field and model are still None as soon
    as the source, its catalogue and the bands are made, before the lens is traced (so
    that work which needs no lens, e.g. compiling the unlensed programs, overlaps it).
    cache_submit: writes the cache folder's models and light in the background
    (`modelcache.pickled`); None: written as they are made."""
    progress = progress or _Progress(False, 1)
    programs = _program_folder() if programs is None else programs
    model_mod.require_float64_mode(scene.render.dtype)
    cosmology = _cosmology(scene)
    accuracy = _accuracy(scene)
    dtype = jnp.float32 if scene.render.dtype == "float32" else jnp.float64
    filters = list(scene.band_names)

    zps = _zeropoints(scene)
    # The PSFs (poppy's transforms in NumPy, ~1.5 s of one core per band when not cached)
    # are made in a thread of their own while this one samples the clumps and their
    # photometry (mostly XLA compiling, which leaves the GIL): on 2 cores the two overlap.
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="clumpylen-psf") as pool:
        later_bands = pool.submit(_bands_stage, scene, accuracy, progress)
        table, host_masses, source, mean = _population_and_photometry(
            scene, filters, zps, cosmology, dtype, progress, programs)
        with progress.stage("bands and PSFs (wait)"):
            bands = later_bands.result()
    if on_source is not None:
        on_source(Prepared(scene, source, table, None, bands, zps, None, None, accuracy, dtype,
                           host_masses, progress.timings, programs, mean, cache_submit))
    with progress.stage("lens"):
        lens = build_lens(scene, cosmology)
        field = _field(scene, lens, source, accuracy)
        # the field is known now: refuse a scene too big for memory before tracing it
        from .preflight import check_memory
        check_memory(scene, field_arcsec=field, n_clumps=0 if table is None else len(table))
    with progress.stage("model (ray tracing)" if lens is not None else "model"):
        rays = cache_root() / "rays" if cache_enabled() else None
        model = modelcache.build(
            lambda *a, **k: model_mod.build_model(*a, ray_cache=rays, **k), source, bands,
            lens=lens, folder=cache_root() / "models" if cache_enabled() else None,
            submit=cache_submit,
            field_arcsec=field, lens_pixel_arcsec=scene.render.lens_pixel_arcsec,
            source_pixel_arcsec=scene.render.source_pixel_arcsec, accuracy=accuracy, dtype=dtype)
    return Prepared(scene, source, table, lens, bands, zps, field, model, accuracy, dtype,
                    host_masses, progress.timings, programs, mean, cache_submit)


# ------------------------------------------------------------------ running and writing


def _program_folder():
    return cache_root() / "programs" if cache_enabled() else None


def _modulation_mean(programs, disk):
    """`render.disk_modulation_mean(disk)` by a program of its own (None: no textured disk).
    `prepare` calls it once and keeps the value in `Prepared.modulation_mean`: the
    population and every host-light program take it as an input (issue 20: each held a copy
    of its quadrature, ~5k lines of optimised HLO)."""
    if disk is None or disk.texture is None:
        return None
    # the mean does not depend on the fluxes: one program and value for any bands
    disk = dataclasses.replace(disk, sersic=dataclasses.replace(
        disk.sersic, flux=jnp.zeros(1, jnp.result_type(disk.sersic.re_arcsec))))
    return _program(programs, "population.disk_modulation_mean", render.disk_modulation_mean,
                    disk, quick_compile="light")


def _mean_for(prep: "Prepared"):
    """The modulation mean in the dtype of the scene's source (a float32 scene's host-light
    programs stay float32)."""
    mean = prep.modulation_mean
    return None if mean is None else jnp.asarray(mean, prep.dtype)


def _program(programs, name: str, fun, *args, quick_compile=False):
    """fun(*args) as one program (arrays traced, every other leaf static); its executable
    kept between runs in `programs` (`programcache`: a folder, a `ReadAhead`, or None).
    quick_compile: `programcache.QUICK_COMPILE` (a program that runs once), "light":
    `programcache.LIGHT_COMPILE` (one whose run costs next to nothing)."""
    return programcache.call(name, fun, *args, folder=programs, quick_compile=quick_compile)


def _with_host_light(programs, model, source: Source, modulation_mean=None, extra_grids=(),
                     submit=None):
    """The model with its host's light per unit flux held (`SceneModel.with_host_light`):
    computed by a program of its own, or read back from the cache folder (`lightcache`:
    it depends on the host's geometry and the grids only). A source without host: the
    model itself. modulation_mean: the textured disk's (`_mean_for`), None without one.
    extra_grids (unlensed models only): more grids whose host light the same program makes
    (`UnlensedHosts.unit_light`); returns (model, their light) then. submit: writes the
    kept light in the background (`Prepared.cache_submit`)."""
    if source.bulge is None and source.disk is None:
        return (model, [(None, None)] * len(extra_grids)) if extra_grids else model
    # what the light depends on, and no more (the key hashes every array it is given):
    # the host renderer (the traced pixels), the sub-grids and the host
    subgrids = tuple(first_band_per_subgrid(model.layouts).items())
    args = (model.hosts, subgrids, Source(source.bulge, source.disk, None), modulation_mean)
    if not extra_grids:
        # run once per scene (then kept by `lightcache`): compiled quickly in 2.6–3.1 s
        # instead of 4.1–6.4 s, its run 0.6–2.4 s either way (not so the unlensed grids'
        # program below: its run took 4× longer compiled quickly; "light" compiled 0.5–0.9 s
        # faster and ran 1 s longer)
        return model.with_host_light(_kept_light(programs, "host_unit_light", _host_unit_light,
                                                 *args, quick_compile=True, submit=submit))
    units = _kept_light(programs, "host_unit_light_and_grids", _host_unit_light_and_grids,
                        *args, tuple(extra_grids), submit=submit)
    return model.with_host_light(units[:len(subgrids)]), units[len(subgrids):]


def _held_light_placeholder(prep: Prepared, model):
    """`_with_host_light(..., model, prep.source, ...)`'s model with zeros in place of the
    held light (same pytree, shapes and dtypes: the same program), found by tracing alone;
    the model itself for a source without host."""
    source = prep.source
    if source.bulge is None and source.disk is None:
        return model
    subgrids = tuple(first_band_per_subgrid(model.layouts).items())
    shapes = eqx.filter_eval_shape(_host_unit_light, model.hosts, subgrids,
                                   Source(source.bulge, source.disk, None), _mean_for(prep))
    return model.with_host_light(jax.tree_util.tree_map(
        lambda s: np.zeros(s.shape, s.dtype), shapes))


def _host_unit_light(hosts, subgrids, source: Source, modulation_mean=None):
    return hosts.unit_light(source, dict(subgrids), modulation_mean)


def _host_unit_light_and_grids(hosts, subgrids, source: Source, modulation_mean, grids):
    return hosts.unit_light(source, dict(subgrids), modulation_mean, extra_grids=grids)


def _kept_light(programs, name: str, fun, *args, quick_compile=False, submit=None):
    """fun(*args) (light per unit flux) as one program, kept between runs in the cache
    folder (`lightcache`) unless it is off."""
    from . import lightcache
    folder = cache_root() / "light" if cache_enabled() else None
    return lightcache.kept(name, lambda: _program(programs, name, fun, *args,
                                                  quick_compile=quick_compile), args, folder,
                          submit)


def _jit_call(programs, model, method: str, *args):
    """Compile and call a SceneModel method (the model's arrays are traced, not hashed),
    compiled quickly: a run calls it once."""
    return _program(programs, f"SceneModel.{method}", lambda m, *a: getattr(m, method)(*a),
                    model, *args, quick_compile=True)


def _wcs_for(grid, scene):
    """TAN WCS of a grid (θ or β frame, arcsec) about the lens centre.

    Unlensed grids use the same reference, so β offsets read as sky offsets from
    it; a scene without a lens has no sky position and is placed at RA = Dec = 0.
    """
    lens = scene.lens
    ref = lens.center_radec_deg if lens is not None and lens.center_radec_deg is not None \
        else (0.0, 0.0)
    return io.make_wcs(ref, grid.pixel_arcsec, grid.shape, (grid.x0_arcsec, grid.y0_arcsec))


def _header(scene, band, zp, seed):
    return {"TELESCOP": band.telescope, "INSTRUME": band.camera, "FILTER": band.filter,
            "EXPTIME": float(band.exptime_s or 0.0), "ZP_AB": float(zp),
            "PIXSCALE": float(band.pixel_arcsec), "SKYLEVEL": float(band.sky_counts_per_s),
            "SEED": int(seed), "BUNIT": "counts/s"}


def _rgb_channels(images, grids, triple):
    """Three images on the first one's grid, as surface brightness (rebinned where needed)."""
    from .pixels import rebin, rebin_operators
    g0 = grids[triple[0]]
    out = []
    for f in triple:
        img, g = images[f], grids[f]
        if g != g0:
            wy, wx = rebin_operators(g, g0)
            img = np.asarray(rebin(jnp.asarray(img), wy, wx))
        out.append(np.asarray(img) / g0.pixel_arcsec**2)
    return out


def simulate(scene, out_dir, *, bands=None, seed=None, noise=None, progress=True,
             programs=None) -> dict:
    """Simulate `scene` (a Scene, a built-in name or a path) and write SCENE.md's outputs in out_dir.

    The run is written aside and swapped into out_dir whole, with a manifest.json
    (`rundir.run_directory`): no file of an earlier or interrupted run is left beside it.
    programs: a `programcache.ReadAhead` started earlier for this scene (`cache.read_ahead`;
    the command line starts it before its imports); None: started here.
    Returns the summary (also written to summary.json).
    """
    with rundir.run_directory(out_dir) as run:
        summary = _simulate_into(scene, run.path, bands=bands, seed=seed, noise=noise,
                                 progress=progress, programs=programs)
        run.meta.update(seed=summary["seed"], scene=summary["scene"]["scene"]["name"],
                        version=__version__)
    return summary


def _simulate_into(scene, out_dir, *, bands=None, seed=None, noise=None, progress=True,
                   programs=None) -> dict:
    """`simulate` into a directory of its own (the run directory's temporary sibling)."""
    if not isinstance(scene, scene_mod.Scene):
        scene = scene_mod.load_scene(scene)
    scene = scene_mod.with_overrides(scene, seed=seed, bands=bands, noise=noise)
    out = Path(out_dir)
    n_stages = 7 + len(scene.bands) + 10
    prog = _Progress(progress, n_stages)
    t_start = time.perf_counter()
    if programs is None:
        programs = read_ahead(scene)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bands").mkdir(exist_ok=True)
    # The programs besides the band render (unlensed bands, high-resolution images, clump
    # magnifications) are loaded or compiled and launched in a background thread while this
    # one traces the lens and runs and writes the band render: JAX runs them asynchronously,
    # so their loading, compilation and running overlap the main thread's work. Same
    # programs, same inputs: the same images as one after the other. Those that need no
    # lens (unlensed, high-resolution source plane) are launched as soon as the source is
    # made (`_launch_unlensed_early`), so that a first run compiles them while the lens is
    # traced.
    # The high-resolution products are written by a thread of their own (their FITS files
    # and colour arrays beside the band files; figures are drawn one at a time).
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="clumpylen-launch")
    writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="clumpylen-write-hr")
    # the cache folder's models and light are written by a thread of their own: the light
    # is written once its program has run, while this thread goes on (a cold run waited
    # for it before it traced the band render)
    cache_writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="clumpylen-cache")
    cache_writes = []

    def cache_submit(fn, *args):
        cache_writes.append(cache_writer.submit(fn, *args))

    early = {}
    try:
        prep = prepare(scene, progress=prog, programs=programs, cache_submit=cache_submit,
                       on_source=lambda src: early.update(_launch_early(src, prog, pool, out)))
        return _simulate_launched(prep, prog, pool, writer, out, t_start, early, cache_writes)
    finally:
        writer.shutdown(wait=True, cancel_futures=True)
        pool.shutdown(wait=True, cancel_futures=True)
        cache_writer.shutdown(wait=True)


def _launch_early(prep: Prepared, prog: _Progress, pool, out: Path) -> dict:
    """The launches that need no lens, submitted to `pool` from a `prepare` whose lens and
    model are not made yet: {"unlensed": future or None, "hr": (the high-resolution source
    as `_hr_source` gives it, its future) or None}."""
    scene = prep.scene
    hr = sgrid = None
    if scene.output.hr:
        with prog.stage("high-resolution photometry"):
            hr = _hr_source(prep)
            sgrid = _hr_grid(prep, hr[0])
        (out / "hr").mkdir(exist_ok=True)
    # with both asked for, the unlensed bands' programs make the high-resolution source
    # plane too (`_launch_unlensed`); with one of them, its own programs only
    later_unl = (pool.submit(_launch_unlensed, prep, prog,
                             None if hr is None else (hr[0], sgrid))
                 if scene.output.unlensed else None)
    return {"unlensed": later_unl,
            "hr": None if hr is None else (hr, pool.submit(
                _launch_hr, prep, prog, hr, sgrid, later_unl))}


def _launch_unlensed(prep: Prepared, prog: _Progress, hr=None):
    """(the unlensed band model, its images, the high-resolution source plane's images or
    None), launched, not waited for. hr: (the high-resolution source, its grid) or None.
    With it, the same programs make the source plane (the same profiles on one more grid):
    the host's light on it by the bands' host-light program, and with Sérsic clump stamps
    their stamps by one call for both (`SceneModel.band_images_and_clumps_on`): two
    programs and ~13k lines of optimised HLO fewer than apart (`_hr_source_plane`)."""
    with prog.stage("unlensed images (launch)"):
        # kept like the lensed model (`modelcache`): its PSF kernels and their transforms
        # are resampled and transformed again on every run otherwise (~0.5 s of CPU)
        unl_model = modelcache.build(
            model_mod.build_model, prep.source, prep.bands, lens=None,
            folder=cache_root() / "models" if cache_enabled() else None,
            submit=prep.cache_submit,
            accuracy=prep.accuracy, dtype=prep.dtype)
        src = prep.source
        if hr is None or (src.bulge is None and src.disk is None and src.clumps is None):
            return (unl_model, _jit_call(prep.programs, _with_host_light(
                prep.programs, unl_model, src, _mean_for(prep), submit=prep.cache_submit),
                'band_images', src), None)
        mono, sgrid = hr
        hr_host = (None, None)
        if src.bulge is not None or src.disk is not None:
            held, (hr_host,) = _with_host_light(prep.programs, unl_model, src, _mean_for(prep),
                                                (sgrid,), submit=prep.cache_submit)
            bulge, disk = hr_host
            if disk is not None:   # as `render.disk_image`: the values × the pixel area
                scale = render.disk_image_scale(src.disk, sgrid)
                disk = np.asarray(disk) if scale == 1.0 else np.asarray(disk) * scale
            hr_host = (bulge, disk)
        else:
            held = unl_model
        groups = _hr_groups(prep, mono, sgrid)
        if groups and isinstance(unl_model.clumps, UnlensedClumps):
            images, plane = _program(prep.programs, "unlensed_and_source_plane",
                                     _unlensed_and_source_plane, held, src, mono, hr_host,
                                     sgrid, prep.accuracy, groups, quick_compile=True)
            return unl_model, images, plane
        return (unl_model, _jit_call(prep.programs, held, 'band_images', src),
                _program(prep.programs, "source_plane_images", _source_plane_images, mono,
                         hr_host, sgrid, prep.accuracy, groups, quick_compile=True))


def _unlensed_and_source_plane(model, source, mono, host, grid, accuracy, groups):
    """(the unlensed band images, the source-plane images of `mono` on `grid`) as one
    program: the clumps' stamps of both by one call."""
    bands, clumps = model.band_images_and_clumps_on(source, grid, groups, mono.clumps.flux)
    return bands, _source_plane_images(mono, host, grid, accuracy, (),
                                       jnp.moveaxis(clumps, -1, 0))


def _write_hr_unlensed_stage(prep, prog, out, hr, later_hr):
    with prog.stage("high-resolution images (unlensed)"):
        return _write_hr_unlensed(prep, out, hr, later_hr)


def _write_hr_lensed_stage(prep, prog, out, hr, hr_lensed):
    with prog.stage("high-resolution images (lensed)"):
        _write_hr_lensed(prep, out, hr, hr_lensed)


def _simulate_launched(prep: Prepared, prog: _Progress, pool, writer, out: Path, t_start,
                       early: dict, cache_writes=()) -> dict:
    """The stages of `simulate` after `prepare`: programs launched in `pool` (those that
    need no lens already, `early`: `_launch_early`'s), the high-resolution products written
    by `writer`, the rest here; returns the summary. cache_writes: futures of the cache
    files written in the background, waited for before the summary."""
    scene, model, table = prep.scene, prep.model, prep.catalog
    # the writer thread imports what writing needs, off the main thread's path, then writes
    # the high-resolution unlensed products as soon as the source plane is done (during the
    # band render) and the lensed ones after the band render
    writer.submit(_import_writing_modules, bool(scene.output.rgb or scene.output.hr))
    later_unl = early.get("unlensed")
    hr, later_hr = early.get("hr") or (None, None)
    hr_written = (writer.submit(_write_hr_unlensed_stage, prep, prog, out, hr, later_hr)
                  if later_hr is not None else None)
    later_noise = pool.submit(_noise_program, prep, prog) if scene.output.noise else None
    with prog.stage("render (compile + run)"):
        (noisy, clean, var), hr_lensed, mags = _render_bands(prep, hr, later_noise)
    lensed_written = (writer.submit(_write_hr_lensed_stage, prep, prog, out, hr, hr_lensed)
                      if hr_lensed is not None else None)
    unlensed, unl_model = [None] * len(scene.bands), None
    if later_unl is not None:
        with prog.stage("unlensed images"):
            unl_model, unl_images, _ = later_unl.result()
            unlensed = [np.asarray(x) for x in unl_images]
    summary_bands, grids = {}, {}
    for k, b in enumerate(scene.bands):
        with prog.stage(f"write {b.filter}"):
            grids[b.filter] = model.layouts[k].grid
            summary_bands[b.filter] = _write_band(out, prep, k, noisy[k], clean[k], var[k],
                                                  unlensed[k], unl_model)
    with prog.stage("colour composites"):
        _write_composites(out, prep, noisy if scene.output.noise else clean, clean, grids)
    hr_info = None
    if hr_written is not None:
        with prog.stage("high-resolution images (wait)"):
            hr_info = hr_written.result()
            if lensed_written is not None:
                lensed_written.result()
    with prog.stage("catalogue"):
        table = _write_catalogue(out, prep, mags)
    with prog.stage("cache files (wait)"):
        for done in cache_writes:       # a failed write fails the run, as one in line did
            done.result()
    summary = _summary(prep, summary_bands, table, hr_info)
    summary["timings_s"] = dict(prog.timings, total=round(time.perf_counter() - t_start, 3))
    summary["timings_split_s"] = prog.clock.split()
    summary["accuracy"] = dataclasses.asdict(prep.accuracy)
    io.write_json(out / "summary.json", summary)
    if isinstance(prep.programs, programcache.ReadAhead):    # the next run reads these programs ahead
        prep.programs.remember()
    return summary


def _import_writing_modules(figures: bool):
    """Import the modules the outputs are written with: FITS and WCS, and with `figures`
    (colour composites asked for) matplotlib (~1 s of a warm run's imports in all)."""
    from astropy.io import fits  # noqa: F401
    from astropy.wcs import WCS  # noqa: F401
    if figures:
        rgbimage._pyplot()


def _render_bands(prep: Prepared, hr, later_noise=None):
    """((noisy, noiseless, variance) images per band [counts/s] as numpy arrays, the
    high-resolution lens-plane images of `hr`'s source or None, and the clumps'
    magnifications or None: unlensed or no clumps); without noise (`later_noise`: the
    launched `_noise_program`, None) the 'noisy' images are the noiseless ones. One program
    (`_band_render`) makes the noiseless images, the lens plane and the magnifications,
    a second one (`_band_noise`, compiled beside it in the background) the noise."""
    scene, model, table = prep.scene, prep.model, prep.catalog
    # the high-resolution lens plane comes from the band render's own program: the host's
    # light at the traced pixels (per unit flux) and the rays are computed once for both
    hr_fluxes = _fluxes(hr[0]) if hr is not None and model.lensed else None
    magnify = bool(table is not None and len(table) and model.lensed)
    args = (prep.source, hr_fluxes, magnify)
    # The host's light per unit flux (its own program, or read back) is made in a thread of
    # its own while this one loads or compiles the band render from zeros of the light's
    # shapes: its compilation and run (~2.6 s of a cold run) are then off this thread's
    # path, on the core the background programs leave free by then. Same program, same
    # inputs: the same images as one after the other.
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="clumpylen-light") as pool:
        later = pool.submit(_with_host_light, prep.programs, model, prep.source,
                            _mean_for(prep), submit=prep.cache_submit)
        render_ = programcache.compiled("SceneModel.band_render", _band_render,
                                        _held_light_placeholder(prep, model), *args,
                                        folder=prep.programs, quick_compile=True)
        clean, hr_lensed, mags = render_(later.result(), *args)
    noisy = clean if later_noise is None else \
        later_noise.result()(jax.random.key(scene.seed), clean)
    clean = [np.asarray(x) for x in clean]
    return ([np.asarray(x) for x in noisy], clean, model.variances(clean)), hr_lensed, \
        None if mags is None else np.asarray(mags)


def _noise_program(prep: Prepared, prog: _Progress):
    """`_band_noise` of the model's bands as a function (key, noiseless images) → noisy
    images, loaded or compiled now from the images' shapes: launched in the background, it
    compiles beside the band render (JAX's Poisson sampler is a fifth of that program)."""
    with prog.stage("noise (compile)"):
        model = prep.model
        # numpy: a jnp.zeros per shape is a compile of its own
        like = tuple(np.zeros(det.grid.shape, prep.dtype) for det in model.layouts)
        return programcache.compiled(
            "band_noise", _band_noise, jax.random.key(0), like,
            tuple(det.name for det in model.layouts),
            tuple(det.exptime_s for det in model.layouts), model.accuracy.gaussian_noise_above,
            # not "light": its Poisson draws differed from a default jit's (`observe`) in
            # 1340 pixels of the paper scene; quickly compiled they are the same bits
            folder=prep.programs, quick_compile=True)


def _band_noise(key, clean, names, exptimes_s, gaussian_above_counts):
    """Photon noise of noiseless band images (with sky, counts/s), as `SceneModel.observe`
    draws it (`noise.add_photon_noise_bands`)."""
    from . import noise
    return noise.add_photon_noise_bands(key, clean, names, exptimes_s, gaussian_above_counts)


def _write_band(out: Path, prep: Prepared, k: int, noisy, clean, var, unlensed, unl_model) -> dict:
    """Write bands/<filter>.fits of band k; returns its entry of summary.json's "bands"."""
    scene, b = prep.scene, prep.scene.bands[k]
    lay = prep.model.layouts[k]
    wcs = _wcs_for(lay.grid, scene)
    unl_wcs = None
    if unlensed is not None:
        unl_wcs = _wcs_for(unl_model.layouts[k].grid, scene)
    header = _header(scene, b, prep.zeropoints[b.filter], scene.seed)
    if b.exptime_s is None:
        header["NOISEMOD"] = "none: no exposure time given"
    io.write_band_fits(out / "bands" / f"{b.filter}.fits", noisy, noiseless=clean,
                       variance=var, unlensed=unlensed, header=header, wcs=wcs,
                       unlensed_wcs=unl_wcs)
    src_counts = float(np.sum(clean) - lay.sky_counts_per_s * clean.size)
    return {
        "total_counts_per_s": src_counts,
        "total_counts": src_counts * float(b.exptime_s or 0.0),
        "shape": list(clean.shape), "pixel_arcsec": b.pixel_arcsec,
        "zeropoint_ab": prep.zeropoints[b.filter],
        "psf": b.psf, "psf_effective": prep.bands[k].psf_effective,
    }


def _write_composites(out: Path, prep: Prepared, shown, clean, grids) -> None:
    """rgb_<F1-F2-F3>.png of the shown images (noisy, or noiseless without noise), sky removed."""
    scene, model = prep.scene, prep.model
    images = {b.filter: shown[k] - model.layouts[k].sky_counts_per_s
              for k, b in enumerate(scene.bands)}
    truth = {b.filter: clean[k] - model.layouts[k].sky_counts_per_s
             for k, b in enumerate(scene.bands)}
    for triple in scene.output.rgb:
        # stretch and colour balance from the noiseless light (faint arcs not set by the noise)
        g0 = grids[triple[0]]
        rgbimage.save_composite(out / f"rgb_{'-'.join(triple)}.png", _rgb_channels(images, grids, triple),
                                rgbimage.extent_of_grid(g0), reference=_rgb_channels(truth, grids, triple),
                                wcs=_wcs_for(g0, scene), title=rgbimage.rgb_title(triple, scene.output.noise))


def _write_catalogue(out: Path, prep: Prepared, mags):
    """catalog.ecsv with each clump's magnification (`mags`: the band render's, None when
    unlensed or no clumps) and smear flag; the table (None: no clumps)."""
    model, table = prep.model, prep.catalog
    if table is not None:
        if mags is not None:   # every source_mode (linearised clumps too)
            table["magnification"] = mags
        else:
            table["magnification"] = np.full(len(table), 1.0 if not model.lensed else np.nan)
        from .preflight import smear_flags
        table["flag"] = smear_flags(model, table, prep.scene.render.source_pixel_arcsec)
        io.write_catalog(out / "catalog.ecsv", table)
    return table


def _summary(prep: Prepared, summary_bands: dict, table, hr_info) -> dict:
    """summary.json's content up to the timings (which the caller adds once the run is done)."""
    scene, model = prep.scene, prep.model
    lensed = model.lensed
    stages_ran = ["population" if scene.source.clumps is not None else None, "photometry",
                  "lensing" if lensed else None]
    return {
        "scene": scene_mod.resolved_dict(scene),
        "seed": scene.seed,
        "version": __version__,
        "bands": summary_bands,
        "band_total_counts": {f: v["total_counts"] for f, v in summary_bands.items()},
        "n_clumps": 0 if table is None else len(table),
        "host_masses_msun": prep.host_masses_msun,
        "field_arcsec": prep.field_arcsec,
        "traced_pixels": None if not lensed else int(model.traced_rows.shape[0]),
        "hr_grid": None if not lensed else dataclasses.asdict(model.hr_grid),
        "hr": hr_info,
        "stages": [s for s in stages_ran if s] +
                  [f"psf:{b.name}" for b in prep.bands if b.psf is not None] +
                  (["noise"] if scene.output.noise else []) +
                  (["unlensed"] if scene.output.unlensed else []) +
                  [f"rgb:{'-'.join(t)}" for t in scene.output.rgb] +
                  (["hr"] if scene.output.hr else []),
    }


def _band_render(model, source, hr_fluxes, magnify: bool):
    """The noiseless band images (`noiseless`), given hr_fluxes the high-resolution
    lens-plane images (`lens_plane`) of the source with those fluxes, and with `magnify` the
    clumps' magnifications, as one program: the work they share (host light per unit flux at
    the traced pixels, rays, the clumps' stamps) is done once, and one program is compiled
    and loaded instead of three; within it, the clumps' stamps are made by one call for
    all three (`SceneModel.noiseless_lens_plane_magnifications`)."""
    return model.noiseless_lens_plane_magnifications(
        source, None if hr_fluxes is None else _with_fluxes(source, hr_fluxes), magnify)


def _fluxes(source: Source):
    """(bulge, disk, clumps) fluxes of a source (None where it has no such component)."""
    return (None if source.bulge is None else source.bulge.flux,
            None if source.disk is None else source.disk.sersic.flux,
            None if source.clumps is None else source.clumps.flux)


def _with_fluxes(source: Source, fluxes):
    """The source with the fluxes of `_fluxes` put in (geometry unchanged)."""
    fb, fd, fc = fluxes
    bulge = None if source.bulge is None else dataclasses.replace(source.bulge, flux=fb)
    disk = None if source.disk is None else dataclasses.replace(
        source.disk, sersic=dataclasses.replace(source.disk.sersic, flux=fd))
    clumps = None if source.clumps is None else dataclasses.replace(source.clumps, flux=fc)
    return Source(bulge, disk, clumps)


def _hr_source(prep: Prepared):
    """The source of the high-resolution images: (source, names, unit): monochromatic at
    hr_rgb_um (μJy), else the band fluxes."""
    waves = prep.scene.output.hr_rgb_um
    if waves is not None:
        return _monochromatic_source(prep, waves), [f"{w:g}um" for w in waves], "uJy/pixel"
    return prep.source, list(prep.scene.band_names), "counts/s/pixel"


def _launch_hr(prep: Prepared, prog: _Progress, hr, sgrid, later_unl=None):
    """(sgrid, the high-resolution source-plane images), launched (not waited for):
    later_unl's (the `_launch_unlensed` submitted before it to the same pool), else by
    programs of their own."""
    with prog.stage("high-resolution images (launch)"):
        if later_unl is not None:
            return sgrid, later_unl.result()[2]
        return _hr_source_plane(prep, hr[0], sgrid)


def _hr_grid(prep: Prepared, mono):
    """The high-resolution source-plane grid (at most 2047² pixels over the source)."""
    center, radius = model_mod.source_extent(mono, prep.accuracy.source_flux_fraction,
                                             prep.accuracy.stamp_flux_fraction)
    from .pixels import Grid
    pix = max(prep.scene.render.source_pixel_arcsec, 2 * radius / 2047)
    return Grid.centered(center, radius, pix)


def _hr_groups(prep: Prepared, mono, sgrid):
    """The source-plane clumps' stamp groups, their indices as tuples: static (baked in as
    constants)."""
    groups = []
    if mono.clumps is not None and mono.clumps.count > 0:
        groups = render.stamp_groups(mono.clumps.re_arcsec, mono.clumps.n, sgrid.pixel_arcsec,
                                     flux_fraction=prep.accuracy.stamp_flux_fraction)
    return tuple((side, tuple(idx.tolist())) for side, idx in groups)


def _hr_source_plane(prep: Prepared, mono, sgrid):
    """(sgrid, the source-plane images of `mono` on it, launched) by programs of their own
    (no unlensed bands asked for)."""
    groups = _hr_groups(prep, mono, sgrid)
    host = (None, None)
    if mono.bulge is not None or mono.disk is not None:
        host = _kept_light(prep.programs, "source_plane_host_light", _source_plane_host_light,
                           Source(mono.bulge, mono.disk, None), sgrid, prep.accuracy,
                           _mean_for(prep), submit=prep.cache_submit)
    return sgrid, _program(prep.programs, "source_plane_images", _source_plane_images, mono,
                           host, sgrid, prep.accuracy, groups, quick_compile=True)


def _write_hr_set(prep: Prepared, out: Path, hr, images, grid, lensed: bool, **composite):
    """One set of high-resolution images (FITS per name, and the colour PNG) on `grid`."""
    _, names, unit = hr
    kind = "lensed" if lensed else "unlensed"
    wcs = _wcs_for(grid, prep.scene)
    for k, name in enumerate(names):
        hdr = {"BUNIT": unit, "PIXSCALE": grid.pixel_arcsec}
        io.write_fits_image(out / "hr" / f"{kind}_{name}.fits", images[k].astype(np.float32),
                            wcs=wcs, header=hdr)
    idx = _hr_rgb_index(prep, names)
    if idx is not None:
        title = rgbimage.rgb_title([names[k] for k in idx], False,
                                   kind=f"high resolution, {kind}")
        rgbimage.save_composite(out / "hr" / f"rgb_{kind}.png", [images[k] for k in idx],
                                rgbimage.extent_of_grid(grid), wcs=wcs, title=title, **composite)


def _write_hr_lensed(prep: Prepared, out: Path, hr, lensed):
    """High-resolution lensed images (the band render's) written to out/hr."""
    _write_hr_set(prep, out, hr, np.asarray(lensed), prep.model.hr_grid, True)


def _write_hr_unlensed(prep: Prepared, out: Path, hr, later):
    """High-resolution unlensed images (`later`: `_launch_hr`'s, launched) written to
    out/hr; returns summary.json's "hr" entry."""
    _, names, unit = hr
    sgrid, unl = later.result()
    _write_hr_set(prep, out, hr, np.asarray(unl), sgrid, False, frame="β", crop=True)
    return {"names": names, "unit": unit, "source_grid": dataclasses.asdict(sgrid)}


def _hr_rgb_index(prep: Prepared, names):
    """Indices into `names` of the high-resolution composites' red, green, blue (None: fewer
    than three images)."""
    if len(names) < 3:
        return None
    rgb = rgbimage.hr_channel_names(names, prep.scene.output.hr_rgb_um, prep.scene.output.rgb)
    return [names.index(n) for n in rgb]


def _source_plane_host_light(source: Source, grid, accuracy, modulation_mean=None):
    """Unit-flux pixel integrals (bulge, disk) [ny, nx] of the source's host on the
    source-plane grid, None for a component it lacks (modulation_mean: the disk's, or None:
    computed here)."""
    bulge = disk = None
    if source.bulge is not None:
        bulge = render.sersic_image(source.bulge, grid, order=accuracy.source_order,
                                    core=accuracy.exact_core)
    if source.disk is not None:
        disk = render.disk_image(source.disk, grid, order=accuracy.source_order,
                                 core=accuracy.exact_core, modulation_mean=modulation_mean)
    return bulge, disk


def _source_plane_images(source: Source, host, grid, accuracy, groups, clumps=None):
    """Pixel-integrated source-plane images [B, ny, nx] (counts or μJy per pixel); host:
    `_source_plane_host_light` of the source; clumps: the clumps' images [B, ny, nx], made
    before, or None (made here from `groups`)."""
    img = 0.0
    bulge, disk = host
    if bulge is not None:
        img = img + source.bulge.flux[:, None, None] * bulge[None]
    if disk is not None:
        img = img + source.disk.sersic.flux[:, None, None] * disk[None]
    cl = source.clumps
    if clumps is not None:
        img = img + clumps
    elif cl is not None and cl.count > 0:
        img = img + jnp.moveaxis(render.clumps_image(cl, grid, groups, cl.flux,
                                                     order=accuracy.source_order,
                                                     core=accuracy.exact_core), -1, 0)
    return img


def _monochromatic_source(prep: Prepared, waves_um):
    """The source with fluxes replaced by f_ν (μJy) at the given observed wavelengths."""
    scene = prep.scene
    cosmology = _cosmology(scene)
    src = scene.source
    s = prep.source

    def mono(mass, age, metallicity, sfh):
        if mass is None or (np.ndim(mass) == 0 and mass <= 0):
            return np.zeros(np.shape(mass) + (len(waves_um),)) if mass is not None else \
                np.zeros(len(waves_um))
        return np.asarray(photometry.monochromatic_fnu(
            mass, age, wavelength_obs_um=list(waves_um), z=scene.z_source,
            metallicity=metallicity, sfh=sfh.kind, sfh_duration_myr=sfh.duration_myr or 0.0,
            cosmology=cosmology))

    dt = prep.dtype
    bulge = disk = clumps = None
    if s.bulge is not None:
        f = mono(prep.host_masses_msun["bulge"], src.bulge.age_myr, src.bulge.metallicity,
                 src.bulge.sfh)
        bulge = dataclasses.replace(s.bulge, flux=jnp.asarray(f, dt))
    if s.disk is not None:
        f = mono(prep.host_masses_msun["disk"], src.disk.age_myr, src.disk.metallicity,
                 src.disk.sfh)
        disk = dataclasses.replace(s.disk, sersic=dataclasses.replace(s.disk.sersic,
                                                                      flux=jnp.asarray(f, dt)))
    if s.clumps is not None:
        t = prep.catalog
        mass = np.asarray(t["mass_msun"], float)
        if np.all(np.isfinite(mass)):
            f = mono(mass, np.asarray(t["age_myr"], float), src.clumps.metallicity, src.clumps.sfh)
        else:
            f = np.zeros((len(t), len(waves_um)))
        clumps = dataclasses.replace(s.clumps, flux=jnp.asarray(f, dt))
    return Source(bulge, disk, clumps)
