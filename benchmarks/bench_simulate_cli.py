"""The whole `clumpylen simulate` command as a user times it (issue 20), cold and warm.

Per repeat, back to back: a **cold** process (fresh `clumpylen simulate SCENE --out DIR`
with `CLUMPYLEN_CACHE` pointing at an empty folder: no compiled programs, PSFs or traced
rays), then a **warm** process (the same command again, same cache folder), then, with
--check, a process with the cache off (`--no-cache`). Each is timed from outside (wall
clock of the process, and its CPU seconds), and its summary.json gives each stage's
compile / run split. Every output the scene writes is included (nothing is switched off).

Bit-for-bit check: the SHA-256 of the data of every FITS HDU (header cards aside: they
hold no timing) of every run must agree — cold, warm and cache-off; with --reference DIR
also against an earlier run's output folder (e.g. the code before a change).

Targets (issue 20, 2 cores): cold < 30 s, warm < 10 s.

Run: ``python benchmarks/bench_simulate_cli.py [--scene cosmic-archipelago] [--repeats 2]
[--check] [--reference DIR]``. Writes benchmarks/results/simulate_cli.{json,md}.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C  # noqa: E402

CLI = Path(sys.executable).with_name("clumpylen")
TARGETS = {"cold": 30.0, "warm": 10.0}


def fits_hashes(folder: Path) -> dict:
    """{relative path[HDU]: SHA-256 of its data} of every FITS file under folder."""
    from astropy.io import fits

    out = {}
    for path in sorted(folder.rglob("*.fits")):
        with fits.open(path) as hdul:
            for k, hdu in enumerate(hdul):
                if hdu.data is not None:
                    name = hdu.name or str(k)
                    out[f"{path.relative_to(folder)}[{name}]"] = hashlib.sha256(
                        hdu.data.tobytes()).hexdigest()
    return out


def run_cli(scene, out: Path, cache: Path, extra=(), code: Path | None = None):
    """Run the command once; (wall s, CPU s of the child, summary dict, exit status).
    code: another checkout's root whose clumpylen_jax runs instead (first on PYTHONPATH)."""
    env = dict(os.environ, CLUMPYLEN_CACHE=str(cache))
    env.pop("CLUMPYLEN_NO_CACHE", None)
    cmd, cwd = [str(CLI)], None
    if code is not None:      # run from its root: `python -c` puts the cwd first on sys.path
        env["PYTHONPATH"] = str(code)
        cwd = str(code)
        cmd = [sys.executable, "-c", "import sys; from clumpylen_jax.cli import main; "
               "sys.exit(main(sys.argv[1:]))"]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run([*cmd, "simulate", scene, "--out", str(out), *extra], env=env,
                          capture_output=True, text=True, cwd=cwd)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout + proc.stderr)
        return wall, cpu, None, proc.returncode
    summary = json.loads((out / "summary.json").read_text())
    return wall, cpu, summary, 0, proc.stdout


