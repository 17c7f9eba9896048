"""The optimiser of observation fits, measured (issue 17, item 4): this package's
one-Jacobian-per-step Levenberg–Marquardt (inference/lm.py) against optimistix's
Levenberg–Marquardt and BFGS, on the same mock fits from the same starts.

    .venv/bin/python benchmarks/bench_optimizers.py [--starts 3] [--solvers lm,optimistix-lm]

The mock is tests/test_observations.py's: two bands in MJy/sr (0.03″ and 0.06″ pixels, a WCS
rotated by 35°), a host and two clumps, Gaussian noise. Each start moves the clump starts by
~1.5 pixels in a random direction (seeded). Per solver: wall and CPU time of the first fit
(compile included) and of the later ones (compiled), steps, final χ², and how often it
reached the best χ² of all solvers for that start (within 0.01). jaxopt is not installed
(not a dependency: not measured). Results: benchmarks/results/optimizers.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--starts", type=int, default=3)
    ap.add_argument("--solvers", default="lm,optimistix-lm,optimistix-bfgs")
    args = ap.parse_args()
    import clumpylen_jax  # noqa: F401
    from test_observations import _mock_scene

    from clumpylen_jax.observations.config import load_observation_scene
    from clumpylen_jax.observations.fit import fit_observations
    from clumpylen_jax.observations.run import catalogue_starts, read_scene_data

    rng = np.random.default_rng(7)
    out = {"load_average_1min": os.getloadavg()[0], "solvers": {}}
    with tempfile.TemporaryDirectory() as tmp:
        scene_path, truth, frame, _ = _mock_scene(Path(tmp))
        scene = load_observation_scene(scene_path)
        obs, frame = read_scene_data(scene)
        base = catalogue_starts(scene.fit.clumps, frame)
        offsets = [rng.normal(0, 0.03, base["phi"].shape) for _ in range(args.starts)]
        chi2 = {}
        for solver in args.solvers.split(","):
            rows = []
            for k, off in enumerate(offsets):
                starts = {"phi": base["phi"] + off, "re_arcsec": base["re_arcsec"]}
                t0, c0 = time.perf_counter(), time.process_time()
                fit = fit_observations(obs, frame, scene.fit, starts, solver=solver)
                rows.append({"start": k, "wall_s": round(time.perf_counter() - t0, 2),
                             "cpu_s": round(time.process_time() - c0, 2),
                             "steps": [s["n_steps"] for s in fit.steps],
                             "chi2": fit.steps[-1]["chi2"], "success": fit.success})
                chi2.setdefault(k, {})[solver] = fit.steps[-1]["chi2"]
                print(solver, rows[-1], flush=True)
            out["solvers"][solver] = rows
    for solver, rows in out["solvers"].items():
        for r in rows:
            r["reached_best"] = bool(r["chi2"] <= min(chi2[r["start"]].values()) + 0.01)
    print(json.dumps(out, indent=1))
    res = ROOT / "benchmarks" / "results"
    res.mkdir(exist_ok=True)
    (res / "optimizers.json").write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
