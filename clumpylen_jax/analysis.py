"""Depth and detectability of a finished run: limiting magnitudes and clump S/N.

`analyze_run(run_dir)` reads what `clumpylen simulate` wrote (bands/*.fits,
catalog.ecsv, summary.json) and measures, per band, as the paper does
(Sect. "Results", "Abell 2744"):

- the limiting magnitude from N random circular apertures on empty sky: the
  standard deviation σ of the sky-subtracted aperture sums gives
  m_lim = ZP − 2.5 log10(nσ · σ);
- the S/N of each clump: the aperture sum (image − sky) at the clump's
  brightest lensed image over sqrt(Σ VARIANCE) in the same aperture.

Results are added to summary.json under "analysis" and returned. Everything
here is NumPy/photutils on the files: it needs no model, only the lens (for
image positions), rebuilt from the resolved scene in summary.json.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .constants import ARCSEC_PER_RAD

__all__ = [
    "analyze_run",
    "band_data",
    "default_aperture_radius_arcsec",
    "empty_sky_mask",
    "limiting_magnitude",
    "clump_image_positions",
    "aperture_snr",
    "theta_to_pixel",
]

# A pixel is "empty" when the source (noiseless − sky) is below this fraction
# of the per-pixel sky noise: far below anything an aperture could detect.
EMPTY_FRACTION_OF_SKY_SIGMA = 0.01


# ------------------------------------------------------------------ reading a run


def band_data(path) -> dict:
    """One band's FITS file as arrays and header numbers.

    Returns {"filter", "image", "noiseless", "variance", "zp", "sky", "pixel_arcsec",
    "exptime_s", "crpix", "telescope", "instrument"}: images in counts/s per pixel,
    crpix the FITS (1-based) reference pixel of the θ frame.
    """
    from astropy.io import fits

    with fits.open(path) as hdul:
        h = hdul[0].header
        out = {
            "filter": str(h.get("FILTER", Path(path).stem)),
            "image": np.asarray(hdul[0].data, float),
            "noiseless": np.asarray(hdul["NOISELESS"].data, float),
            "variance": np.asarray(hdul["VARIANCE"].data, float),
            "zp": float(h["ZP_AB"]),
            "sky": float(h.get("SKYLEVEL", 0.0)),
            "pixel_arcsec": float(h["PIXSCALE"]),
            "exptime_s": float(h.get("EXPTIME", 0.0)),
            "crpix": (float(h["CRPIX1"]), float(h["CRPIX2"])),
            "telescope": str(h.get("TELESCOP", "")),
            "instrument": str(h.get("INSTRUME", "")),
        }
        if "UNLENSED" in hdul:
            out["unlensed"] = np.asarray(hdul["UNLENSED"].data, float)
    return out


def theta_to_pixel(theta1_arcsec, theta2_arcsec, crpix, pixel_arcsec):
    """0-based (x, y) pixel coordinates of θ (arcsec) on a band image.

    The band WCS (io.make_wcs) puts θ = 0 at CRPIX with x along +θ1 and y along
    +θ2, so the map is linear; this avoids the TAN projection's mas-level
    curvature, which the θ frame does not have.
    """
    x = crpix[0] - 1.0 + np.asarray(theta1_arcsec, float) / pixel_arcsec
    y = crpix[1] - 1.0 + np.asarray(theta2_arcsec, float) / pixel_arcsec
    return x, y


def _read_summary(run_dir: Path) -> dict:
    from .errors import ConfigError

    path = run_dir / "summary.json"
    try:
        with open(path, encoding="utf-8") as fh:
            summary = json.load(fh)
    except (ValueError, UnicodeDecodeError) as exc:   # JSONDecodeError is a ValueError
        raise ConfigError(str(path), "<unreadable>", f"the JSON summary `simulate` wrote ({exc})") from exc
    if not isinstance(summary, dict):
        raise ConfigError(str(path), type(summary).__name__, "a JSON object (the run's summary)")
    return summary


def _read_catalog(run_dir: Path):
    path = run_dir / "catalog.ecsv"
    if not path.exists():
        return None
    from astropy.table import Table

    return Table.read(path, format="ascii.ecsv")


def _lens_from_summary(summary: dict, run_dir: Path):
    """The run's lens (None when unlensed), rebuilt from the resolved scene."""
    scene_d = summary.get("scene") or {}
    if not scene_d.get("lens"):
        return None
    from . import pipeline
    from .scene import scene_from_dict

    return pipeline.build_lens(scene_from_dict(scene_d, base_dir=run_dir))


