"""Hard scenes through the command line against an independent brute-force renderer.

Each scene is a TOML file given to ``clumpylen simulate --no-noise`` (a subprocess,
as a user would run it); its ``NOISELESS`` extension minus the sky is compared with a
numpy midpoint sum of the analytic surface brightness over ss × ss points per detector
pixel — through the analytic lens equation for the lensed scenes — that shares no code
with the project (the profile normalisation and b(n) come from scipy). The reference's
own convergence is reported as the change from ss/2 to ss samples.

Scenes (all psf = "none", so that only the pixel integrals and the lens are tested):
- ``thin``: an unlensed n = 0.2, q = 0.05 Sérsic of R_e one ACS pixel, off-centre;
- ``lensed-caustic``: an n = 1 host (R_e 50 mas, q 0.5) 20 mas from the point caustic of
  an SIS (θ_E = 1″), NIRCam 0.031″ pixels (not a multiple of the 2.5 mas lens pixels);
- ``lensed-compact``: an n = 4 host of R_e 5 mas 0.3″ from the SIS, 0.03″ pixels.

Run: ``python benchmarks/check_cli_hard_scenes.py [--ss 400]``; writes
benchmarks/results/cli_hard_scenes.{json,md}. About 2 minutes.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from astropy.io import fits
from scipy.special import gamma, gammaincinv

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

CLI = str(Path(sys.executable).with_name("clumpylen"))

HOST = {  # name: (magnitude, R_e arcsec, n, q, pa rad, centre β arcsec)
    "thin": (22.0, 0.05, 0.2, 0.05, 1.0, (0.015, -0.015)),
    "lensed-caustic": (24.0, 0.05, 1.0, 0.5, 0.4, (0.02, 0.0)),
    "lensed-compact": (24.0, 0.005, 4.0, 0.7, 0.3, (0.3, 0.05)),
}

SCENES = {
    "thin": """
