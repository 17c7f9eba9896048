"""Cost of counting clumps without recompiling (inference/auto.py, capacity.py).

For a capacity of 10, 40 and 200 clump slots (an unlensed toy scene, one band, Gaussian
PSF): the compile time and the warm time per Levenberg–Marquardt step of

- the local fit of a counting step (host, background and LOCAL_SLOTS clumps free, the
  rest held: a fixed number of Jacobian columns whatever the capacity), and
- the joint fit of every slot (`capacity.solve_batch`; measured at 10 and 40, and at 200
  unless --quick; the final refit of `fit_without_truth` solves only the kept clumps'
  entries, as a local fit),

then a whole `fit_without_truth` run on a mock with 6 clumps, recording the XLA compiles
(jax.monitoring) of each counting step and of the final refit: every adding step after the
first reuses the compiled code (0 compiles), so compile time does not grow with the number
of steps; the final refit reuses it too (`capacity.solve_local_batch` takes any number of
rows moved, up to the capacity).

The fit's model draws its round n = 0.5 clumps as `fit_without_truth`'s callers build it
(`auto.fit_clump_pixels`: the exact separable renderer, "round_gaussian"); --clump-pixels
sersic measures the general Sérsic stamps instead. The mock images are always rendered with
the Sérsic stamps (their clumps are elliptical).

Run: .venv/bin/python benchmarks/bench_fit_auto.py [--quick] [--clump-pixels sersic]
Writes benchmarks/results/bench_fit_auto.{json,md} (with --clump-pixels sersic:
bench_fit_auto_sersic.{json,md}).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import clumpylen_jax

clumpylen_jax.enable_float64()  # float64: the caller's choice
from clumpylen_jax.inference import auto, capacity
from clumpylen_jax.inference.auto import AutoOptions, fit_without_truth
from clumpylen_jax.inference.mock import TOY_ACCURACY, toy_bands, toy_clumps
from clumpylen_jax.model import build_model
from clumpylen_jax.source import Sersic, Source

from _common import RESULTS, machine

ACC = dataclasses.replace(TOY_ACCURACY, psf_oversampling=3)
BANDS = toy_bands(1, psf_sigma_pix=1.0)
NPIX = 61
HALF = 0.5 * NPIX * 0.03
FIELD = ((-HALF, HALF), (-HALF, HALF))
HOST = Sersic(jnp.array([60.0]), jnp.asarray(0.3), jnp.asarray(1.0), jnp.asarray(0.7),
              jnp.asarray(0.4), jnp.zeros(2))

_COMPILES = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, secs, **kw: _COMPILES.append(secs) if event.endswith("backend_compile_duration")
    else None)


CLUMP_PIXELS = [auto.fit_clump_pixels(AutoOptions.clump_n, True, lensed=False)]  # --clump-pixels


def make_model(src):
    """The fit's model."""
    return build_model(src, BANDS, field_arcsec=FIELD,
                       accuracy=dataclasses.replace(ACC, clump_pixels=CLUMP_PIXELS[0]))


def mock(n_clumps, seed=0):
    cl = toy_clumps(n_clumps, seed=seed, half_width_arcsec=0.6, flux=(2.0, 6.0),
                    re_arcsec=(0.005, 0.03), min_separation_arcsec=0.15).clumps
    truth = Source(bulge=HOST, clumps=cl)
    model = build_model(truth, BANDS, field_arcsec=FIELD, accuracy=ACC)
    noisy, _, var = model.observe(truth, jax.random.key(seed))
    return [np.asarray(noisy[0])], [np.asarray(var[0])]


def _timed(f):
    t = time.perf_counter()
    out = jax.block_until_ready(f())
    return out, time.perf_counter() - t