# ------------------------------------------------------------------ apertures


def default_aperture_radius_arcsec(band: dict, psf: str | None) -> float:
    """1.5 × the PSF FWHM (diffraction λ_pivot/D, broadened by the pixel), or 0.1″ without a PSF."""
    if psf in (None, "none"):
        return 0.1
    try:
        from .filters import load_filter
        from .psf import TELESCOPE_DIAMETER_M

        try:
            filt = load_filter(f"{band['instrument']}/{band['filter']}")
        except Exception:  # the instrument header spelling differs from the filter table's
            filt = load_filter(band["filter"])
        tel = "JWST" if "JWST" in band["telescope"].upper() else "HST"
        fwhm = 1.03 * filt.pivot_wavelength_aa * 1e-10 / TELESCOPE_DIAMETER_M[tel] * ARCSEC_PER_RAD
    except Exception:  # an unknown filter: fall back to the no-PSF default
        return 0.1
    # A pixel-sampled PSF is about the diffraction core convolved with a pixel.
    return 1.5 * math.hypot(fwhm, band["pixel_arcsec"])


def empty_sky_mask(noiseless, variance, sky, *, fraction=EMPTY_FRACTION_OF_SKY_SIGMA):
    """Pixels where the source (noiseless − sky) is below `fraction` × the sky's per-pixel σ.

    The sky σ is the smallest σ in the VARIANCE map (pixels with sky only);
    with no noise at all every pixel with zero source is empty.
    """
    src = np.abs(np.asarray(noiseless) - sky)
    var = np.asarray(variance)
    sigma_sky = float(np.sqrt(np.min(var[var > 0]))) if np.any(var > 0) else 0.0
    return src <= fraction * sigma_sky


def _disk(radius_px: float) -> np.ndarray:
    r = int(math.ceil(radius_px))
    y, x = np.mgrid[-r:r + 1, -r:r + 1]
    return x * x + y * y <= radius_px * radius_px


def _place_apertures(mask, radius_px, n, rng):
    """Up to n centres (x, y) whose whole aperture lies on `mask`, non-overlapping when possible.

    Candidates are the mask eroded by the aperture (+1 pixel for the partial
    pixels photutils counts) and kept off the border; they are drawn in random
    order and accepted if at least one diameter from every accepted one. If the
    empty area cannot hold n separate apertures, the rest overlap (correlated
    sums, but still sky).
    """
    from scipy import ndimage

    inner = np.zeros_like(mask)
    m = int(math.ceil(radius_px)) + 1
    if mask.shape[0] > 2 * m and mask.shape[1] > 2 * m:
        inner[m:-m, m:-m] = mask[m:-m, m:-m]
    ok = ndimage.binary_erosion(inner, structure=_disk(radius_px + 1.0))
    ys, xs = np.nonzero(ok)
    if len(xs) == 0:
        return np.zeros((0, 2))
    order = rng.permutation(len(xs))
    # Sub-pixel jitter so that centres do not all fall on pixel centres.
    cand = np.stack([xs[order], ys[order]], axis=1) + rng.uniform(-0.5, 0.5, (len(xs), 2))
    chosen = []
    for c in cand:
        if all(np.hypot(*(c - p)) >= 2 * radius_px for p in chosen):
            chosen.append(c)
            if len(chosen) == n:
                break
    if len(chosen) < n:  # not enough room: fill with overlapping ones
        chosen += [cand[i % len(cand)] for i in range(n - len(chosen))]
    return np.asarray(chosen)


def _aperture_sums(image, centres_xy, radius_px):
    from photutils.aperture import CircularAperture, aperture_photometry

    if len(centres_xy) == 0:
        return np.zeros(0)
    ap = CircularAperture(centres_xy, r=radius_px)
    return np.asarray(aperture_photometry(image, ap)["aperture_sum"], float)


