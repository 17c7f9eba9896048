"""The paper's colour figure of a run (its Fig. "RGB_M0416"), as RUN/plots/paper_rgb.png.

Four panels on the same θ field, as the paper shows the Cosmic Archipelago:

1. the high-resolution lensed image in colour (hr/lensed_*.fits; red, green, blue
   as the run wrote hr/rgb_lensed.png);
2. one high-resolution channel convolved with a detector band's PSF, without pixels
   or noise: what the instrument's resolution alone does. The pair (HR channel,
   band) with the closest wavelengths is taken, bluest first: F115W with a per-band
   HR image of F115W as in the paper; the 2 μm channel with F200W for a run with
   `hr_rgb_um = [5, 3, 2]` (the paper used the F115W magnitudes, which such a run
   does not render at high resolution);
3. and 4. the detector colour composites the scene asks for (`output.rgb`, e.g. SW
   F200W/F150W/F115W and LW F444W/F356W/F277W), with noise.

The clump of interest (the brightest lensed clump in the panel-2 band) is circled
in every panel, and the critical curves are drawn dashed. Panels that a run lacks
are left out.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from . import rgbimage

__all__ = ["plot_paper_rgb", "paper_figure_of_run"]

CIRCLE_RADIUS_ARCSEC = 0.12  # a few NIRCam SW PSF widths: the clump and its immediate surroundings


def _wavelength_um(name):
    """μm of an HR channel name ('2um') or a band's pivot (filter name); None if unknown."""
    m = re.fullmatch(r"([0-9.]+)um", name)
    if m:
        return float(m.group(1))
    try:
        from .filters import load_filter

        return load_filter(name).pivot_wavelength_aa / 1e4
    except Exception:  # a user filter file that is gone: the band just is not paired
        return None


def _read_image(path):
    from astropy.io import fits
    from astropy.wcs import WCS

    with fits.open(path) as h:
        return np.asarray(h[0].data, float), WCS(h[0].header)


def _read_wcs(path):
    from astropy.io import fits
    from astropy.wcs import WCS

    return WCS(fits.getheader(path))


def _hr_lensed(run_dir, summary):
    hr = summary.get("hr") or {}
    names = hr.get("names") or []
    out = run_dir / "hr"
    if len(names) < 1 or not all((out / f"lensed_{n}.fits").exists() for n in names):
        return None, {}
    return names, {n: _read_image(out / f"lensed_{n}.fits") for n in names}


