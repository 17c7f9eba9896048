"""A synthetic run directory (what `clumpylen simulate` writes), made in well under a second.

The pipeline takes minutes to compile on the shared test machine; analysis and
plotting only read files, so the tests give them files with known content:
Gaussian clumps of known flux on a flat sky with Gaussian photon noise, a
catalogue, and a summary whose resolved scene rebuilds the lens (SIS θ_E = 1″).
"""

from __future__ import annotations

import textwrap

import numpy as np
from astropy.table import Table

from clumpylen_jax import io, rundir
from clumpylen_jax import scene as sc

PIXEL = 0.03
HALF = 1.5  # field half-width, arcsec

SCENE_TOML = """
[scene]
name = "fake"
seed = 1
z_source = 2.0
[source]
center_arcsec = [{cx}, {cy}]
[source.bulge]
magnitudes = {{ F150W = 30.0, F200W = 30.0 }}
re_arcsec = 0.05
{lens}
[render]
source_pixel_arcsec = 0.005
lens_pixel_arcsec = 0.01
field_arcsec = {{ x = [-{h}, {h}], y = [-{h}, {h}] }}
accuracy = "fast"
[[bands]]
instrument = "JWST/NIRCam"
filter = "F150W"
exptime_s = 1000.0
sky_counts_per_s = 0.15
psf = "none"
[[bands]]
instrument = "JWST/NIRCam"
filter = "F200W"
exptime_s = 1000.0
sky_counts_per_s = 0.16
psf = "none"
"""

LENS_TOML = """
[lens]
z_lens = 0.4
center_radec_deg = [64.0, -24.0]
components = [{ kind = "sis", theta_e_arcsec = 1.0 }]
"""


def _gaussians(shape, x, y, flux, sigma_px):
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    img = np.zeros(shape)
    for xi, yi, fi in zip(x, y, flux):
        img += fi * np.exp(-0.5 * ((xx - xi) ** 2 + (yy - yi) ** 2) / sigma_px**2) / (2 * np.pi * sigma_px**2)
    return img


def make_fake_run(root, *, lensed=False, exptime_s=1000.0, seed=0, clumps=None, zp=28.0):
    """Write a run into `root` and return its path.

    clumps: list of (theta1, theta2, flux counts/s, mag) in the lens plane;
    for an unlensed run θ = β. For a lensed run the catalogue's β are those
    of the SIS (β = θ − θ_E θ/|θ|), so the brightest image is back at θ.
    """
    root.mkdir(parents=True, exist_ok=True)
    if clumps is None:  # one bright and one faint clump; outside θ_E when lensed (the brighter image)
        clumps = [(1.1, 0.3, 2.0, 27.2), (-0.9, -0.8, 0.1, 30.5)] if lensed else \
                 [(0.4, 0.3, 2.0, 27.2), (-0.5, -0.4, 0.1, 30.5)]
    toml = SCENE_TOML.format(cx=0.1, cy=0.0, h=HALF, lens=LENS_TOML if lensed else "")
    (root / "scene.toml").write_text(textwrap.dedent(toml))
    scene = sc.load_scene(str(root / "scene.toml"))
    n = int(round(2 * HALF / PIXEL))
    theta0 = -HALF + 0.5 * PIXEL  # θ of pixel 0's centre
    wcs = io.make_wcs((64.0, -24.0), PIXEL, (n, n), (theta0, theta0))
    rng = np.random.default_rng(seed)
    t1 = np.array([c[0] for c in clumps])
    t2 = np.array([c[1] for c in clumps])
    flux = np.array([c[2] for c in clumps])
    src = _gaussians((n, n), (t1 - theta0) / PIXEL, (t2 - theta0) / PIXEL, flux, 1.5)
    bands = {}
    for b in scene.bands:
        noiseless = src + b.sky_counts_per_s
        var = noiseless / exptime_s
        image = noiseless + rng.normal(size=noiseless.shape) * np.sqrt(var)
        header = {"TELESCOP": "JWST", "INSTRUME": "NIRCAM", "FILTER": b.filter, "EXPTIME": exptime_s,
                  "ZP_AB": zp, "PIXSCALE": PIXEL, "SKYLEVEL": b.sky_counts_per_s, "SEED": seed}
        io.write_band_fits(root / "bands" / f"{b.filter}.fits", image, noiseless=noiseless, variance=var,
                           unlensed=src[n // 3: 2 * n // 3, n // 3: 2 * n // 3], header=header, wcs=wcs,
                           unlensed_wcs=wcs)
        bands[b.filter] = {"psf": "none", "pixel_arcsec": PIXEL, "zeropoint_ab": zp}
    r = np.hypot(t1, t2)
    scale = (1.0 - 1.0 / r) if lensed else np.ones_like(r)  # SIS: β = θ (1 − θ_E/|θ|)
    mags = np.array([c[3] for c in clumps])
    table = Table({"id": np.arange(len(clumps)), "beta1_arcsec": t1 * scale, "beta2_arcsec": t2 * scale,
                   "mass_msun": 10 ** rng.uniform(4, 7, len(clumps)), "re_pc": rng.uniform(1, 20, len(clumps)),
                   "re_arcsec": np.full(len(clumps), 0.002), "q": np.ones(len(clumps)),
                   "pa_rad": np.zeros(len(clumps)), "age_myr": 10 ** rng.uniform(0, 2.7, len(clumps)),
                   "sersic_n": np.full(len(clumps), 0.5), "mag_F150W": mags, "mag_F200W": mags,
                   "magnification": np.ones(len(clumps))})
    io.write_catalog(root / "catalog.ecsv", table)
    io.write_json(root / "summary.json", {"scene": sc.resolved_dict(scene), "bands": bands,
                                          "field_arcsec": [[-HALF, HALF], [-HALF, HALF]],
                                          "timings_s": {"total": 0.0}})
    rundir.write_manifest(root, {"seed": seed, "scene": "fake"})   # as simulate does
    return root
