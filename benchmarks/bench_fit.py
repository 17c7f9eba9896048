"""Benchmarks of the inference package; writes benchmarks/results/bench_fit.{json,md}.

1. cost of one log-likelihood + gradient vs one forward evaluation (target 2–4×);
2. MAP fit time (Levenberg–Marquardt, flux + centre + R_e free) vs number of clumps;
3. coverage of Fisher errors over noise realisations (fraction of |pull| < 1, < 2).

Run: .venv/bin/python benchmarks/bench_fit.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

import clumpylen_jax  # noqa: E402
clumpylen_jax.enable_float64()  # float64: the caller's choice
from clumpylen_jax.inference import fisher_uncertainty, fit_map, make_data, make_log_likelihood, make_state, parametrize
from clumpylen_jax.inference.mock import TOY_ACCURACY, toy_bands, toy_clumps, toy_model
from clumpylen_jax.model import Accuracy

FREE = {"clumps.flux": True, "clumps.center_arcsec": True, "clumps.re_arcsec": True}


def _time(f, *args, repeat=20):
    jax.block_until_ready(f(*args))
    t = time.perf_counter()
    for _ in range(repeat):
        jax.block_until_ready(f(*args))
    return (time.perf_counter() - t) / repeat


def grad_ratio(n_clumps, accuracy, label):
    src = toy_clumps(n_clumps, seed=1)
    model = toy_model(src, toy_bands(1, psf_sigma_pix=1.0), npix=41, accuracy=accuracy)
    noisy, _, var = eqx.filter_jit(model.observe)(src, jax.random.key(0))
    data = make_data(model, noisy, var)
    param = parametrize(make_state(src, 1), FREE)
    u = param.initial()
    fwd = jax.jit(lambda u: model.band_images(param.state(u).render_source())[0])
    vg = jax.jit(jax.value_and_grad(make_log_likelihood(model, data, param)))
    t_f, t_g = _time(fwd, u), _time(vg, u)
    return {"accuracy": label, "n_clumps": n_clumps, "n_params": int(param.size),
            "forward_ms": 1e3 * t_f, "loglike_grad_ms": 1e3 * t_g, "ratio": t_g / t_f}


def fit_time(n_clumps, npix=61):
    src = toy_clumps(n_clumps, seed=n_clumps, half_width_arcsec=0.75, min_separation_arcsec=0.15)
    model = toy_model(src, toy_bands(1), npix=npix)
    observe = eqx.filter_jit(model.observe)
    out = {"n_clumps": n_clumps, "n_params": 4 * n_clumps, "image": f"{npix}x{npix}"}
    for trial in range(2):  # first call includes compilation
        noisy, _, var = observe(src, jax.random.key(trial))
        data = make_data(model, noisy, var)
        param = parametrize(make_state(src, 1), FREE)
        u0 = param.initial() + 0.05 * jax.random.normal(jax.random.key(10 + trial), (param.size,))
        t = time.perf_counter()
        res = fit_map(model, data, param, u0)
        jax.block_until_ready(res.u)
        dt = time.perf_counter() - t
        out["first_s" if trial == 0 else "fit_s"] = dt
        out["steps"] = int(res.n_steps)
        out["success"] = bool(res.success)
    return out


def coverage(n_real=40):
    src = toy_clumps(3, seed=2, flux=(2.0, 5.0))
    model = toy_model(src, toy_bands(1))
    observe = eqx.filter_jit(model.observe)
    param = parametrize(make_state(src, 1), FREE)
    truth = np.asarray(param.physical_of_state())
    pulls = []
    for k in range(n_real):
        noisy, _, var = observe(src, jax.random.key(100 + k))
        data = make_data(model, noisy, var)
        # each realisation's fit starts away from the truth (5 % in the fit's coordinates)
        u0 = param.initial() + 0.05 * jax.random.normal(jax.random.key(1000 + k), (param.size,))
        res = fit_map(model, data, param, u0)
        err = np.asarray(fisher_uncertainty(model, param, res.x, data).err)
        pulls.append((np.asarray(res.x) - truth) / err)
    p = np.abs(np.array(pulls))
    return {"n_realisations": n_real, "n_params": int(param.size),
            "frac_within_1sigma": float(np.mean(p < 1)), "frac_within_2sigma": float(np.mean(p < 2)),
            "expected": [0.683, 0.954],
            "per_param_within_1sigma": dict(zip(param.labels, np.mean(p < 1, axis=0).round(3).tolist()))}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    res = {"platform": platform.platform(), "device": str(jax.devices()[0]), "jax": jax.__version__}
    res["grad_ratio"] = [grad_ratio(3, TOY_ACCURACY, "toy (exact_core=0, order 2)"),
                         grad_ratio(3, Accuracy(), "default")]
    ns = (5, 10) if args.quick else (5, 10, 20, 40)
    res["fit_time"] = [fit_time(n) for n in ns]
    res["coverage"] = coverage(10 if args.quick else 40)
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    (out / "bench_fit.json").write_text(json.dumps(res, indent=2))
    md = ["# bench_fit", "", f"{res['platform']}, {res['device']}, jax {res['jax']}", "",
          "## log-likelihood + gradient vs forward (41×41, PSF, 3 clumps, 12 free)", "",
          "| accuracy | forward ms | lnL+grad ms | ratio |", "|---|---|---|---|"]
    md += [f"| {r['accuracy']} | {r['forward_ms']:.2f} | {r['loglike_grad_ms']:.2f} | {r['ratio']:.2f} |"
           for r in res["grad_ratio"]]
    md += ["", "## MAP fit (LM) time vs clumps (flux, centre, R_e free)", "",
           "| clumps | params | image | first call s (compile) | fit s | steps |", "|---|---|---|---|---|---|"]
    md += [f"| {r['n_clumps']} | {r['n_params']} | {r['image']} | {r['first_s']:.1f} | {r['fit_s']:.2f} | {r['steps']} |"
           for r in res["fit_time"]]
    c = res["coverage"]
    md += ["", "## Coverage of Fisher errors", "",
           f"{c['n_realisations']} realisations, {c['n_params']} parameters: |pull| < 1 in "
           f"{c['frac_within_1sigma']:.3f} (expected 0.683), < 2 in {c['frac_within_2sigma']:.3f} (0.954)", ""]
    (out / "bench_fit.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
