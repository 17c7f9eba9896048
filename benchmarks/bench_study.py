"""Studies on Dask: throughput, compile vs steady state, memory, completeness cost scaling.

    .venv/bin/python benchmarks/bench_study.py [--quick]

For each kind of task (simulate, completeness injections, Fisher maps, fit) on a tiny
unlensed scene (one NIRCam band, 52² pixels), on a LocalCluster of 1 and 2 worker
processes: wall time of the whole batch, tasks per hour, each task's own time (the first
task of a worker includes compilation), and the workers' peak memory. Then the steady
cost of one injection and of one Fisher-map position against positions per task and map
size, and, on paper, a 10⁶-sample training set and the 476-galaxy completeness study.
Writes benchmarks/results/study.{md,json}. Short on purpose: the host is shared.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import clumpylen_jax

clumpylen_jax.enable_float64()  # float64: the caller's choice

ROOT = Path(__file__).resolve().parent
RESULTS = ROOT / "results"

SCENE = """
[scene]
name = "bench-tiny"
seed = 1
z_source = 2.0
[source]
center_arcsec = [0.0, 0.0]
[source.bulge]
magnitudes = { F200W = 25.0 }
re_arcsec = 0.2
n = 1.0
q = 0.7
pa_rad = 0.5
[render]
field_arcsec = { x = [-0.8, 0.8], y = [-0.8, 0.8] }
accuracy = "fast"
[[bands]]
instrument = "JWST/NIRCam"
filter = "F200W"
exptime_s = 1000.0
sky_counts_per_s = 0.16
psf = "none"
"""

STUDIES = {
    "simulate": """[study]\nkind = "simulate"\nseed = 1\nscenes = ["scene.toml"]
[clumps]\nmass_msun = {{ min = 1e5, max = 1e7 }}\nre_pc = {{ min = 10.0, max = 80.0 }}\nregion_arcsec = 0.4
[simulate]\nsamples = {n}\nclumps_per_sample = [1, 16]\nbuckets = [16]\n""",
    "completeness": """[study]\nkind = "completeness"\nseed = 1\nscenes = ["scene.toml"]
[clumps]\nmass_msun = {{ min = 1e5, max = 3e7, num = {n} }}\nre_pc = [20.0]\nregion_arcsec = 0.4
[completeness]\npositions = {pos}\npositions_per_task = {pos}\nmap_npix = {m}\nnpixels = 1\n""",
    "fit": """[study]\nkind = "fit"\nseed = 1\nscenes = ["scene.toml"]
