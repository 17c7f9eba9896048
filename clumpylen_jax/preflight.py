"""Checks of a scene that read its files or add up its sizes: run by `validate` and, before
any computation, by `simulate`, so that both refuse the same scenes.

`scene.load_scene` checks every key by itself; what needs more than the key is here:

- `check_files`: every PSF file read as `simulate` reads it (truncated, NaN, a pixel scale
  that cannot be the band's), the deflection maps (readable, same grid), the clump
  population settings through the sampler's own validation;
- `memory_estimate` / `check_memory`: the memory a run needs, added up from the scene's
  grids (detector sub-grids and their FFTs, the lens-plane grid, clumps), refused when
  above the machine's memory, naming the knob that dominates;
- `warnings`: scenes that run but lose accuracy silently (clumps far below the
  source-plane pixel in a lensed scene).
"""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np
from astropy.io import fits

from .errors import ConfigError

# Bytes per pixel or per clump of each part of a run, at float64 (float32 halves the
# images), set from the peak memory (RSS) of three runs on a 2-core CPU host: the
# estimate is 1.00x single-sersic's (0.51 GiB), 1.11x that of a 12" SIS field at 2.5 mas
# (23 M lens-plane pixels, 1.85 GiB) and 0.83x cosmic-archipelago's (3.48 GiB)
_BYTES_HR_BUILD = 48          # per lens-plane pixel: traced corners, masks, footprints (float64)
_BYTES_HR_IMAGE = 8           # per lens-plane pixel and image held (hosts; HR output twice)
_BYTES_FFT = 16 * 6           # per padded FFT pixel and band: complex temporaries
_BYTES_STAMP = 8 * 3          # per source-grid stamp pixel of a ray-traced clump
_STAMP_FLUX_FRACTION = 0.9999  # the light a stamp holds (model.Accuracy's default)
_BYTES_CLUMP = 4096           # per clump: catalogue, photometry, stamps (+ per band below)
_BYTES_CLUMP_BAND = 256
_BYTES_HR_SOURCE = 8 * 3      # per HR source-plane pixel and band: image and its copies
_HR_SOURCE_SIDE = 2047        # pipeline._write_hr's largest source grid
_DIFFRACTION_PSF_ARCSEC = 4.0  # a diffraction PSF's width (32 λ/D: 4.5" at F444W)
_BASE_BYTES = 0.5 * 2**30     # the Python and JAX runtime (single-sersic peaks at 0.52 GB)
ENV_LIMIT = "CLUMPYLEN_MEMORY_LIMIT_GB"


def _sub_factor(scene, band) -> int:
    return scene.render.accuracy.psf_oversampling if band.psf != "none" else 1


def _source_radius(scene) -> float:
    """Radius (arcsec) about the source centre holding its hosts' light and catalogue clumps."""
    from .profiles import sersic_radius_enclosing_np as _radius_enclosing

    src = scene.source
    frac = scene.render.accuracy.source_flux_fraction
    r = 0.0
    for comp in (src.bulge, src.disk):
        if comp is not None:
            r = max(r, float(_radius_enclosing(frac, comp.re_arcsec, comp.n)))
    if src.clumps is not None and src.clumps.catalog is not None:
        from astropy.table import Table
        t = Table.read(src.clumps.catalog)
        c = np.asarray(src.center_arcsec, float)
        d = np.hypot(np.asarray(t["beta1_arcsec"], float) - c[0],
                     np.asarray(t["beta2_arcsec"], float) - c[1])
        r = max(r, float(d.max()) if d.size else 0.0)
    return r


def _psf_side_arcsec(scene, band) -> float:
    if band.psf == "none":
        return 0.0
    if band.psf == "diffraction":
        return _DIFFRACTION_PSF_ARCSEC
    try:
        with fits.open(band.psf) as hdul:
            for hdu in hdul:
                if hdu.header.get("NAXIS", 0) >= 2:
                    n = max(hdu.header["NAXIS1"], hdu.header["NAXIS2"])
                    return n * (band.psf_pixel_arcsec or band.pixel_arcsec)
    except (OSError, ValueError, KeyError):   # check_files reports unreadable files
        pass
    return _DIFFRACTION_PSF_ARCSEC