def capacity_costs(cap, data, var, steps, joint=True):
    """Compile and per-step times of the local and joint LM fits at a capacity."""
    opts = AutoOptions(max_clumps=cap, n_starts=1).validate()
    ctx, u0 = auto._setup(make_model, data, var, None, None, None, opts)
    active = np.zeros((1, cap))
    active[0, :3] = 1.0
    idx, rows = auto._solve_layout(ctx, list(range(auto.LOCAL_SLOTS)))
    row = {"capacity": cap, "free_local": int(np.sum(idx < ctx.param.size)),
           "free_joint": int(ctx.param.size)}

    def local(max_steps):
        return capacity.solve_local_batch(ctx.model, ctx.data, ctx.param, jnp.asarray(u0[None]),
                                          jnp.asarray(idx[None]), jnp.asarray(rows[None]),
                                          jnp.asarray(active), 0.0, max_steps,
                                          int(ctx.host_index.size), auto.LOCAL_SLOTS)

    def joint_fit(max_steps):
        return capacity.solve_batch(ctx.model, ctx.data, ctx.param, jnp.asarray(u0[None]),
                                    jnp.asarray(active), 0.0, max_steps)

    fits = [("local", local)] + ([("joint", joint_fit)] if joint else [])
    for name, f in fits:
        n0 = len(_COMPILES)
        _, cold = _timed(lambda: f(steps))
        compile_s = float(sum(_COMPILES[n0:]))
        out, warm = _timed(lambda: f(steps))
        n_steps = int(np.asarray(out[3])[0])
        row[f"{name}_compile_s"] = compile_s
        row[f"{name}_cold_s"] = cold
        row[f"{name}_s_per_step"] = warm / max(n_steps, 1)
        print(f"capacity {cap:4d} {name}: compile {compile_s:.1f} s, {warm / max(n_steps, 1):.3f} s "
              f"per LM step ({n_steps} steps)", flush=True)
    return row


def counting_compiles(n_clumps=6, cap=10):
    """Compiles and wall time per step of a whole run (compiles counted per step)."""
    data, var = mock(n_clumps, seed=3)
    marks = []
    orig = auto._fit_local

    def spy(*a, **k):
        n0, t0 = len(_COMPILES), time.perf_counter()
        out = orig(*a, **k)
        marks.append({"compiles": len(_COMPILES) - n0, "compile_s": float(sum(_COMPILES[n0:])),
                      "wall_s": time.perf_counter() - t0})
        return out

    auto._fit_local = spy
    try:
        fit = fit_without_truth(make_model, data, var, options=AutoOptions(max_clumps=cap, n_starts=4))
    finally:
        auto._fit_local = orig
    for m, s in zip(marks, [s for s in fit.steps if s["action"] in ("host", "add", "reject", "final")]):
        m["action"] = s["action"]
        m["n_clumps"] = s["n_clumps"]
    return {"true_clumps": n_clumps, "found": len(fit.table), "steps": marks}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="no joint fit at capacity 200")
    ap.add_argument("--clump-pixels", choices=["sersic", "round_gaussian"], default=CLUMP_PIXELS[0])
    args = ap.parse_args()
    CLUMP_PIXELS[0] = args.clump_pixels
    stem = "bench_fit_auto" + ("" if args.clump_pixels == "round_gaussian" else "_" + args.clump_pixels)
    data, var = mock(8)
    rows = []
    for cap in (10, 40, 200):
        rows.append(capacity_costs(cap, data, var, steps=5, joint=cap <= 40 or not args.quick))
    count = counting_compiles()
    res = {"machine": machine(), "capacities": rows, "counting": count,
           "clump_pixels": args.clump_pixels, "load_average": list(os.getloadavg()),
           "scene": f"unlensed, {NPIX}x{NPIX} px of 0.03\", Gaussian PSF sigma 1 px, "
                    f"psf_oversampling 3, host + clumps (clump_pixels {args.clump_pixels})"}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(res, indent=2))
    lines = ["# bench_fit_auto: counting clumps without recompiling", "",
             f"{res['scene']}; {res['machine']['date']}, {res['machine']['cpu_count']} CPUs, "
             f"load average {' / '.join(f'{v:.1f}' for v in res['load_average'])}", "",
             "| capacity | free (local) | free (joint) | local compile s | local s/step | "
             "joint compile s | joint s/step |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['capacity']} | {r['free_local']} | {r['free_joint']} | "
                     f"{r['local_compile_s']:.1f} | {r['local_s_per_step']:.3f} | "
                     f"{r.get('joint_compile_s', float('nan')):.1f} | "
                     f"{r.get('joint_s_per_step', float('nan')):.3f} |")
    lines += ["", f"Counting run ({count['true_clumps']} true clumps, capacity 10, 4 starts; "
              f"{count['found']} found): XLA compiles per step", "",
              "| step | action | clumps | compiles | compile s | wall s |", "|---|---|---|---|---|---|"]
    for i, m in enumerate(count["steps"]):
        lines.append(f"| {i} | {m.get('action', '')} | {m.get('n_clumps', '')} | {m['compiles']} | "
                     f"{m['compile_s']:.1f} | {m['wall_s']:.1f} |")
    (RESULTS / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
