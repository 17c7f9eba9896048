"""Colour composites and sky images people can read: stretch, axes, scale bar, compass.

- `rgb_array(r, g, b)`: a Lupton et al. (2004) asinh composite (astropy's
  `make_lupton_rgb`, bit for bit) after balancing the channels on the bright light (each channel divided by its median over
  the brightest tenth of the pixels), so that the average colour of the object is neutral and
  its parts (old host, young clumps, arms) differ in colour as their spectra do;
  saturated pixels keep their hue (astropy scales a pixel by max(R, G, B), it does
  not clip channels), and the brightest light is set below saturation.
- `draw_sky(ax, image, extent_arcsec, ...)`: an image in the θ frame of DESIGN.md
  (arcsec from the lens centre, +θ1 West to the right, +θ2 North up), drawn without
  smoothing, with a scale bar, a N/E compass from the WCS, and optional circles
  and curves.
- `save_sky_figure(path, image, extent_arcsec, ...)`: one such panel as a PNG of at
  least `min_px` pixels across, written atomically.

Matplotlib runs on the Agg backend; nothing here opens a window.
"""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np

__all__ = ["rgb_array", "save_composite", "draw_sky", "save_sky_figure", "nice_length", "extent_of_wcs",
           "extent_of_grid", "crop_to_light", "rgb_title", "compass_directions",
           "hr_channel_names"]


# pyplot's state is shared by the process: figures are drawn and saved one at a time, so
# that threads (the pipeline writes the high-resolution products in one of its own) may call
# save_sky_figure side by side; the arrays they show are made outside the lock.
_FIGURE_LOCK = threading.RLock()


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)  # no display; a no-op when a backend is already set
    import matplotlib.pyplot as plt

    return plt


def rgb_array(r, g, b, *, reference=None, shown=None, bright_pct=90.0, top_pct=99.7, Q=7.0,
              soft_sigma=3.0, floor_sigma=0.5, min_top_sigma=20.0, balance=True):
    """RGB floats in [0, 1] (ny, nx, 3) from three sky-subtracted images of the same shape.

    reference: optional (r, g, b) noiseless images that set the scales (so that faint
    arcs are not scaled by the noise); default the images themselves. With a reference,
    the noise (image − reference) sets where the stretch turns from linear to
    logarithmic: at `soft_sigma` times the noise of the intensity, so the sky stays
    dark and light a few sigma above it shows. Without one, `Q` does (larger shows
    fainter light against the brightest). floor_sigma: that many sigma of the noise
    are subtracted first (black), so that the sky does not look like coloured snow.
    bright_pct: pixels above this percentile of the summed reference light are "the object": each channel is divided by its median there (robust to a few bright clumps) (the colour balance) when
    `balance`. top_pct: the percentile of the balanced intensity that reaches the top
    of the stretch (brighter pixels saturate with their hue kept).
    shown: (r, g, b) coloured with the balance and stretch that the images set (default
    the images themselves; its shape is the result's).
    """
    chans = [np.nan_to_num(np.asarray(c, dtype=float)) for c in (r, g, b)]
    if not (chans[0].shape == chans[1].shape == chans[2].shape) or chans[0].ndim != 2:
        raise ValueError("r, g, b must be 2-D images of the same shape")
    refs = chans if reference is None else [np.nan_to_num(np.asarray(c, float)) for c in reference]
    total = sum(np.clip(c, 0, None) for c in refs)
    bright = total >= np.percentile(total, bright_pct)
    scales = [1.0, 1.0, 1.0]
    if balance:
        means = [float(np.median(np.clip(c, 0, None)[bright])) for c in refs]
        ok = [m for m in means if m > 0]
        scales = [1.0 / m if m > 0 else (1.0 / max(ok) if ok else 1.0) for m in means]
    chans = [c * s for c, s in zip(chans, scales)]
    intensity = sum(np.clip(c * s, 0, None) for c, s in zip(refs, scales)) / 3.0
    top = float(np.percentile(intensity, top_pct)) or float(intensity.max()) or 1.0
    sigma = 0.0
    if reference is not None:
        sigma = float(np.std(sum(chans) / 3.0 - sum(c * s for c, s in zip(refs, scales)) / 3.0))
    if sigma > 0:
        # Lupton: f(I) = asinh(Q I / stretch) / Q, linear below stretch / Q = the softening. Where the
        # brightest light is only a few sigma, the top stays at min_top_sigma sigma: noise stays dim.
        top = max(top, min_top_sigma * sigma)
        Q = math.asinh(top / (soft_sigma * sigma))
        top -= floor_sigma * sigma
    if shown is not None:
        chans = [np.nan_to_num(np.asarray(c, dtype=float)) * s for c, s in zip(shown, scales)]
    if sigma > 0:
        chans = [c - floor_sigma * sigma for c in chans]
    stretch = top * Q / math.sinh(Q)  # f(top) = 1
    rgb = _lupton_rgb(chans, stretch, Q)
    return np.clip(np.nan_to_num(rgb, copy=False), 0.0, 1.0, out=rgb)


