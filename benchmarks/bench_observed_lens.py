"""`clumpylen fit` through a lens model with its own WCS, checked against the truth (issue 17).

The JWST i2d-like fixture (`fixtures/jwst_like_f200w_i2d.fits`: MJy/sr, a celestial WCS
rotated by 25°) is a clumpy disk at z = 2 behind the fixtures' SIS, whose HFF-format
deflection maps (`fixtures/lens_hff_*-arcsec-deflect.fits`, 0.2" pixels, their own WCS) are
given to the fit as `[lens] deflection`. The fit finds and counts clumps in the image plane
(`clumps = "auto"`, n = 0.5 as the fixture's clumps); the lens then maps each fitted clump to
the source plane. The check: for each of the four true clumps (`fixtures/clumps.ecsv`, source
plane), the fitted clumps whose β lies within 0.03" — one per image of it — with their β,
|μ|, intrinsic R_e and intrinsic magnitude beside the truth. Agreement in β says the cutout
landed on the map at the right sky position, through the rotated WCS.

    .venv/bin/python benchmarks/bench_observed_lens.py [--fit-dir DIR]

--fit-dir: read an existing output folder of the same command instead of fitting (the fit
took 391 s on 2 shared cores on 2026-11-27, ~30 min a day earlier). Writes
benchmarks/results/observed_lens.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from astropy.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, write_json, write_text  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FIX = ROOT / "fixtures"
MATCH_ARCSEC = 0.03

SCENE = f"""[scene]
name = "fixture-sis-lens-model"
z_source = 2.0

[[observations]]
filter = "F200W"
image = "{FIX / 'jwst_like_f200w_i2d.fits'}"
psf = "{FIX / 'psf_nircam_f200w_detsamp.fits'}"

[fit]
clumps = "auto"
clump_n = 0.5
clump_shape = "elliptical"

[lens]
z_lens = 0.396
center_radec_deg = [64.038142, -24.067472]
deflection = {{ x = "{FIX / 'lens_hff_x-arcsec-deflect.fits'}", y = "{FIX / 'lens_hff_y-arcsec-deflect.fits'}" }}
"""


def run_fit(out: Path) -> float:
    scene = out.parent / "scene.toml"
    scene.write_text(SCENE)
    cli = Path(sys.executable).with_name("clumpylen")
    env = dict(os.environ, CLUMPYLEN_CACHE=str(out.parent / "cache"))
    t = time.perf_counter()
    subprocess.run([str(cli), "fit", str(scene), "--out", str(out)], check=True, env=env)
    return time.perf_counter() - t


def compare(fit_dir: Path) -> list:
    t = Table.read(fit_dir / "fit.ecsv")
    truth = Table.read(FIX / "clumps.ecsv")
    rows = []
    for r in truth:
        d = np.hypot(t["beta1_arcsec"] - r["beta1_arcsec"], t["beta2_arcsec"] - r["beta2_arcsec"])
        for i in np.flatnonzero(d < MATCH_ARCSEC):
            rows.append({"true_id": int(r["id"]), "true_beta": [float(r["beta1_arcsec"]),
                                                               float(r["beta2_arcsec"])],
                         "true_re_arcsec": float(r["re_arcsec"]),
                         "true_mag_F200W": float(r["mag_F200W"]),
                         "fit_id": int(t["id"][i]), "x_pix": float(t["x_pix"][i]),
                         "y_pix": float(t["y_pix"][i]),
                         "beta": [float(t["beta1_arcsec"][i]), float(t["beta2_arcsec"][i])],
                         "beta_err": [float(t["beta1_arcsec_err"][i]),
                                      float(t["beta2_arcsec_err"][i])],
                         "magnification": float(t["magnification"][i]),
                         "re_arcsec": float(t["re_arcsec"][i]),
                         "re_arcsec_err": float(t["re_arcsec_err"][i]),
                         "mag_int_F200W": float(t["mag_int_F200W"][i]),
                         "mag_int_F200W_err": float(t["mag_int_F200W_err"][i]),
                         "flag": int(t["flag"][i]),
                         "source_id": int(t["source_id"][i]) if "source_id" in t.colnames
                         else None})
    return rows


def group_lines(summary, rows) -> list:
    """The fit's images of one source clump (summary.json `multiple_images`), each member with
    the true clump its β matches: a group is right when all its members match one."""
    truth_of = {}
    for r in rows:
        truth_of.setdefault(r["fit_id"], set()).add(r["true_id"])
    groups = summary.get("multiple_images", [])
    lines = ["", "Images grouped by the fit (`source_id`; β within `image_match_arcsec` and "
             "opposite parity or ≥ `image_separation_min_arcsec` apart):", ""]
    if not groups:
        return lines + ["none"]
    lines += ["| source_id | fitted clumps | the true clump of each | colour χ² / dof |",
              "|---|---|---|---|"]
    for g in groups:
        true = [sorted(truth_of.get(m, [])) for m in g["members"]]
        lines.append(f"| {g['source_id']} | {g['members']} | {true} | "
                     f"{g['colour_chi2']:.2f} / {g['colour_dof']} |")
    return lines


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fit-dir", type=Path, default=None)
    args = ap.parse_args()
    wall = None
    if args.fit_dir is None:
        work = Path(tempfile.mkdtemp(prefix="observed-lens-"))
        args.fit_dir = work / "out"
        wall = run_fit(args.fit_dir)
    summary = json.loads((args.fit_dir / "summary.json").read_text())
    rows = compare(args.fit_dir)
    payload = {"machine": machine(), "fit_dir": str(args.fit_dir), "wall_s": wall,
               "n_clumps": summary["n_clumps"], "chi2_per_dof": summary["chi2_per_dof"],
               "lens": summary["lens"], "matches": rows,
               "multiple_images": summary.get("multiple_images", [])}
    write_json("observed_lens", payload)
    lines = ["# `clumpylen fit` through deflection maps with their own WCS (fixture SIS)", "",
             f"{payload['machine']['date']}; fit wall "
             f"{'(read from ' + str(args.fit_dir) + ')' if wall is None else f'{wall:.0f} s'}; "
             f"{summary['n_clumps']} clumps fitted; χ²/dof {summary['chi2_per_dof']}", "",
             f"True clumps (source plane) and the fitted clumps whose β lies within "
             f"{MATCH_ARCSEC}\" (one per image):", "",
             "| true | β true | R_e true | mag true | fit | pixel | β fit | |μ| | R_e fit | "
             "mag_int fit | flag | source_id |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['true_id']} | {r['true_beta'][0]:.3f}, {r['true_beta'][1]:.3f} | "
            f"{r['true_re_arcsec']:.4f} | {r['true_mag_F200W']:.2f} | {r['fit_id']} | "
            f"{r['x_pix']:.0f}, {r['y_pix']:.0f} | {r['beta'][0]:.3f}±{r['beta_err'][0]:.3f}, "
            f"{r['beta'][1]:.3f}±{r['beta_err'][1]:.3f} | {r['magnification']:.2f} | "
            f"{r['re_arcsec']:.4f}±{r['re_arcsec_err']:.4f} | "
            f"{r['mag_int_F200W']:.2f}±{r['mag_int_F200W_err']:.2f} | {r['flag']} | "
            f"{r['source_id']} |")
    lines += group_lines(summary, rows)
    write_text("observed_lens.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