def row_of(kind, repeat, wall, cpu, summary):
    split = summary["timings_split_s"]
    return dict(run=kind, repeat=repeat, wall_s=wall, cpu_s=cpu,
                compile_s=sum(v["compile"] for v in split.values()),
                run_s=sum(v["run"] for v in split.values()),
                in_process_s=summary["timings_s"]["total"], stages=split)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="cosmic-archipelago")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--check", action="store_true",
                    help="also run with --no-cache and compare the images bit for bit")
    ap.add_argument("--reference", type=Path, help="an earlier run's output folder to compare with")
    ap.add_argument("--keep", type=Path, help="keep the output folders here")
    ap.add_argument("--baseline", type=Path,
                    help="root of another checkout (e.g. `git archive` of the code before a "
                         "change): its cold and warm runs are timed in the same repeat, "
                         "interleaved with this code's (back to back on the same load)")
    ap.add_argument("--results", default="simulate_cli",
                    help="name of the result files under benchmarks/results/")
    args = ap.parse_args(argv)

    work = Path(tempfile.mkdtemp(prefix="bench_simulate_cli_"))
    rows, hashes, tails, base_hashes = [], {}, {}, {}
    try:
        for rep in range(args.repeats):
            cache = work / f"cache{rep}"
            cache.mkdir()
            kinds = ["cold", "warm"] + (["no-cache"] if args.check and rep == 0 else [])
            if args.baseline is not None:
                (work / f"base-cache{rep}").mkdir()
                kinds = ["base-cold", "cold", "base-warm", "warm"] + kinds[2:]
            for kind in kinds:
                out = work / f"{kind}{rep}"
                base = kind.startswith("base-")
                res = run_cli(args.scene, out, work / f"base-cache{rep}" if base else cache,
                              ["--no-cache"] if kind == "no-cache" else [],
                              code=args.baseline if base else None)
                if res[2] is None:
                    raise SystemExit(f"{kind} run failed with status {res[3]}")
                wall, cpu, summary, _, stdout = res
                rows.append(row_of(kind, rep, wall, cpu, summary))
                (base_hashes if base else hashes)[f"{kind}{rep}"] = fits_hashes(out)
                tails[kind] = stdout.strip().splitlines()[-3:]
                print(f"{kind} #{rep}: {wall:.1f} s wall, {cpu:.1f} s CPU, compile "
                      f"{rows[-1]['compile_s']:.1f} s + run {rows[-1]['run_s']:.1f} s", flush=True)
        cache_bytes = sum(p.stat().st_size for p in (work / "cache0").rglob("*") if p.is_file())
        if args.keep:
            args.keep.mkdir(parents=True, exist_ok=True)
            for p in work.iterdir():
                if p.name.startswith(("cold", "warm", "no-cache", "base-")):
                    shutil.copytree(p, args.keep / p.name, dirs_exist_ok=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    first = next(iter(hashes.values()))
    identical = {k: v == first for k, v in hashes.items()}
    ref = None
    if args.reference is not None:
        ref_h = fits_hashes(args.reference)
        ref = {"folder": str(args.reference),
               "all_hdus_identical": ref_h == first,
               "noiseless_identical": all(ref_h.get(k) == v for k, v in first.items()
                                          if "NOISELESS" in k or "UNLENSED" in k
                                          or k.startswith("hr/")),
               "differing": sorted(k for k in first if ref_h.get(k) != first[k])}
    med = {}
    for kind in ("cold", "warm") + (("base-cold", "base-warm") if args.baseline else ()):
        walls = sorted(r["wall_s"] for r in rows if r["run"] == kind)
        med[kind] = walls[len(walls) // 2]
    baseline = None
    if args.baseline is not None:
        bh = next(iter(base_hashes.values()))
        baseline = {"code": str(args.baseline),
                    "cold_speedup": med["base-cold"] / med["cold"],
                    "warm_speedup": med["base-warm"] / med["warm"],
                    "identical_between_its_runs": all(v == bh for v in base_hashes.values()),
                    "differing_hdus": sorted(k for k in first if bh.get(k) != first[k])}
    payload = dict(machine=C.machine(), scene=args.scene, rows=rows,
                   median_wall_s=med, warm_over_cold=med["warm"] / med["cold"],
                   targets_s=TARGETS, met={k: med[k] < TARGETS[k] for k in TARGETS},
                   images_identical_between_runs=identical, reference=ref,
                   cache_bytes=cache_bytes, fits_hdus=len(first), demo_tail=tails,
                   baseline=baseline, load_average=os.getloadavg())
    C.write_json(args.results, payload)
    C.write_text(f"{args.results}.md", markdown(payload))
    print(markdown(payload))


def markdown(p):
    cols = [("run", "run"), ("repeat", "#"), ("wall_s", "wall s"), ("cpu_s", "CPU s"),
            ("compile_s", "compile s"), ("run_s", "run s"), ("in_process_s", "in-process s")]
    lines = [f"# `clumpylen simulate {p['scene']}` as a process (issue 20)", "",
             f"{p['machine']['date']}, {p['machine']['cpu_count']} CPUs, jax "
             f"{p['machine']['jax']}. cold: empty cache folder; warm: the second process; "
             "compile = JAX tracing + lowering + XLA compilation or cache load, from "
             "summary.json, summed over the stages of every thread (the programs after the "
             "band render load and run in a background thread: compile + run can exceed "
             "the wall time).", "", C.markdown_table(p["rows"], cols), "",
             f"Median wall: cold {p['median_wall_s']['cold']:.1f} s (target < 30 s: "
             f"{'met' if p['met']['cold'] else 'NOT met'}), warm "
             f"{p['median_wall_s']['warm']:.1f} s (target < 10 s: "
             f"{'met' if p['met']['warm'] else 'NOT met'}); warm / cold = "
             f"{p['warm_over_cold']:.2f}. Cache after one run: {p['cache_bytes'] / 2**20:.1f} MiB.",
             "", f"FITS data identical across runs ({p['fits_hdus']} HDUs): "
             + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in
                         p["images_identical_between_runs"].items())]
    if p.get("baseline"):
        b = p["baseline"]
        lines += ["", f"Baseline code {b['code']}, timed in the same run: cold "
                  f"{p['median_wall_s']['base-cold']:.1f} s → {p['median_wall_s']['cold']:.1f} s "
                  f"({b['cold_speedup']:.2f}×), warm {p['median_wall_s']['base-warm']:.1f} s → "
                  f"{p['median_wall_s']['warm']:.1f} s ({b['warm_speedup']:.2f}×). HDUs that "
                  f"differ from the baseline's: {', '.join(b['differing_hdus']) or 'none'}"]
    if p.get("load_average"):
        lines += ["", "Load average at the end (1, 5, 15 min; 2 cores shared): "
                  + ", ".join(f"{x:.1f}" for x in p["load_average"])]
    if p["reference"]:
        r = p["reference"]
        lines += ["", f"Against {r['folder']}: all HDUs identical: {r['all_hdus_identical']}; "
                  f"noiseless, unlensed and high-resolution identical: {r['noiseless_identical']}"
                  + (f"; differing: {', '.join(r['differing'])}" if r["differing"] else "")]
    lines += ["", "Per stage (first repeat), total / compile / run s:", "",
              "| stage | " + " | ".join(r["run"] for r in p["rows"] if r["repeat"] == 0) + " |",
              "|---|" + "---|" * sum(1 for r in p["rows"] if r["repeat"] == 0)]
    first = [r for r in p["rows"] if r["repeat"] == 0]
    names = list(dict.fromkeys(name for r in first for name in r["stages"]))   # every run's
    for stage in names:
        cells = []
        for r in first:
            v = r["stages"].get(stage)
            cells.append("–" if v is None else
                         f"{v['total']:.2f} / {v['compile']:.2f} / {v['run']:.2f}")
        lines.append(f"| {stage} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