def _lupton_rgb(chans, stretch, Q):
    """astropy's ``make_lupton_rgb(*chans, minimum=0, stretch=stretch, Q=Q,
    output_dtype=float64)`` (ny, nx, 3): the same arithmetic on every pixel, so the same
    array bit for bit, in a few in-place passes. astropy makes some twenty full-size
    temporaries, and scans each channel twice for interval limits this call does not use:
    ~1 s of a run's CPU on a high-resolution frame."""
    # astropy's LuptonAsinhStretch: its bounds on Q and its constants
    Q = 0.1 if abs(Q) < 1.0 / 2**23 else min(Q, 1e10)
    frac = 0.1
    slope = frac / np.arcsinh(frac * Q)
    rgb = np.stack(chans)                      # x − 0 (the minimum) is x
    intensity = (rgb[0] + rgb[1] + rgb[2]) / 3.0
    ratio = intensity * (Q / float(stretch))   # f(I) / I, 0 where I ≤ 0
    np.arcsinh(ratio, out=ratio)
    ratio *= slope
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio /= intensity
    ratio[intensity <= 0] = 0.0
    rgb *= ratio
    np.clip(rgb, 0.0, None, out=rgb)
    # pixels whose brightest channel exceeds 1 are scaled down by it (their hue kept)
    top = np.max(rgb, axis=0)
    over = top > 1.0
    rgb[:, over] /= top[over]
    return np.dstack(rgb)


def extent_of_wcs(wcs, shape):
    """imshow extent (θ1 left, right, θ2 bottom, top in arcsec: pixel edges) of an image on a TAN WCS
    whose reference point is the lens centre and whose axes follow θ (as clumpylen writes them)."""
    ny, nx = shape
    scale = np.sqrt(np.abs(np.linalg.det(wcs.pixel_scale_matrix))) * 3600.0
    crpix = wcs.wcs.crpix  # 1-based: pixel index i has θ1 = (i + 1 − CRPIX1) p
    x0 = (0.5 - crpix[0]) * scale
    y0 = (0.5 - crpix[1]) * scale
    return (x0, x0 + nx * scale, y0, y0 + ny * scale)


def extent_of_grid(grid):
    """imshow extent (pixel edges, arcsec) of a pixels.Grid (x0, y0: centre of pixel [0, 0])."""
    p = grid.pixel_arcsec
    x0, y0 = grid.x0_arcsec - p / 2, grid.y0_arcsec - p / 2
    return (x0, x0 + grid.nx * p, y0, y0 + grid.ny * p)


def hr_channel_names(names, hr_rgb_um, rgb):
    """The three HR images shown as red, green, blue (one rule for pipeline and figures).

    hr_rgb_um given: its order (names[:3]); else the first detector composite asked
    for (`rgb`); else the first three bands, reddest first (scenes list blue to red).
    """
    if hr_rgb_um:
        return list(names[:3])
    if rgb and all(n in names for n in rgb[0]):
        return list(rgb[0])
    return list(names[:3])[::-1]


def rgb_title(names, noise, *, kind=None):
    """'R F200W  G F150W  B F115W' and what the image is."""
    chans = "  ".join(f"{c} {n}" for c, n in zip("RGB", names))
    what = kind or ("with noise, sky subtracted" if noise else "noiseless, sky subtracted")
    return f"{chans}   ({what})"


