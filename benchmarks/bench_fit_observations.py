"""A three-band fit of the real JWST cutout (120² pixels, F115W/F150W/F200W, MJy/sr) with
~10 clumps, compile included: the speed target of issue 17 (< 1 min on 2 cores).

    .venv/bin/python benchmarks/bench_fit_observations.py [--threshold 0.05] [--out DIR]

Clump starts: peaks of the F150W image smoothed by a 1-pixel Gaussian above `threshold`
MJy/sr (photutils.find_peaks, 5-pixel box): 9 at 0.05. Prints and writes
benchmarks/results/fit_observations.json: wall time of each stage, LM steps, χ²/dof.
The machine's load average is recorded beside the times (a shared host inflates them).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real" / "abell_s1063_sys4_im1"


def write_scene(d: Path, threshold: float) -> Path:
    import numpy as np
    from astropy.io import fits
    from astropy.table import Table
    from photutils.detection import find_peaks
    from scipy.ndimage import gaussian_filter

    sci = fits.getdata(DATA / "s1063_sys4_im1_f150w.fits", "SCI")
    peaks = find_peaks(gaussian_filter(np.asarray(sci, float), 1.0), threshold=threshold, box_size=5)
    Table({"x_pix": np.asarray(peaks["x_peak"], float),
           "y_pix": np.asarray(peaks["y_peak"], float)}).write(d / "starts.ecsv", overwrite=True)
    text = '[scene]\nname = "s1063-sys4-im1"\n'
    for f in ("f115w", "f150w", "f200w"):
        text += (f'\n[[observations]]\nfilter = "{f.upper()}"\ninstrument = "JWST/NIRCam"\n'
                 f'image = "{DATA / f"s1063_sys4_im1_{f}.fits"}"\n'
                 f'psf = "{DATA / f"psf_webbpsf_{f}.fits"}"\n')
    text += '\n[fit]\nclumps = "starts.ecsv"\n'
    (d / "scene.toml").write_text(text)
    return d / "scene.toml"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--threshold", type=float, default=0.05)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    if not DATA.is_dir():
        raise SystemExit(f"data not found: {DATA}")
    t0 = time.perf_counter()
    import clumpylen_jax  # noqa: F401
    from clumpylen_jax.observations.run import fit_observation_scene
    with tempfile.TemporaryDirectory() as tmp:
        scene = write_scene(Path(tmp), args.threshold)
        out = args.out or os.path.join(tmp, "out")
        fit, table, host, files = fit_observation_scene(str(scene), out)
        summary = json.loads(Path(out, "summary.json").read_text())
    wall = time.perf_counter() - t0
    result = {"n_clumps": fit.n_clumps, "wall_s_total_with_imports": round(wall, 1),
              "timings_s": fit.timings_s, "steps": fit.steps,
              "chi2_per_dof": summary["chi2_per_dof"], "n_free": summary["n_free"],
              "load_average_1min": os.getloadavg()[0], "cpu_count": os.cpu_count()}
    print(json.dumps(result, indent=1))
    res = Path(__file__).resolve().parent / "results"
    res.mkdir(exist_ok=True)
    (res / "fit_observations.json").write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