def expected_clump_count(scene) -> int:
    """Clumps the scene will have: catalogue rows, or the sampler's mass budget / mean mass."""
    cl = scene.source.clumps
    if cl is None:
        return 0
    if cl.catalog is not None:
        from astropy.table import Table
        return len(Table.read(cl.catalog))
    host = scene.source.disk if cl.host == "disk" else scene.source.bulge
    if host is None or host.mass_msun is None:
        return 0
    c = cl.cmf
    lm = np.linspace(math.log(c.m_min_msun), math.log(c.m_max_msun), 4001)
    m = np.exp(lm)
    pdf = m ** (c.slope + 1) * np.exp(-c.delta * (m / c.m_cut_msun) ** c.gamma)  # per ln M
    mean = float(np.trapezoid(pdf * m, lm) / np.trapezoid(pdf, lm))
    return int(math.ceil(cl.mass_fraction * host.mass_msun / mean))


def _stamp_side(scene) -> float:
    """Mean side (source-grid pixels) of a ray-traced clump's stamp: catalogue sizes, or the
    size relation at the mean CMF mass."""
    from .profiles import sersic_radius_enclosing_np as _radius_enclosing

    from .cosmology import arcsec_per_pc, scene_cosmology

    cl = scene.source.clumps
    scale = arcsec_per_pc(scene.z_source, scene_cosmology(scene))
    if cl.catalog is not None:
        from .population import read_clump_catalog
        # the scene's own scale: a catalogue giving only re_pc gets its sizes in arcsec
        t = read_clump_catalog(cl.catalog, arcsec_per_pc=scale, sersic_n_default=cl.sersic_n)
        re, n = np.asarray(t["re_arcsec"], float), np.asarray(t["sersic_n"], float)
    else:
        from .population import clump_config_from_scene
        c = clump_config_from_scene(dataclasses.asdict(cl))
        mean_mass = cl.mass_fraction * (cl.cmf.m_min_msun * cl.cmf.m_max_msun) ** 0.5
        re_pc = c.size_norm_pc * (min(mean_mass, c.cmf_m_max_msun) / c.size_pivot_msun) ** c.size_slope
        re = np.array([re_pc * scale])
        n = np.array([cl.sersic_n])
    r = _radius_enclosing(_STAMP_FLUX_FRACTION, re, n)
    return float(np.sqrt(np.mean((2 * r / scene.render.source_pixel_arcsec + 3) ** 2)))


def _field(scene, field_arcsec):
    if field_arcsec is not None:
        return field_arcsec
    f = scene.render.field_arcsec
    return None if f is None else (tuple(f.x), tuple(f.y))


def memory_estimate(scene, *, field_arcsec=None, n_clumps=None) -> dict:
    """Peak memory (bytes) a run of `scene` needs, by part: {"total", "parts": {name: (bytes, knob)}}.

    field_arcsec: the lens-plane field when known (lensed scenes without
    render.field_arcsec find theirs after the population: without it the lens plane is
    left out). n_clumps: the clumps, when known (else `expected_clump_count`).
    """
    field = _field(scene, field_arcsec)
    d = 4 if scene.render.dtype == "float32" else 8
    nb = len(scene.bands)
    radius = _source_radius(scene)
    if field is not None:
        w, h = field[0][1] - field[0][0], field[1][1] - field[1][0]
    else:
        w = h = 2 * radius
    parts = {}
    fft = 0.0
    for b in scene.bands:
        sub = b.pixel_arcsec / _sub_factor(scene, b)
        k = _psf_side_arcsec(scene, b) / sub
        fft += (w / sub + k) * (h / sub + k)
    parts["detector grids and FFTs"] = (fft * _BYTES_FFT * d / 8,
                                        "render.field_arcsec (smaller) or render.accuracy.psf_oversampling (lower)")
    if scene.lens is not None and field is not None:
        hr = math.ceil(w / scene.render.lens_pixel_arcsec) * math.ceil(h / scene.render.lens_pixel_arcsec)
        n_comp = (scene.source.bulge is not None) + (scene.source.disk is not None)
        held = n_comp + (2 * nb if scene.output.hr else 0)
        parts["lens-plane grid"] = (hr * (_BYTES_HR_BUILD + _BYTES_HR_IMAGE * d / 8 * held),
                                    "render.field_arcsec (smaller) or render.lens_pixel_arcsec (larger)")
    if scene.output.hr:
        side = min(_HR_SOURCE_SIDE, 2 * radius / scene.render.source_pixel_arcsec + 1)
        parts["high-resolution source plane"] = (side**2 * nb * _BYTES_HR_SOURCE,
                                                 "render.source_pixel_arcsec (larger) or output.hr (false)")
    n = expected_clump_count(scene) if n_clumps is None else int(n_clumps)
    if n and scene.lens is not None and scene.render.accuracy.source_mode != "analytic":
        side = _stamp_side(scene)
        parts["clump stamps on the source grid"] = (n * side**2 * _BYTES_STAMP,
                                                    "render.source_pixel_arcsec (larger)")
    if n:
        parts["clumps"] = (n * (_BYTES_CLUMP + _BYTES_CLUMP_BAND * nb),
                           "source.clumps (fewer clumps: mass_fraction, cmf.m_min_msun "
                           "or the catalogue)")
    total = _BASE_BYTES + sum(v for v, _ in parts.values())
    return {"total": total, "parts": parts}