def save_composite(path, channels, extent, *, reference=None, crop=False, min_px=600, **kw) -> Path:
    """A colour composite (rgb_array of three images) as a decorated figure (save_sky_figure).

    crop: zoom to the box holding 99.5 % of the light (for mostly empty frames such as
    the source plane). Other keywords go to draw_sky (wcs, title, frame, circles, curves).
    """
    if crop:
        sl, extent = crop_to_light(reference if reference is not None else channels, extent)
        channels = [np.asarray(c)[sl] for c in channels]
        reference = None if reference is None else [np.asarray(c)[sl] for c in reference]
    f = np.shape(channels[0])[1] // max(min_px, 600)   # image pixels per drawn pixel
    if f < 2:
        rgb = rgb_array(*channels, reference=reference)
    else:
        # A frame several times larger than it is drawn (a 2028² high-resolution one, drawn
        # 600 px across) is coloured on its f × f block means, with the balance and stretch
        # of its every f-th pixel: 9× fewer pixels (~2 s less CPU a frame), the same look
        # (the stretch set by the block means would differ: a clump's light fills f² more
        # of the frame's area there), and no more detail drawn than the figure shows.
        shown, extent = _block_means(channels, extent, f)
        rgb = rgb_array(*[np.asarray(c)[::f, ::f] for c in channels], shown=shown,
                        reference=None if reference is None else
                        [np.asarray(c)[::f, ::f] for c in reference])
    return save_sky_figure(path, rgb, extent, min_px=min_px, **kw)