def limiting_magnitude(band: dict, *, radius_arcsec, n_apertures=100, nsigma=5.0, seed=0) -> dict:
    """m_lim = ZP − 2.5 log10(nsigma · std of N empty-sky aperture sums), and the expected value.

    "expected" uses the VARIANCE map instead of the noise draw: the σ of an
    aperture sum of independent pixels is sqrt(Σ var), a check on the
    empirical number.
    """
    radius_px = radius_arcsec / band["pixel_arcsec"]
    mask = empty_sky_mask(band["noiseless"], band["variance"], band["sky"])
    rng = np.random.default_rng(seed)
    centres = _place_apertures(mask, radius_px, int(n_apertures), rng)
    sums = _aperture_sums(band["image"] - band["sky"], centres, radius_px)
    var_sums = _aperture_sums(band["variance"], centres, radius_px)
    std = float(np.std(sums, ddof=1)) if len(sums) > 1 else float("nan")
    sigma_exp = float(np.sqrt(np.mean(var_sums))) if len(var_sums) else float("nan")

    def mag(sigma):
        return band["zp"] - 2.5 * math.log10(nsigma * sigma) if sigma > 0 else float("nan")

    return {"mag_lim": mag(std), "mag_lim_expected": mag(sigma_exp), "nsigma": nsigma,
            "aperture_radius_arcsec": radius_arcsec, "n_apertures": int(len(centres)),
            "aperture_std_counts_per_s": std, "empty_fraction": float(np.mean(mask))}


# ------------------------------------------------------------------ clumps


def clump_image_positions(catalog, lens, field, *, pixel_arcsec=None, chunk=256):
    """θ (arcsec) and |μ| of each clump's most magnified image inside `field`.

    Unlensed (lens None): θ = β, μ = 1. Lensed: `find_images` vmapped over the
    clumps (the field grid is traced once per chunk, not per clump). A clump with
    no image in the field gets NaN.
    """
    b1 = np.asarray(catalog["beta1_arcsec"], float)
    b2 = np.asarray(catalog["beta2_arcsec"], float)
    if lens is None:
        return b1, b2, np.ones_like(b1)
    import jax
    import jax.numpy as jnp

    from .lensing.images import find_images

    (x0, x1), (y0, y1) = field
    field = ((float(x0), float(x1)), (float(y0), float(y1)))
    if pixel_arcsec is None:
        # Fine enough to separate the images of a typical arc, coarse enough to be cheap.
        pixel_arcsec = max(x1 - x0, y1 - y0) / 200.0
    fn = jax.jit(jax.vmap(lambda a, b: find_images(lens, a, b, field=field, pixel_arcsec=pixel_arcsec)))
    t1 = np.full(b1.shape, np.nan)
    t2 = np.full(b1.shape, np.nan)
    mu = np.full(b1.shape, np.nan)
    for s in range(0, len(b1), chunk):
        # Pad to a fixed chunk so one compile serves every chunk.
        n = min(chunk, len(b1) - s)
        pa = np.zeros(chunk)
        pb = np.zeros(chunk)
        pa[:n], pb[:n] = b1[s:s + n], b2[s:s + n]
        im = fn(jnp.asarray(pa), jnp.asarray(pb))
        valid = np.asarray(im.valid)[:n]
        amu = np.where(valid, np.abs(np.asarray(im.magnification)[:n]), -1.0)
        k = np.argmax(amu, axis=1)
        rows = np.arange(n)
        good = amu[rows, k] > 0
        t1[s:s + n] = np.where(good, np.asarray(im.theta1)[:n][rows, k], np.nan)
        t2[s:s + n] = np.where(good, np.asarray(im.theta2)[:n][rows, k], np.nan)
        mu[s:s + n] = np.where(good, amu[rows, k], np.nan)
    return t1, t2, mu


def aperture_snr(band: dict, theta1_arcsec, theta2_arcsec, radius_arcsec):
    """S/N = Σ(image − sky) / sqrt(Σ VARIANCE) in apertures at θ (NaN off the image)."""
    x, y = theta_to_pixel(theta1_arcsec, theta2_arcsec, band["crpix"], band["pixel_arcsec"])
    ny, nx = band["image"].shape
    inside = np.isfinite(x) & np.isfinite(y) & (x >= -0.5) & (x <= nx - 0.5) & (y >= -0.5) & (y <= ny - 0.5)
    snr = np.full(np.shape(x), np.nan)
    flux = np.full(np.shape(x), np.nan)
    if np.any(inside):
        r = radius_arcsec / band["pixel_arcsec"]
        xy = np.stack([x[inside], y[inside]], axis=1)
        s = _aperture_sums(band["image"] - band["sky"], xy, r)
        v = _aperture_sums(band["variance"], xy, r)
        flux[inside] = s
        snr[inside] = np.where(v > 0, s / np.sqrt(np.where(v > 0, v, 1.0)), np.nan)
    return snr, flux


