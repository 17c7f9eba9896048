"""Run every benchmark of issue 7 and write their results under benchmarks/results/.

Usage: ``python benchmarks/run_all.py [--quick] [--only accuracy,lenstronomy,scene,scaling,paper_lens,simulate_cli]``.
Each script also runs on its own (see benchmarks/README.md). bench_fit.py (likelihood +
gradient cost) belongs to the inference benchmarks and runs separately.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
# each job: a script and the argument lists of its processes (lenstronomy's large counts
# in their own processes: XLA's CPU JIT can run out of code memory after many models)
JOBS = {
    "accuracy": ("bench_accuracy.py", [[]]),
    "lenstronomy": ("bench_lenstronomy.py", [["--counts", "10,30,100"],
                                             ["--counts", "300", "--append"],
                                             ["--counts", "1000", "--append"]]),
    "scene": ("bench_scene.py", [[]]),
    "scaling": ("bench_scaling.py", [[]]),
    "paper_lens": ("bench_paper_lens.py", [[]]),
    "simulate_cli": ("bench_simulate_cli.py", [["--check"]]),
}
QUICK = {"accuracy": [["--quick"]], "lenstronomy": [["--quick"]],
         "scene": [["--settings", "as-is"]], "scaling": [["--quick"]], "paper_lens": [[]],
         "simulate_cli": [[]]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--only", default=",".join(JOBS))
    args = ap.parse_args(argv)
    status = 0
    for name in args.only.split(","):
        script, runs = JOBS[name]
        for extra in QUICK[name] if args.quick else runs:
            cmd = [sys.executable, str(HERE / script)] + extra
            t = time.perf_counter()
            print(f"== {name}: {' '.join(cmd[1:])}", flush=True)
            rc = subprocess.call(cmd)   # one process per run: separate peak RSS and caches
            print(f"== {name}: exit {rc} in {time.perf_counter() - t:.0f}s", flush=True)
            status = status or rc
    return status


if __name__ == "__main__":
    sys.exit(main())