def memory_limit_bytes() -> float:
    """The machine's physical memory, or $CLUMPYLEN_MEMORY_LIMIT_GB."""
    env = os.environ.get(ENV_LIMIT)
    if env:
        try:
            value = float(env)
        except ValueError:
            raise ConfigError(ENV_LIMIT, env, "a memory limit in GB (a number)") from None
        if not value > 0:
            raise ConfigError(ENV_LIMIT, env, "a memory limit in GB > 0")
        return value * 2**30
    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return math.inf


def check_memory(scene, *, field_arcsec=None, n_clumps=None) -> dict:
    """Refuse (ConfigError naming the knob) a scene whose estimate exceeds the memory limit."""
    est = memory_estimate(scene, field_arcsec=field_arcsec, n_clumps=n_clumps)
    limit = memory_limit_bytes()
    if est["total"] > limit:
        name, (size, knob) = max(est["parts"].items(), key=lambda kv: kv[1][0])
        gib = 2.0**30
        raise ConfigError(knob.split(" (")[0], f"a run needing ~{est['total'] / gib:.3g} GiB "
                          f"({name}: {size / gib:.3g} GiB)",
                          f"a scene that fits in {limit / gib:.3g} GiB of memory: change {knob} "
                          f"(limit: ${ENV_LIMIT})")
    return est


def check_files(scene) -> None:
    """Read what `simulate` will read (PSF files, deflection maps, population settings) and
    refuse what it would refuse, naming the scene key."""
    from .psf import psf_for_band

    for i, b in enumerate(scene.bands):
        if b.pixel_arcsec is None or b.zeropoint_ab is None:
            raise ConfigError(f"bands[{i}]", b.filter, "a band with pixel_arcsec and zeropoint_ab")
        if b.psf not in ("none", "diffraction"):
            psf_for_band(b.psf, instrument=b.instrument, filter_name=b.filter,
                         detector_pixel_arcsec=b.pixel_arcsec, psf_pixel_arcsec=b.psf_pixel_arcsec,
                         base_dir=scene.base_dir, setting=f"bands[{i}].psf",
                         grid_oversampling=scene.render.accuracy.psf_oversampling)
    cl = scene.source.clumps
    if cl is not None and cl.catalog is None:
        from .population import clump_config_from_scene
        clump_config_from_scene(dataclasses.asdict(cl))
    waves = scene.output.hr_rgb_um if scene.output.hr else None
    if waves is not None:   # read only when the HR images are written: after the render
        from .sps import default_library
        rest = np.asarray(default_library().wavelength_aa) / 1e4
        lo, hi = rest[0] * (1 + scene.z_source), rest[-1] * (1 + scene.z_source)
        if not all(lo <= w <= hi for w in waves):
            raise ConfigError("output.hr_rgb_um", list(waves), f"wavelengths inside the SSP "
                              f"library's range at z = {scene.z_source:g}: {lo:.3f}-{hi:.3f} μm")
    lens = scene.lens
    if lens is not None and lens.deflection is not None:
        from .lensing.fits import load_deflection_maps
        try:
            load_deflection_maps(lens.deflection.x, lens.deflection.y,
                                 lens_center_radec_deg=lens.center_radec_deg, z_lens=lens.z_lens,
                                 z_source=scene.z_source)
        except ConfigError as exc:
            raise ConfigError(f"lens.deflection ({exc.setting})", exc.value, exc.expected) from exc
        except (OSError, ValueError, TypeError) as exc:   # truncated or corrupt FITS
            raise ConfigError("lens.deflection", [lens.deflection.x, lens.deflection.y],
                              f"complete, readable FITS maps ({exc})") from exc