def _clump_report(band, catalog, t1, t2, mu, radius_arcsec, snr_threshold, top):
    """S/N of every clump in one band; the `top` brightest (apparent magnitude) listed."""
    snr, flux = aperture_snr(band, t1, t2, radius_arcsec)
    col = f"mag_{band['filter']}"
    mag = np.asarray(catalog[col], float) if col in catalog.colnames else np.full(len(catalog), np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        apparent = mag - 2.5 * np.log10(mu)
    rank = np.argsort(np.where(np.isfinite(apparent) & np.isfinite(snr), apparent, np.inf))
    ids = np.asarray(catalog["id"]) if "id" in catalog.colnames else np.arange(len(catalog))
    brightest = [{"id": int(ids[i]), "mag": float(mag[i]), "apparent_mag": float(apparent[i]),
                  "magnification": float(mu[i]), "theta_arcsec": [float(t1[i]), float(t2[i])],
                  "flux_counts_per_s": float(flux[i]), "snr": float(snr[i])}
                 for i in rank[:top] if np.isfinite(snr[i])]
    measured = np.isfinite(snr)
    return {"n_clumps": int(len(catalog)), "n_measured": int(measured.sum()),
            "n_above_threshold": int(np.sum(snr[measured] > snr_threshold)),
            "snr_threshold": float(snr_threshold), "aperture_radius_arcsec": radius_arcsec,
            "brightest": brightest}


# ------------------------------------------------------------------ the run


def analyze_run(run_dir, *, n_apertures=100, aperture_radius_arcsec=None, nsigma=5.0, seed=0,
                snr_threshold=3.0, top=10) -> dict:
    """Limiting magnitude and clump S/N per band of a finished run; saved in summary.json.

    aperture_radius_arcsec: None → 1.5 × PSF FWHM per band (0.1″ without a PSF).
    Returns {"bands": {FILTER: {"limit": {...}, "clumps": {...} or None}}, "settings": {...}}.
    """
    from .errors import ConfigError
    from .io import write_json

    run_dir = Path(run_dir)
    if not (run_dir / "summary.json").exists():
        raise FileNotFoundError(f"not a run directory (no summary.json): {run_dir}")
    if not (isinstance(n_apertures, int) and n_apertures >= 2):
        raise ConfigError("n_apertures", n_apertures, "an integer >= 2")
    if not (nsigma > 0):
        raise ConfigError("nsigma", nsigma, "a positive number")
    if not (np.isfinite(snr_threshold) and snr_threshold > 0):
        raise ConfigError("--snr-threshold", snr_threshold, "a finite S/N > 0")
    if aperture_radius_arcsec is not None and not (aperture_radius_arcsec > 0):
        raise ConfigError("aperture_radius_arcsec", aperture_radius_arcsec, "a positive number or None")
    summary = _read_summary(run_dir)
    catalog = _read_catalog(run_dir)
    band_files = sorted((run_dir / "bands").glob("*.fits"))

    positions = None
    if catalog is not None and len(catalog):
        lens = _lens_from_summary(summary, run_dir)
        positions = clump_image_positions(catalog, lens, summary.get("field_arcsec"))

    results = {}
    for path in band_files:
        band = band_data(path)
        psf = (summary.get("bands", {}).get(band["filter"]) or {}).get("psf")
        radius = aperture_radius_arcsec or default_aperture_radius_arcsec(band, psf)
        entry = {"limit": limiting_magnitude(band, radius_arcsec=radius, n_apertures=n_apertures,
                                             nsigma=nsigma, seed=seed),
                 "clumps": None}
        if positions is not None:
            entry["clumps"] = _clump_report(band, catalog, *positions, radius, snr_threshold, top)
        results[band["filter"]] = entry
    analysis = {"bands": results,
                "settings": {"n_apertures": n_apertures, "nsigma": nsigma, "seed": seed,
                             "snr_threshold": snr_threshold,
                             "aperture_radius_arcsec": aperture_radius_arcsec,
                             "empty_fraction_of_sky_sigma": EMPTY_FRACTION_OF_SKY_SIGMA}}
    # Re-read just before writing so a concurrent `plot`/other writer's keys survive.
    summary = _read_summary(run_dir)
    summary["analysis"] = analysis
    write_json(run_dir / "summary.json", summary)
    from .rundir import update_manifest
    update_manifest(run_dir, "summary.json")   # the run stays whole: its manifest follows
    return analysis