[clumps]\nmass_msun = {{ min = 3e6, max = 3e7 }}\nre_pc = {{ min = 40.0, max = 80.0 }}\nregion_arcsec = 0.3
[fit]\nsamples = {n}\nclumps_per_sample = 2\n""",
}


def timed_task(study, task):
    """Run one task on a worker: (task id, seconds, kind, worker pid, peak RSS MiB)."""
    from clumpylen_jax.study.work import run_task

    t0 = time.perf_counter()
    run_task(study, task)
    dt = time.perf_counter() - t0
    return task.id, dt, task.kind, os.getpid(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_batch(study, n_workers: int, cache: str) -> dict:
    from distributed import Client, LocalCluster

    from clumpylen_jax.study.runner import _plugin
    from clumpylen_jax.study.tasks import make_tasks

    tasks = make_tasks(study)
    os.environ["CLUMPYLEN_CACHE"] = cache
    with LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        client.register_plugin(_plugin(os.path.join(cache, "jax")))
        client.run(lambda: __import__("clumpylen_jax"))        # imports outside the timing
        t0 = time.perf_counter()
        out = client.gather([client.submit(timed_task, study, t, pure=False) for t in tasks])
        wall = time.perf_counter() - t0
    # the first task of each (worker, kind of task) compiles its program; the rest are steady
    groups: dict = {}
    for tid, dt, kind, pid, rss in out:
        groups.setdefault((pid, kind), []).append(dt)
    first = [v[0] for v in groups.values()]
    steady = [dt for v in groups.values() for dt in v[1:]]
    by_kind = {}
    for (pid, kind), v in groups.items():
        by_kind.setdefault(kind, []).extend(v[1:])
    return {"workers": n_workers, "tasks": len(tasks), "wall_s": wall,
            "tasks_per_hour": 3600 * len(tasks) / wall,
            "first_task_s": float(np.mean(first)),
            "steady_task_s": float(np.median(steady)) if steady else float("nan"),
            "steady_tasks_per_hour": 3600 * n_workers / np.median(steady) if steady else float("nan"),
            "peak_rss_mib_per_worker": float(max(r for *_, r in out)),
            "steady_s_by_kind": {k: float(np.median(v)) for k, v in by_kind.items() if v},
            "raw": [(tid, round(dt, 4), kind, pid) for tid, dt, kind, pid, _ in out]}


def steady_costs(tmp: Path, shapes=((8, 8), (16, 12))) -> dict:
    """Per-task steady time in this process (after one warm-up call of each shape):
    (positions per injection task, Fisher map side) pairs."""
    from clumpylen_jax.study import study_from_dict
    from clumpylen_jax.study.tasks import make_tasks
    from clumpylen_jax.study.work import run_task
    import tomllib

    rows = []
    for pos, m in shapes:
        text = STUDIES["completeness"].format(n=3, pos=pos, m=m)
        study = study_from_dict(tomllib.loads(text), str(tmp), text)
        tasks = make_tasks(study)
        res = {}
        for kind in ("inject", "map"):
            ts = [t for t in tasks if t.kind == kind]
            t0 = time.perf_counter()
            run_task(study, ts[0])
            compile_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            for t in ts[1:]:
                run_task(study, t)
            res[kind] = (compile_s, (time.perf_counter() - t0) / (len(ts) - 1))
        rows.append({"positions": pos, "map_npix": m,
                     "inject_first_s": res["inject"][0], "inject_steady_s": res["inject"][1],
                     "inject_s_per_position": res["inject"][1] / pos,
                     "map_first_s": res["map"][0], "map_steady_s": res["map"][1],
                     "map_s_per_position": res["map"][1] / (m * m + pos)})
    return {"rows": rows}


def on_paper(batches, costs) -> dict:
    """Extrapolations from the measured steady rates (stated assumptions, not measurements)."""
    sim = [b for b in batches if b["kind"] == "simulate" and b["workers"] == 1][0]
    t_sample = sim["steady_task_s"]
    inj = np.median([r["inject_s_per_position"] for r in costs["rows"]])
    fis = np.median([r["map_s_per_position"] for r in costs["rows"]])
    # a real arc: ~200 × 200 detector pixels per band (vs 52² here: ×15 in pixels), 3 bands,
    # a 10 × 8 (mass, size) grid, 100 positions per cell, a 32² Fisher map per cell
    px = (200 * 200) / (52 * 52)
    per_galaxy = 80 * 3 * (100 * inj + (32 * 32 + 100) * fis) * px
    return {
        "training_set_1e6_samples_cpu_hours": 1e6 * t_sample / 3600,
        "training_set_assumption": "this scene (52² px, 1 band, ≤ 16 clumps); 1 worker = 1 core",
        "completeness_476_galaxies_cpu_hours": 476 * per_galaxy / 3600,
        "completeness_assumption": "200² px × 3 bands per arc (pixels ×15 of the bench scene, cost "
                                   "taken ∝ pixels), 10 × 8 (mass, size) grid, 100 positions and a "
                                   "32² Fisher map per cell; unlensed cost (lensed arcs cost more)",
        "per_galaxy_cpu_hours": per_galaxy / 3600,
    }


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer tasks")
    args = ap.parse_args(argv)
    from clumpylen_jax.study import study_from_dict
    import tomllib

    n = 6 if args.quick else 12
    tmp = Path(tempfile.mkdtemp(prefix="bench-study-"))
    (tmp / "scene.toml").write_text(SCENE)
    cache = str(tmp / "cache")
    batches = []
    for kind in ("simulate", "completeness", "fit"):
        text = STUDIES[kind].format(n=n if kind != "completeness" else max(n // 2, 3), pos=8, m=8)
        study = study_from_dict(tomllib.loads(text), str(tmp), text)
        for w in (1, 2):
            t0 = time.perf_counter()
            b = run_batch(study, w, cache)
            b["kind"] = kind
            batches.append(b)
            print(f"{kind:12s} {w} worker(s): {b['tasks']} tasks in {b['wall_s']:.1f} s "
                  f"({b['tasks_per_hour']:.0f}/h), first {b['first_task_s']:.2f} s, steady "
                  f"{b['steady_task_s']:.3f} s, {b['peak_rss_mib_per_worker']:.0f} MiB "
                  f"[{time.perf_counter() - t0:.0f} s]", flush=True)
    costs = steady_costs(tmp)
    for r in costs["rows"]:
        print(r, flush=True)
    paper = on_paper(batches, costs)
    print(paper)
    load = os.getloadavg()
    report = {"host": {"cpus": os.cpu_count(), "load_avg": load,
                       "note": "shared 2-core machine, 6 other sessions running: wall times are "
                               "inflated and noisy"},
              "batches": batches, "completeness_scaling": costs, "on_paper": paper}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "study.json").write_text(json.dumps(report, indent=1, default=float))
    (RESULTS / "study.md").write_text(_markdown(report))
    print(f"wrote {RESULTS / 'study.md'}")


def _markdown(r) -> str:
    lines = ["# Studies on Dask (`benchmarks/bench_study.py`)", "",
             f"Host: {r['host']['cpus']} CPUs, load average {r['host']['load_avg'][0]:.1f} "
             f"during the run ({r['host']['note']}).", "",
             "Tiny unlensed scene (one NIRCam band, 52² px, no PSF, `fast` accuracy). "
             "First task = the first of each kind on each worker (includes compilation; the "
             "compilation cache starts empty for the 1-worker run, the 2-worker run finds it "
             "filled); steady = median of the others. Tasks: simulate = one "
             "sample (≤ 16 clumps), completeness = 8 injections + detection per task and one "
             "Fisher map (8² + 8 positions, vmapped) per cell; fit = one MAP fit of 2 clumps "
             "from a start off the truth.", "",
             "| kind | workers | tasks | wall s | tasks/h | first task s | steady task s | steady tasks/h | peak RSS MiB/worker |",
             "|---|---|---|---|---|---|---|---|---|"]
    for b in r["batches"]:
        lines.append(f"| {b['kind']} | {b['workers']} | {b['tasks']} | {b['wall_s']:.1f} | "
                     f"{b['tasks_per_hour']:.0f} | {b['first_task_s']:.2f} | {b['steady_task_s']:.3f} | "
                     f"{b['steady_tasks_per_hour']:.0f} | {b['peak_rss_mib_per_worker']:.0f} |")
    lines += ["", "## Completeness cost against positions per task and Fisher-map size (one process)", "",
              "| positions | map npix | inject first s | inject steady s | s / injection | map first s | map steady s | s / map position |",
              "|---|---|---|---|---|---|---|---|"]
    for x in r["completeness_scaling"]["rows"]:
        lines.append(f"| {x['positions']} | {x['map_npix']} | {x['inject_first_s']:.2f} | "
                     f"{x['inject_steady_s']:.3f} | {x['inject_s_per_position']:.4f} | "
                     f"{x['map_first_s']:.2f} | {x['map_steady_s']:.3f} | {x['map_s_per_position']:.4f} |")
    p = r["on_paper"]
    lines += ["", "## On paper (extrapolated from the steady rates above)", "",
              f"- 10⁶-sample training set: {p['training_set_1e6_samples_cpu_hours']:.0f} worker-hours "
              f"({p['training_set_assumption']}): on N workers, that divided by N "
              f"(e.g. {p['training_set_1e6_samples_cpu_hours'] / 64:.1f} h on 64).",
              f"- 476-galaxy completeness study: {p['completeness_476_galaxies_cpu_hours']:.0f} "
              f"worker-hours ({p['per_galaxy_cpu_hours']:.2f} per galaxy; "
              f"{p['completeness_assumption']}): on 64 workers "
              f"{p['completeness_476_galaxies_cpu_hours'] / 64:.1f} h.",
              "- Compilation is paid once per program and worker, then loaded from the shared "
              "cache; with a handful of programs per study it is negligible at these scales.", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
