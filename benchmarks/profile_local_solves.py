"""CPU seconds and LM steps of each `capacity.solve_local_batch` call of the S1063 fit (the
auto stage's counting steps, then its final refit), for the clumpylen_jax under ROOT:

    .venv/bin/python benchmarks/profile_local_solves.py ROOT > OUT.json

Run two checkouts at the same time (each sees the same load) to compare codes per call.
"""

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, sys.argv[1])
import clumpylen_jax  # noqa: E402

clumpylen_jax.enable_float64()
from clumpylen_jax.inference import capacity  # noqa: E402
from clumpylen_jax.observations.run import fit_observation_scene  # noqa: E402

SCENE = Path(__file__).resolve().parent / "real" / "s1063_sys4_im1.toml"
calls = []
solve = capacity.solve_local_batch


def timed(*a, **k):
    c0, t0 = time.process_time(), time.perf_counter()
    out = solve(*a, **k)
    calls.append(dict(cpu=time.process_time() - c0, wall=time.perf_counter() - t0,
                      steps=np.asarray(out[3]).tolist(), active=int(np.asarray(a[6])[0].sum())))
    return out


capacity.solve_local_batch = timed
c0 = time.process_time()
fit_observation_scene(str(SCENE), None)
print(json.dumps(dict(total_cpu=time.process_time() - c0, calls=calls)))