def _psf_panel(summary, bands, names, images, run_dir):
    """(image, wcs, title, band) of the HR channel convolved with the nearest band's PSF, or None."""
    from scipy.signal import fftconvolve

    from .psf import psf_for_band, resample_psf

    scene_bands = {b["filter"]: b for b in summary["scene"].get("bands", [])}
    with_psf = [f for f in bands if (scene_bands.get(f, {}).get("psf") or "none") != "none"]
    pairs = []
    for n in names:
        wn = _wavelength_um(n)
        for f in with_psf:
            wf = _wavelength_um(f)
            if wn is not None and wf is not None:
                pairs.append((abs(np.log(wn / wf)), wf, n, f))
    if not pairs:
        return None
    _, _, name, band = min(pairs)
    b = scene_bands[band]
    img, wcs = images[name]
    pix = float(np.sqrt(abs(np.linalg.det(wcs.pixel_scale_matrix)))) * 3600.0
    psf = psf_for_band(b["psf"], instrument=b["instrument"], filter_name=band,
                       detector_pixel_arcsec=bands[band]["pixel_arcsec"], psf_pixel_arcsec=b.get("psf_pixel_arcsec"),
                       base_dir=run_dir)
    kernel = resample_psf(psf, pix, size=min(2 * (int(1.0 / pix) // 2) + 1, 401))  # 1" across at most
    conv = fftconvolve(img, kernel, mode="same")
    return conv, wcs, f"high resolution {name} convolved with the {band} PSF (no pixels, no noise)", band


def _composite(bands, triple):
    ims = [bands[f] for f in triple]
    if not all(i["image"].shape == ims[0]["image"].shape for i in ims):
        return None
    chans = [i["image"] - i["sky"] for i in ims]
    ref = [i["noiseless"] - i["sky"] for i in ims]
    return rgbimage.rgb_array(*chans, reference=ref)


def _clump_of_interest(catalog, lens, field, band, *, avoid=None):
    """θ of the brightest lensed clump in `band` (mag − 2.5 log10 |μ|), or None.

    avoid: (β1, β2, radius_arcsec) of the host's centre: clumps there are lost in the
    bulge's light, and the circle is meant to show a clump that stands out.
    """
    if catalog is None or not len(catalog) or f"mag_{band}" not in catalog.colnames:
        return None
    mag = np.asarray(catalog[f"mag_{band}"], float)
    mu = np.abs(np.asarray(catalog["magnification"], float)) if "magnification" in catalog.colnames \
        else np.ones(len(catalog))
    lensed_mag = np.where(np.isfinite(mu) & (mu > 0), mag - 2.5 * np.log10(np.where(mu > 0, mu, 1.0)), np.inf)
    if avoid is not None:
        far = np.hypot(np.asarray(catalog["beta1_arcsec"], float) - avoid[0],
                       np.asarray(catalog["beta2_arcsec"], float) - avoid[1]) > avoid[2]
        lensed_mag = np.where(far, lensed_mag, np.inf)
    if not np.any(np.isfinite(lensed_mag)):
        return None
    k = int(np.argmin(lensed_mag))
    beta = (float(catalog["beta1_arcsec"][k]), float(catalog["beta2_arcsec"][k]))
    if lens is None:
        return beta
    return _nearest_image(lens, beta, field)


def _nearest_image(lens, beta, field, n=250):
    """θ of the field pixel (n × n grid) whose ray lands closest to β: an image of β to a pixel.

    Good enough to circle a clump (field/n ≈ 0.02″ here) at a fraction of the cost of
    image finding (whose compilation takes half a minute on a small machine).
    """
    import jax.numpy as jnp

    (x0, x1), (y0, y1) = field
    t1, t2 = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n))
    a1, a2 = (np.asarray(a) for a in lens.deflection(jnp.asarray(t1), jnp.asarray(t2)))
    d2 = (t1 - a1 - beta[0]) ** 2 + (t2 - a2 - beta[1]) ** 2
    j = int(np.argmin(d2))
    return float(t1.ravel()[j]), float(t2.ravel()[j])


def plot_paper_rgb(run_dir, path, *, summary, bands, catalog=None, lens=None, curves=()):
    """Write the paper's four-panel colour figure; returns the path, or None when the run has neither
    high-resolution images nor detector composites. bands: {filter: analysis.band_data dict}."""
    from .io import atomic_write
    from .plotting import _pyplot

    run_dir = Path(run_dir)
    out = summary["scene"].get("output") or {}
    panels = []  # (image, extent, wcs, title, cmap)
    names, hr = _hr_lensed(run_dir, summary)
    if names and len(names) >= 3:
        rgb = rgbimage.hr_channel_names(names, out.get("hr_rgb_um"), out.get("rgb"))
        img = rgbimage.rgb_array(*[hr[n][0] for n in rgb])
        w = hr[rgb[0]][1]
        panels.append((img, rgbimage.extent_of_wcs(w, img.shape[:2]), w,
                       rgbimage.rgb_title(rgb, False, kind="high resolution, lensed"), None))
    psf_band = None
    if names:
        got = _psf_panel(summary, bands, names, hr, run_dir)
        if got is not None:
            conv, w, title, psf_band = got
            panels.append((conv, rgbimage.extent_of_wcs(w, conv.shape), w, title, "gray"))
    for triple in (out.get("rgb") or [])[:2]:
        if all(f in bands for f in triple):
            img = _composite(bands, triple)
            if img is not None:
                w = _read_wcs(run_dir / "bands" / f"{triple[0]}.fits")
                panels.append((img, rgbimage.extent_of_wcs(w, img.shape[:2]), w,
                               rgbimage.rgb_title(triple, True), None))
    if not panels:
        return None
    field = summary.get("field_arcsec")
    band = psf_band or next(iter(bands), None)
    src = summary["scene"].get("source") or {}
    centre = src.get("center_arcsec") or [0.0, 0.0]
    bulge_re = float((src.get("bulge") or {}).get("re_arcsec") or 0.0)
    avoid = (centre[0], centre[1], 2.0 * bulge_re)
    coi = _clump_of_interest(catalog, lens, field, band, avoid=avoid) if (field and band) else None
    circles = [(coi[0], coi[1], CIRCLE_RADIUS_ARCSEC, "red")] if coi else []
    return _draw(path, panels, circles, curves, _pyplot(), atomic_write)


def _draw(path, panels, circles, curves, plt, atomic_write):
    from astropy.visualization import AsinhStretch, ImageNormalize

    ncol = 2 if len(panels) > 1 else 1
    nrow = (len(panels) + ncol - 1) // ncol
    fig, axes = plt.subplots(nrow, ncol, figsize=(6.2 * ncol, 6.2 * nrow), squeeze=False, dpi=110)
    for ax in axes.ravel()[len(panels):]:
        ax.axis("off")
    try:
        for ax, (img, extent, wcs, title, cmap) in zip(axes.ravel(), panels):
            norm = None
            if cmap is not None:  # a single channel: asinh over its own range
                top = float(np.percentile(img, 99.9)) or float(img.max()) or 1.0
                norm = ImageNormalize(vmin=0.0, vmax=top, stretch=AsinhStretch(0.02))
            rgbimage.draw_sky(ax, img, extent, wcs=wcs, title=title, circles=circles, curves=curves,
                              cmap=cmap, norm=norm)
        fig.tight_layout()
        with atomic_write(path) as tmp:
            fig.savefig(tmp, format="png", dpi=110)
    finally:
        plt.close(fig)
    return Path(path)


def paper_figure_of_run(run_dir, out_dir=None, *, curves=None):
    """plot_paper_rgb for a finished run read from disk: RUN/plots/paper_rgb.png (or out_dir/).

    curves: the critical curves ((N, 2) arrays, arcsec); computed from the run's lens when None.
    Returns the path, or None when the run has nothing to show.
    """
    from .analysis import _lens_from_summary, _read_catalog, _read_summary, band_data

    run_dir = Path(run_dir)
    summary = _read_summary(run_dir)   # a ConfigError naming the file when it is corrupt
    bands = {b["filter"]: b for b in (band_data(p) for p in sorted((run_dir / "bands").glob("*.fits")))}
    lens = _lens_from_summary(summary, run_dir)
    field = summary.get("field_arcsec")
    if curves is None and lens is not None and field:
        from .plotting import _critical_curves

        cc = _critical_curves(lens, field)
        curves = list(cc["tangential"]) + list(cc["radial"])
    out = Path(out_dir) if out_dir is not None else run_dir / "plots"
    return plot_paper_rgb(run_dir, out / "paper_rgb.png", summary=summary, bands=bands,
                          catalog=_read_catalog(run_dir), lens=lens, curves=curves or [])