[scene]
name = "thin"
z_source = 2.0
[source]
center_arcsec = [{cx}, {cy}]
[source.bulge]
magnitudes = {{ F814W = {mag} }}
re_arcsec = {re}
n = {n}
q = {q}
pa_rad = {pa}
[render]
field_arcsec = {{ x = [-0.6, 0.6], y = [-0.6, 0.6] }}
[[bands]]
instrument = "HST/ACS"
filter = "F814W"
exptime_s = 1000.0
sky_counts_per_s = 0.1
psf = "none"
""",
}

# the two lensed scenes differ in the host component, the field and the detector pixel
_LENSED = """
[scene]
name = "{name}"
z_source = 2.0
[source]
center_arcsec = [{cx}, {cy}]
[source.{component}]
magnitudes = {{ F150W = {mag} }}
re_arcsec = {re}
n = {n}
q = {q}
pa_rad = {pa}
[lens]
z_lens = 0.4
center_radec_deg = [150.0, 2.0]
components = [ {{ kind = "sis", theta_e_arcsec = 1.0 }} ]
[render]
field_arcsec = {{ x = [-{half}, {half}], y = [-{half}, {half}] }}
accuracy = {{ preset = "default", source_flux_fraction = 0.9999 }}
[[bands]]
instrument = "JWST/NIRCam"
filter = "F150W"
exptime_s = 3000.0
sky_counts_per_s = 0.2
psf = "none"
"""
SCENES["lensed-caustic"] = _LENSED.replace("{name}", "lensed-caustic").replace(
    "{component}", "disk").replace("{half}", "1.55")
SCENES["lensed-compact"] = _LENSED.replace("{name}", "lensed-compact").replace(
    "{component}", "bulge").replace("{half}", "1.5") + "pixel_arcsec = 0.03\n"



def sersic(x, y, flux, re, n, q, pa, cx, cy):
    """Surface brightness (per arcsec²) of an elliptical Sérsic of total flux `flux`."""
    b = gammaincinv(2 * n, 0.5)
    dx, dy = x - cx, y - cy
    u = np.cos(pa) * dx + np.sin(pa) * dy
    v = -np.sin(pa) * dx + np.cos(pa) * dy
    r = np.sqrt(u**2 + (v / q) ** 2)
    norm = flux / (2 * np.pi * q * re**2 * n * gamma(2 * n) / b ** (2 * n))
    return norm * np.exp(-b * (r / re) ** (1 / n))


def reference(name, shape, x0, y0, pix, flux, ss):
    """Midpoint sums over ss × ss points of every detector pixel where light can land."""
    _, re, n, q, pa, (cx, cy) = HOST[name]
    lensed = name != "thin"
    off = (np.arange(ss) + 0.5) / ss - 0.5
    out = np.zeros(shape)
    for j in range(shape[0]):
        for i in range(shape[1]):
            xc, yc = x0 + i * pix, y0 + j * pix
            if lensed and abs(np.hypot(xc, yc) - 1.0) > 0.45:
                continue            # the images lie within 0.45" of the Einstein ring
            x, y = np.meshgrid(xc + off * pix, yc + off * pix)
            if lensed:
                r = np.hypot(x, y)
                x, y = x - x / r, y - y / r         # β = θ − θ_E θ/|θ|, θ_E = 1"
            out[j, i] = sersic(x, y, flux, re, n, q, pa, cx, cy).mean() * pix**2
    return out


def run(name, ss, workdir):
    mag, re, n, q, pa, (cx, cy) = HOST[name]
    scene = workdir / f"{name}.toml"
    scene.write_text(SCENES[name].format(mag=mag, re=re, n=n, q=q, pa=pa, cx=cx, cy=cy))
    out = workdir / name
    t = time.perf_counter()
    subprocess.run([CLI, "simulate", str(scene), "--out", str(out), "--no-noise", "--quiet"],
                   check=True)
    cli_s = time.perf_counter() - t
    band = next((out / "bands").glob("*.fits"))
    with fits.open(band) as h:
        hdr = h[0].header
        img = h["NOISELESS"].data.astype(float) - hdr["SKYLEVEL"]
    pix = hdr["PIXSCALE"]
    x0, y0 = (1 - hdr["CRPIX1"]) * pix, (1 - hdr["CRPIX2"]) * pix   # centre of pixel [0, 0]
    flux = 10 ** (-0.4 * (mag - hdr["ZP_AB"]))
    ref = reference(name, img.shape, x0, y0, pix, flux, ss)
    half = reference(name, img.shape, x0, y0, pix, flux, ss // 2)
    sigma = np.sqrt(hdr["SKYLEVEL"] * hdr["EXPTIME"]) / hdr["EXPTIME"]
    d = img - ref
    row = dict(scene=name, cli_s=cli_s, ss=ss, peak_over_sigma=float(ref.max() / sigma),
               max_err_rel_peak=float(np.abs(d).max() / ref.max()),
               max_err_sigma=float(np.abs(d).max() / sigma),
               flux_rel_err=float(img.sum() / ref.sum() - 1),
               reference_change_rel_peak=float(np.abs(ref - half).max() / ref.max()),
               reference_flux_change=float(ref.sum() / half.sum() - 1))
    print({k: C.fmt(v) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ss", type=int, default=400, help="reference samples per pixel side")
    ap.add_argument("--scenes", default=",".join(SCENES))
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        rows = [run(name, args.ss, Path(tmp)) for name in args.scenes.split(",")]
    meta = dict(machine=C.machine(), hosts={k: dict(zip(("mag", "re_arcsec", "n", "q", "pa_rad",
                                                          "center_arcsec"), v))
                                             for k, v in HOST.items()})
    C.write_json("cli_hard_scenes", {"meta": meta, "rows": rows})
    cols = [("scene", "scene"), ("peak_over_sigma", "peak/σ"),
            ("max_err_rel_peak", "max |Δ|/peak"), ("max_err_sigma", "max |Δ|/σ"),
            ("flux_rel_err", "total flux error"),
            ("reference_change_rel_peak", "reference ss/2→ss, /peak"),
            ("reference_flux_change", "reference ss/2→ss, flux"), ("cli_s", "CLI s")]
    C.write_text("cli_hard_scenes.md", "\n".join([
        "# Hard scenes through the CLI against brute force", "",
        "Generated by `benchmarks/check_cli_hard_scenes.py` (see its docstring).", "",
        C.markdown_table(rows, cols), ""]))
    return rows


if __name__ == "__main__":
    main()
