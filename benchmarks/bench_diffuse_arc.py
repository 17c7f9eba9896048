"""`clumpylen fit` of a mock arc with and without the diffuse light (issue 17).

The arc (`tests/test_diffuse.py::_arc_cutout`: a ring segment, Gaussian across (σ 0.12″) and
along it, which no Sérsic draws, three Gaussian clumps of R_e 0.024″ on it, PSF FWHM 0.09″,
64² pixels of 0.03″, Gaussian noise) is fitted from the image alone (`clumps = "auto"`,
n = 0.5 as the truth's clumps) three ways: a Sérsic host (the default), the diffuse light
without a host at nodes 0.18″ and 0.27″ apart. Reported per run: wall time of the command,
χ²/dof, clumps found, false ones (no true clump within 1.5 pixels), and the flux pulls of
the true clumps found.

    .venv/bin/python benchmarks/bench_diffuse_arc.py

Writes benchmarks/results/diffuse_arc.{json,md}.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from astropy.table import Table

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))
from _common import machine, write_json, write_text  # noqa: E402
from test_diffuse import _arc_cutout  # noqa: E402
from test_observations import _scene  # noqa: E402

RUNS = {"sersic host": 'host = "sersic"\n',
        "diffuse 0.18\"": 'host = "none"\ndiffuse_spacing_arcsec = 0.18\n',
        "diffuse 0.27\"": 'host = "none"\ndiffuse_spacing_arcsec = 0.27\n'}
MATCH_PIX = 1.5


def run(tmp: Path, name: str, fit_keys: str) -> dict:
    work = tmp / name.replace(" ", "_").replace('"', "")
    work.mkdir()
    image, psf, truth_pix, truth_flux = _arc_cutout(work)
    scene = _scene(work, [{"filter": "F150W", "image": image, "psf": psf}],
                   fit='clumps = "auto"\nmax_clumps = 8\nclump_n = 0.5\n' + fit_keys)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "clumpylen_jax.cli", "fit", scene, "--out",
                           str(work / "out")], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode:
        raise SystemExit(proc.stderr)
    summary = json.loads((work / "out" / "summary.json").read_text())
    t = Table.read(work / "out" / "fit.ecsv")
    found = np.c_[t["x_pix"], t["y_pix"]] if len(t) else np.zeros((0, 2))
    d = np.hypot(*(found[:, None] - truth_pix[None]).transpose(2, 0, 1)) if len(t) else \
        np.full((0, len(truth_pix)), np.inf)
    matched = [int(np.argmin(d[:, j])) if len(t) and d[:, j].min() < MATCH_PIX else None
               for j in range(len(truth_pix))]
    pulls = [None if i is None else float((t["flux_F150W"][i] - f) / t["flux_F150W_err"][i])
             for i, f in zip(matched, truth_flux)]
    false = int(sum(1 for i in range(len(t)) if i not in matched))
    return {"wall_s": round(wall, 1), "chi2_per_dof": summary["chi2_per_dof"]["F150W"],
            "found": len(t), "recovered": sum(i is not None for i in matched), "false": false,
            "flux_pulls": pulls, "load_1min": round(__import__("os").getloadavg()[0], 2)}


def main():
    out = {"machine": machine(), "runs": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for name, keys in RUNS.items():
            out["runs"][name] = run(Path(tmp), name, keys)
            print(name, out["runs"][name], flush=True)
    write_json("diffuse_arc", out)
    lines = ["# A mock arc fitted with and without the diffuse light (bench_diffuse_arc.py)", "",
             f"{out['machine']['date']}, {out['machine']['cpu_count']} CPUs, jax "
             f"{out['machine']['jax']}; load: 1-min load average when the fit ended (shared host). "
             f"Recovered: a true clump with a fitted one within {MATCH_PIX} pixels; false: a fitted "
             "clump with no true one there; pull: (fitted − true flux) / fitted σ.", "",
             "| fit | wall s | load | χ²/dof | found | recovered / 3 | false | flux pulls |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in out["runs"].items():
        pulls = ", ".join("–" if p is None else f"{p:+.1f}" for p in r["flux_pulls"])
        lines.append(f"| {name} | {r['wall_s']} | {r['load_1min']} | {r['chi2_per_dof']:.3f} | "
                     f"{r['found']} | {r['recovered']} | {r['false']} | {pulls} |")
    write_text("diffuse_arc.md", "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