def _block_means(channels, extent, f: int):
    """(channels averaged over f × f pixel blocks, their extent): rows and columns past the
    last whole block are left out, and the extent follows."""
    ny, nx = np.shape(channels[0])
    my, mx = ny // f * f, nx // f * f
    x0, x1, y0, y1 = extent
    return ([np.asarray(c, float)[:my, :mx].reshape(my // f, f, mx // f, f).mean(axis=(1, 3))
             for c in channels], (x0, x0 + (x1 - x0) * mx / nx, y0, y0 + (y1 - y0) * my / ny))


def crop_to_light(images, extent, *, flux_fraction=0.995, pad=0.15, min_pixels=32):
    """The smallest square box (index slices, and its extent) holding `flux_fraction` of the summed light.

    images: a list of 2-D arrays (summed, negative values ignored). The box is grown by
    `pad` of its size on each side and kept at least `min_pixels` across; used to zoom
    figures of sparse fields (a source-plane image is mostly empty sky).
    """
    total = sum(np.clip(np.nan_to_num(np.asarray(a, float)), 0, None) for a in images)
    ny, nx = total.shape
    s = total.sum()
    if not s > 0:
        return (slice(0, ny), slice(0, nx)), extent
    cut = (1.0 - flux_fraction) / 2.0
    bounds = []
    for axis in (1, 0):  # rows (y), then columns (x): cumulative light along each axis
        c = np.cumsum(total.sum(axis=axis)) / s
        bounds.append((int(np.searchsorted(c, cut)), int(np.searchsorted(c, 1.0 - cut)) + 1))
    (y0, y1), (x0, x1) = bounds
    half = max(y1 - y0, x1 - x0, min_pixels) * (0.5 + pad)
    cy, cx = 0.5 * (y0 + y1), 0.5 * (x0 + x1)
    ya, yb = int(max(0, cy - half)), int(min(ny, cy + half))
    xa, xb = int(max(0, cx - half)), int(min(nx, cx + half))
    px = (extent[1] - extent[0]) / nx
    py = (extent[3] - extent[2]) / ny
    sub = (extent[0] + xa * px, extent[0] + xb * px, extent[2] + ya * py, extent[2] + yb * py)
    return (slice(ya, yb), slice(xa, xb)), sub


def nice_length(span_arcsec: float) -> float:
    """A round scale-bar length (1, 2, 5 × 10^k arcsec) near a fifth of the span."""
    target = span_arcsec / 5.0
    k = math.floor(math.log10(target))
    for m in (5.0, 2.0, 1.0):
        if m * 10**k <= target:
            return m * 10**k
    return 10**k


def _fmt_arcsec(x: float) -> str:
    if x >= 1:
        return f'{x:g}"'
    return f"{x * 1000:g} mas"


def _scale_bar(ax, extent, colour):
    x0, x1, y0, y1 = extent
    length = nice_length(abs(x1 - x0))
    w, h = x1 - x0, y1 - y0
    xs = x0 + 0.06 * w
    ys = y0 + 0.07 * h
    ax.plot([xs, xs + length], [ys, ys], color=colour, lw=3, solid_capstyle="butt")
    ax.text(xs + length / 2, ys + 0.025 * h, _fmt_arcsec(length), color=colour, ha="center", va="bottom",
            fontsize=10, fontweight="bold")


def compass_directions(wcs):
    """Unit vectors (pixel x, y) towards North and East at the image centre, from the WCS."""
    from astropy.coordinates import SkyCoord
    import astropy.units as u

    ny, nx = wcs.pixel_shape[::-1] if wcs.pixel_shape else (1, 1)
    c = wcs.pixel_to_world(0.5 * (nx - 1), 0.5 * (ny - 1))
    p0 = np.array(wcs.world_to_pixel(c), float)
    step = 1.0 / 3600.0  # 1 arcsec on the sky
    out = []
    for dra, ddec in ((0.0, step), (step / np.cos(np.deg2rad(c.dec.deg)), 0.0)):
        p = SkyCoord(c.ra.deg + dra, c.dec.deg + ddec, unit=u.deg, frame=c.frame)
        d = np.array(wcs.world_to_pixel(p), float) - p0
        out.append(d / np.hypot(*d))
    return out[0], out[1]


def _compass(ax, extent, wcs, colour):
    """N and E arrows at the top right. The figures' axes run along the pixel axes (θ grids), so a
    pixel direction is drawn as is."""
    x0, x1, y0, y1 = extent
    w, h = x1 - x0, y1 - y0
    arm = 0.11 * min(abs(w), abs(h))
    base = np.array([x1 - 0.1 * w, y1 - 0.1 * h - arm])
    for label, d in zip("NE", compass_directions(wcs)):
        d = d * arm
        ax.annotate("", xy=tuple(base + d), xytext=tuple(base),
                    arrowprops=dict(arrowstyle="-|>", color=colour, lw=1.6))
        ax.text(*(base + 1.3 * d), label, color=colour, ha="center", va="center", fontsize=10,
                fontweight="bold")


def draw_sky(ax, image, extent, *, wcs=None, title=None, circles=(), curves=(), colour="w",
             cmap=None, norm=None, frame="θ"):
    """Draw `image` (2-D, or (ny, nx, 3) RGB in [0, 1]) over `extent` (arcsec) on ax, decorated.

    circles: (θ1, θ2, radius_arcsec, colour) tuples. curves: (N, 2) arrays in arcsec
    (e.g. critical curves), drawn dashed and clipped to the image. frame: "θ" (lens
    plane) or "β" (source plane) for the axis labels.
    """
    from matplotlib.patches import Circle

    ny, nx = np.shape(image)[:2]
    fig = ax.figure
    px_axes = ax.get_window_extent().width if fig is not None else nx
    # Upsampled: every data pixel a sharp block; downsampled: matplotlib's anti-aliasing.
    interp = "nearest" if px_axes >= nx else "antialiased"
    ax.imshow(image, origin="lower", extent=extent, interpolation=interp, cmap=cmap, norm=norm)
    for seg in curves:
        seg = np.asarray(seg)
        ax.plot(seg[:, 0], seg[:, 1], color="gold", lw=0.9, ls="--", alpha=0.8)
    for t1, t2, radius, col in circles:
        ax.add_patch(Circle((t1, t2), radius, fill=False, color=col, lw=1.6))
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    sym = r"\theta" if frame == "θ" else r"\beta"
    ax.set_xlabel(rf"${sym}_1$ [arcsec] (West →)")
    ax.set_ylabel(rf"${sym}_2$ [arcsec] (North ↑)")
    _scale_bar(ax, extent, colour)
    if wcs is not None:
        _compass(ax, extent, wcs, colour)
    if title:
        ax.set_title(title, fontsize=10)


def save_sky_figure(path, image, extent, *, min_px=600, dpi=110, caption=None, **kw) -> Path:
    """One decorated panel (see draw_sky) as a PNG whose image area is at least min_px across."""
    with _FIGURE_LOCK:
        return _save_sky_figure(path, image, extent, min_px=min_px, dpi=dpi, caption=caption,
                                **kw)


def _save_sky_figure(path, image, extent, *, min_px, dpi, caption, **kw) -> Path:
    from .io import atomic_write

    plt = _pyplot()
    ny, nx = np.shape(image)[:2]
    side_in = max(min_px, 600) / dpi  # the image axes, inches
    aspect = ny / nx
    left, right, top = 0.9, 0.25, 0.4  # margins, inches: labels, title
    bottom = 0.7 + (0.4 if caption else 0.0)
    w, h = left + side_in + right, bottom + side_in * aspect + top
    fig = plt.figure(figsize=(w, h), dpi=dpi)
    ax = fig.add_axes([left / w, bottom / h, side_in / w, side_in * aspect / h])
    try:
        draw_sky(ax, image, extent, **kw)
        if caption:
            fig.text(0.5, 0.005, caption, ha="center", va="bottom", fontsize=8, wrap=True)
        with atomic_write(path) as tmp:
            fig.savefig(tmp, format="png", dpi=dpi)
    finally:
        plt.close(fig)
    return Path(path)