def warnings(scene) -> list[str]:
    """Scenes that run but lose accuracy without an error: one line each."""
    out = []
    cl = scene.source.clumps
    pix = scene.render.source_pixel_arcsec
    if scene.lens is not None and cl is not None and cl.catalog is None:
        # sampled sizes: the smallest clump of the size relation, 2 sigma below it
        from .cosmology import arcsec_per_pc, scene_cosmology
        from .population import clump_config_from_scene
        c = clump_config_from_scene(dataclasses.asdict(cl))
        re_pc = (c.size_norm_pc * (c.cmf_m_min_msun / c.size_pivot_msun) ** c.size_slope
                 * math.exp(-2 * c.size_scatter_ln))
        re = re_pc * arcsec_per_pc(scene.z_source, scene_cosmology(scene))
        if re < SMEAR_FRACTION * pix:
            out.append(f"sampled clumps of M = cmf.m_min_msun reach R_e = {re:.2g}\" (2 sigma "
                       f"below the size relation), below {SMEAR_FRACTION:g} × "
                       f"render.source_pixel_arcsec = {pix:g}\": near a caustic such clumps "
                       "are smeared to that pixel (flagged in catalog.ecsv)")
    if scene.lens is not None and cl is not None and cl.catalog is not None:
        from astropy.table import Table
        from .population import read_clump_catalog
        t = read_clump_catalog(cl.catalog, arcsec_per_pc=1.0)
        if "re_arcsec" in Table.read(cl.catalog).colnames:
            small = int(np.sum(np.asarray(t["re_arcsec"], float) < SMEAR_FRACTION * pix))
            if small:
                out.append(f"{small} clump(s) of source.clumps.catalog have R_e below "
                           f"{SMEAR_FRACTION:g} × render.source_pixel_arcsec = {pix:g}\": near a "
                           "caustic (where they are ray-traced) their image and magnification are "
                           "those of a clump smeared to that pixel (flagged in catalog.ecsv)")
    return out


# A ray-traced clump with R_e below this fraction of the source-plane pixel is smeared by it
SMEAR_FRACTION = 0.5


def preflight(scene) -> list[str]:
    """check_files, then check_memory; returns `warnings`."""
    check_files(scene)
    check_memory(scene)
    return warnings(scene)


def smear_flags(model, table, source_pixel_arcsec: float) -> np.ndarray:
    """A catalogue's `flag` column: "smeared" for a clump ray-traced through the source-plane
    grid (in hybrid mode: near a caustic) with R_e < SMEAR_FRACTION of its pixel, whose
    image and magnification are then those of a clump the size of a pixel; "ok" otherwise.

    Flagged rather than rendered otherwise: the analytic path samples such a clump at the
    rays, which resolve it no better (a 1e-5" clump between rays 0.6 mas apart).
    """
    flags = np.full(len(table), "ok", dtype="<U7")
    if not getattr(model, "lensed", False) or model.clump_grid is None or not len(table):
        return flags
    traced = np.concatenate([np.asarray(i) for i in model.clump_stamp_index]) \
        if model.clump_stamp_index else np.zeros(0, int)
    re = np.asarray(table["re_arcsec"], float)
    small = np.zeros(len(table), bool)
    small[traced] = re[traced] < SMEAR_FRACTION * source_pixel_arcsec
    flags[small] = "smeared"
    return flags
