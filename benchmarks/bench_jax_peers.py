"""Speed against the JAX-ecosystem peers, caustics and JAXtronomy, at matched accuracy (issue 20).

The scene of bench_lenstronomy.py (imported from it, not copied): 0.03" pixels on
a 90 × 90 field, the 21 × 21 Moffat PSF at detector sampling, N Sérsic clumps
(n = 0.5 / 1, R_e 0.5–3 mas, q 0.3–1) within 0.08" of (0.25, 0.05) behind an
SIS with θ_E = 1". Two lenses:

- "map": the SIS rasterised on a 0.01" grid, bilinear. This project:
  `DeflectionGrid`; caustics: `caustics.lenses.PixelatedDeflection` (bilinear,
  `caustics.utils.interp2d`; its map is (2, ny, nx) with pixel centres at
  x0 + (i + ½ − n/2)·pixelscale, so the 401-point map centred on 0 lands on the
  same nodes). JAXtronomy has no interpolated deflection lens ("INTERPOL" is in
  its `LensModel.profile_list_base._SUPPORTED_MODELS` but raises "not in
  JAXtronomy; use lenstronomy instead"), so it is absent from this scene.
- "sis": the analytic SIS, in all three codes (this project: `lensing.SIS`;
  caustics: `caustics.lenses.SIS`; JAXtronomy: "SIS").
The same-rays checks run every peer on both scenes where it can; the error sweep
and the timing run caustics on "map" (its pixelated-deflection lens, the
scene of bench_lenstronomy) and JAXtronomy on "sis" (TIMED_OF): a caustics
render at ss = 144 costs ~1.2 s per clump on this machine, too slow to time twice.
This project's rays on an analytic lens are interpolated bilinearly inside each
2.5 mas lens pixel from its traced corners (exact for the bilinear map), so on
"sis" its sub=1 image is not the peers' point samples; the two peers are
compared with each other there instead.

caustics is built on **PyTorch**, not JAX (its `backend_obj` is torch by
default); it is here because it is the differentiable strong-lensing simulator a
user would pick instead. Profile conventions (checked numerically, below):
caustics' `Sersic` is Ie·exp(−k((e/Re)^(1/n) − 1)) with e = √(x'² + (y'/q)²)
(`caustics.light.func.brightness_sersic`, `caustics.utils.to_elliptical`): Re on
the major axis, k from Ciotti & Bertin's expansion (`k_sersic`), phi the major
axis from +x; so Re = R_e·(k/b)^n and Ie = I0·e^(−k), b the exact b(n) of this
project, k the peer's own. JAXtronomy's "SERSIC_ELLIPSE" is lenstronomy's
(product-average radius, b = 1.9992n − 0.3271, radius floor `smoothing`), so
`bench_lenstronomy.lenstronomy_kwargs` converts for it and smoothing is 1e-9".

Sampling. Both peers are sampled as lenstronomy's adaptive mode is in
bench_lenstronomy: the detector pixels this project traces get ss × ss point
samples at sub-pixel centres, the others one at the centre. JAXtronomy does this
itself (`kwargs_numerics` compute_mode "adaptive", its ImageModel). caustics'
`LensSource` supersamples the whole field only (`upsample_factor`; 1.7e8 rays at
ss = 144), so its lens `raytrace` and a `LightStack` of its `Sersic` sources are
called on the same sub-pixel centres (see _peer_worker.py); `LensSource` itself,
full field, is used in the same-rays check. The PSF is applied at detector
sampling in all codes, as in bench_lenstronomy.

Order of a run (`main`), for each lens:
1. check: 1 clump and 30 clumps, the peers at ss = 12 (full field and adaptive)
   against this project with the same rays (2.5 mas lens pixels, one ray each,
   clumps analytic) — the profile, grid and PSF conventions;
2. error of every setting against a converged reference on the 30-clump scene
   ("map": lenstronomy at ss = 288, as bench_lenstronomy; "sis": JAXtronomy at
   ss = 288, each other code's ss = 288 given as agreement); a peer's matched
   supersampling is the smallest of PEER_SS whose max |Δ|/σ is no larger than
   this project's hybrid mode (or the best it reached, said so);
3. timing for each N: this project (hybrid, grid, sub=1) and each peer at ss = 12
   and its matched ss, cold (building + first call, in a fresh subprocess for
   the peers: JIT compilation included for JAXtronomy; imports excluded) and
   warm (median of repeated calls). Every ratio of a row comes from one run;
   the load average of the (shared) machine is recorded with each row.

Set-up (each peer in its own virtual environment, so that neither enters this
project's dependencies nor changes its JAX):

    python3.11 -m venv /tmp/venv-caustics && /tmp/venv-caustics/bin/pip install caustics
    python3.11 -m venv /tmp/venv-jaxtronomy && /tmp/venv-jaxtronomy/bin/pip install jaxtronomy

(or point CAUSTICS_PYTHON / JAXTRONOMY_PYTHON at other interpreters). This
script runs in the project's environment (it needs lenstronomy, the `bench`
extra, for the "map" reference) and starts each peer as
``<python> benchmarks/_peer_worker.py job.npz out.npz``. A peer whose
interpreter is missing is skipped.

Run: ``python benchmarks/bench_jax_peers.py [--lenses map,sis] [--counts 10,30,100,300,1000]``;
large counts in their own process with ``--counts 300 --append`` (the stored checks and
errors are kept); ``--single-call`` renders each peer once at its matched ss (cold only;
for 1000 clumps, where one render takes ~15–20 min here); ``--write-only`` rewrites the
Markdown from the JSON. Writes benchmarks/results/jax_peers.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import _common as C  # noqa: E402
import bench_lenstronomy as L  # noqa: E402
from clumpylen_jax import profiles  # noqa: E402
from clumpylen_jax.lensing import SIS  # noqa: E402

HERE = Path(__file__).resolve().parent
PYTHON = {
    "caustics": os.environ.get("CAUSTICS_PYTHON", "/tmp/venv-caustics/bin/python"),
    "jaxtronomy": os.environ.get("JAXTRONOMY_PYTHON", "/tmp/venv-jaxtronomy/bin/python"),
}
PEERS_OF = {"map": ("caustics",), "sis": ("caustics", "jaxtronomy")}     # same-rays checks
# error sweep and timing: caustics on its pixelated-deflection lens, JAXtronomy on the SIS (a
# caustics render at ss = 144 took 1.2 s per clump here, so it is timed on one scene only)
TIMED_OF = {"map": ("caustics",), "sis": ("jaxtronomy",)}
PEER_SS = (12, 36, 72, 108, 144, 216)
REF_SS = 288
OURS = {k: L.OURS[k] for k in ("sub1_analytic", "default", "hybrid")}


def our_lens(lens):
    return None if lens == "map" else SIS(jnp.asarray(L.THETA_E), jnp.asarray([0.0, 0.0]))


def clump_job(c):
    """This project's clump parameters plus I0 and the exact b(n), and lenstronomy's keywords."""
    b = np.array([float(profiles.sersic_b(float(n))) for n in c["n"]])
    i0 = np.array([float(c["flux"][k, 0]) * math.exp(float(profiles.sersic_log_norm(
        1.0, float(c["re"][k]), float(c["n"][k]), float(c["q"][k]), b[k])))
        for k in range(len(b))])
    lt = L.lenstronomy_kwargs(c)
    out = dict(center=c["center"], re=c["re"], n=c["n"], q=c["q"], pa=c["pa"], i0=i0, b_exact=b,
               lt_smoothing=L.LT_SMOOTHING)
    for key in lt[0]:
        out["lt_" + key] = np.array([d[key] for d in lt])
    return out


def run_peer(peer, lens, c, mask, settings, timeout=3000):
    """[(image, cold s, warm s)] for settings [(ss, warm repeats, full_field)], and the meta."""
    g = L.detector_grid()
    axis, a1, a2 = L.sis_map()
    job = dict(peer=peer, lens=lens, nx=g.nx, ny=g.ny, pixel=L.PIXEL, x0=g.x0_arcsec,
               y0=g.y0_arcsec, psf=L.moffat_kernel(), mask=mask, theta_e=L.THETA_E,
               map_a1=a1, map_a2=a2, map_pixel=L.MAP_PIXEL,
               map_center=np.array([axis[(len(axis) - 1) // 2]] * 2),
               settings=np.array(settings, dtype=np.int64), **clump_job(c))
    with tempfile.TemporaryDirectory() as tmp:
        jp, op = Path(tmp) / "job.npz", Path(tmp) / "out.npz"
        np.savez(jp, **job)
        r = subprocess.run([PYTHON[peer], str(HERE / "_peer_worker.py"), str(jp), str(op)],
                           capture_output=True, text=True, timeout=timeout)
        if r.returncode != 0:
            raise RuntimeError(f"{peer} worker failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
        print(r.stdout.strip(), flush=True)
        out = dict(np.load(op, allow_pickle=False))
    res = [(out[f"img{i}"], float(out[f"cold{i}"]), float(out[f"warm{i}"]))
           for i in range(len(settings))]
    return res, dict(import_s=float(out["import_s"]), versions=str(out["versions"]))


def available(peer):
    return Path(PYTHON[peer]).exists()


def check_and_errors(lens, meta):
    """Same-rays check (1 and 30 clumps) and every setting's error against the reference."""
    ol = our_lens(lens)
    scene = {}
    for n_cl in (1, 30):
        c = L.make_clumps(n_cl)
        ours, _, _, model = L.time_ours(c, OURS["sub1_analytic"], repeats=1, lens=ol)
        mask = L.traced_mask(model)
        adaptive = {}
        for peer in filter(available, PEERS_OF[lens]):
            (full, ad), m = run_peer(peer, lens, c, mask, [(12, 0, 1), (12, 0, 0)])
            meta.setdefault("peer_versions", {})[peer] = m["versions"]
            adaptive[peer] = ad[0]
            scene[f"check_{n_cl}_clumps_{peer}"] = dict(
                full_field=L.residual(ours, full[0]), adaptive=L.residual(ours, ad[0]),
                masked_pixels=int(mask.sum()))
            print(lens, peer, n_cl, "clumps, same rays:", scene[f"check_{n_cl}_clumps_{peer}"],
                  flush=True)
        if len(adaptive) == 2:      # the two peers against each other, the same point samples
            scene[f"peers_{n_cl}_clumps_caustics_vs_jaxtronomy"] = L.residual(
                adaptive["caustics"], adaptive["jaxtronomy"])
    # c, mask: the 30-clump scene
    peer_imgs = {}
    for peer in TIMED_OF[lens]:         # main() runs a scene only when its timed peers exist
        res, _ = run_peer(peer, lens, c, mask, [(ss, 0, 0) for ss in PEER_SS + (REF_SS,)])
        peer_imgs[peer] = {ss: r[0] for ss, r in zip(PEER_SS + (REF_SS,), res)}
    if lens == "map":
        ref_name = f"lenstronomy ss={REF_SS}"
        ref = L.time_lenstronomy(c, REF_SS, mask, repeats=0)[0]
    else:
        ref_name = f"jaxtronomy ss={REF_SS}"
        ref = peer_imgs["jaxtronomy"][REF_SS]
    errors = {}
    for peer in TIMED_OF[lens]:
        if f"{peer} ss={REF_SS}" != ref_name:
            errors[f"agreement: {peer} ss={REF_SS} vs reference"] = L.residual(
                peer_imgs[peer][REF_SS], ref)
    for name, acc in OURS.items():
        errors[f"ours {name}"] = L.residual(L.time_ours(c, acc, repeats=1, lens=ol)[0], ref)
    for peer in TIMED_OF[lens]:
        for ss in PEER_SS:
            errors[f"{peer} ss={ss}"] = L.residual(peer_imgs[peer][ss], ref)
    for k, v in errors.items():
        print(f"{lens} error {k}: {v}", flush=True)
    scene["reference"] = ref_name
    scene["errors_30_clumps"] = errors
    scene["ss_matched"] = {peer: matched_ss(errors, peer) for peer in TIMED_OF[lens]}
    return scene


def matched_ss(errors, peer):
    """(ss, reached): the smallest ss with max |Δ|/σ ≤ hybrid's, else the best one tried."""
    target = errors["ours hybrid"]["max_abs_over_sigma"]
    for ss in PEER_SS:
        if errors[f"{peer} ss={ss}"]["max_abs_over_sigma"] <= target:
            return [ss, True]
    best = min(PEER_SS, key=lambda s: errors[f"{peer} ss={s}"]["max_abs_over_sigma"])
    return [best, False]


def near_miss(errors, peer, ss, margin=1.1):
    """Whether `peer` at `ss` misses hybrid's max |Δ|/σ by less than `margin`×."""
    return (errors[f"{peer} ss={ss}"]["max_abs_over_sigma"]
            <= margin * errors["ours hybrid"]["max_abs_over_sigma"])


def time_row(lens, n, ss_matched, errors, single_call=False):
    """One row; single_call: each peer rendered once at its matched ss only (cold; no warm
    call, no ss = 12, no near miss), for counts where a render takes many minutes."""
    c = L.make_clumps(n)
    ol = our_lens(lens)
    row = dict(lens=lens, clumps=n, load_avg_start=os.getloadavg()[0])
    model = None
    for name, acc in OURS.items():
        _, row[f"ours_{name}_cold_s"], row[f"ours_{name}_warm_s"], m = L.time_ours(c, acc, lens=ol)
        model = model or m
    mask = L.traced_mask(model)
    for peer in TIMED_OF[lens]:
        if not available(peer):
            continue
        ss = ss_matched[peer][0]
        slow = n >= 300 or ss >= 144
        settings = [(12, 2, 0), (ss, 1 if slow else 2, 0)]
        below = PEER_SS[PEER_SS.index(ss) - 1]
        if near_miss(errors, peer, below):      # within 10 % of hybrid's error: timed too
            settings.append((below, 1 if slow else 2, 0))
        if single_call:
            (res,), _ = run_peer(peer, lens, c, mask, [(ss, 0, 0)])
            row[f"{peer}_ss"] = ss
            row[f"{peer}_matched_cold_s"] = res[1]
            row[f"{peer}_ratio_cold"] = res[1] / row["ours_hybrid_cold_s"]
            row[f"{peer}_ratio_cold_vs_our_warm"] = res[1] / row["ours_hybrid_warm_s"]
            continue
        res, _ = run_peer(peer, lens, c, mask, settings)
        row[f"{peer}_ss"] = ss
        row[f"{peer}_ss12_cold_s"], row[f"{peer}_ss12_warm_s"] = res[0][1:]
        row[f"{peer}_matched_cold_s"], row[f"{peer}_matched_warm_s"] = res[1][1:]
        if len(res) > 2:
            row[f"{peer}_near_ss"] = below
            row[f"{peer}_near_cold_s"], row[f"{peer}_near_warm_s"] = res[2][1:]
            row[f"{peer}_near_ratio_warm"] = row[f"{peer}_near_warm_s"] / row["ours_hybrid_warm_s"]
        row[f"{peer}_ratio_warm"] = row[f"{peer}_matched_warm_s"] / row["ours_hybrid_warm_s"]
        row[f"{peer}_ratio_cold"] = row[f"{peer}_matched_cold_s"] / row["ours_hybrid_cold_s"]
        row[f"{peer}_ratio_same_rays"] = (row[f"{peer}_ss12_warm_s"]
                                          / row["ours_sub1_analytic_warm_s"])
    row["load_avg_end"] = os.getloadavg()[0]
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lenses", default="map,sis")
    ap.add_argument("--counts", default="10,30,100,300,1000")
    ap.add_argument("--append", action="store_true",
                    help="keep the result file's checks, errors and other rows; (re)time these counts")
    ap.add_argument("--single-call", action="store_true",
                    help="peers: one (cold) render at the matched ss only (e.g. 1000 clumps)")
    ap.add_argument("--write-only", action="store_true",
                    help="rewrite jax_peers.md from jax_peers.json, nothing run")
    args = ap.parse_args(argv)
    if args.write_only:
        old = json.loads((C.RESULTS / "jax_peers.json").read_text())
        write_results(old["rows"], old["meta"])
        return old["rows"], old["meta"]
    lenses = args.lenses.split(",")
    counts = [int(v) for v in args.counts.split(",")]
    path = C.RESULTS / "jax_peers.json"
    old = json.loads(path.read_text()) if path.exists() else None
    meta = dict(machine=C.machine(), pixel_arcsec=L.PIXEL, field=L.FIELD,
                psf="Moffat 21x21 FWHM 2.5 px beta 2.5 at detector sampling",
                theta_e=L.THETA_E, map_pixel=L.MAP_PIXEL, peer_ss=PEER_SS, ref_ss=REF_SS,
                scenes={}, load_avg_start=os.getloadavg())
    rows = []
    if args.append and old:
        meta["scenes"] = old["meta"]["scenes"]
        meta["peer_versions"] = old["meta"].get("peer_versions", {})
        rows = [r for r in old["rows"] if not (r["lens"] in lenses and r["clumps"] in counts)]
    for lens in lenses:
        missing = [p for p in TIMED_OF[lens] if not available(p)]
        if missing:
            print(f"{lens}: {missing} not installed at {[PYTHON[p] for p in missing]}: skipped")
            continue
        if lens not in meta["scenes"]:
            meta["scenes"][lens] = check_and_errors(lens, meta)
            write_results(rows, meta)
        for n in counts:
            sc = meta["scenes"][lens]
            rows.append(time_row(lens, n, sc["ss_matched"], sc["errors_30_clumps"],
                                 args.single_call))
            print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in rows[-1].items()},
                  flush=True)
            meta["peak_rss_mb"] = C.peak_rss_mb()
            rows.sort(key=lambda r: (r["lens"], r["clumps"]))
            write_results(rows, meta)
    return rows, meta


def write_results(rows, meta):
    C.write_json("jax_peers", {"meta": meta, "rows": rows})
    md = ["# Speed against caustics and JAXtronomy", "",
          "Generated by `benchmarks/bench_jax_peers.py`: seconds per render (warm: median of "
          "repeated calls; cold: model building + first call, JIT included); ratio = peer / "
          "this project's hybrid mode, both measured in one run of the script. caustics runs on "
          "PyTorch (CPU), JAXtronomy on JAX; each in its own virtual environment.",
          f"Machine: {meta['machine']}; peers: {meta.get('peer_versions')}", ""]
    err_cols = [("setting", "setting (30 clumps)"), ("max_abs_over_sigma", r"max \|Δ\|/σ"),
                ("max_abs_over_peak", r"max \|Δ\|/peak"), ("flux_rel", "total flux error")]
    for lens, sc in meta["scenes"].items():
        peers = TIMED_OF[lens]
        md += [f"## Lens: {'SIS rasterised at 0.01 arcsec (pixelated deflection)' if lens == 'map' else 'analytic SIS'}", ""]
        for k, v in sc.items():
            if k.startswith("peers_"):
                md.append(f"- {k} (ss = 12 adaptive, the same point samples): max |Δ|/peak "
                          f"{C.fmt(v['max_abs_over_peak'])}, flux {C.fmt(v['flux_rel'])}")
            if k.startswith("check_"):
                md.append(f"- {k} (same rays as ours sub=1 analytic): full field max |Δ|/peak "
                          f"{C.fmt(v['full_field']['max_abs_over_peak'])}, flux "
                          f"{C.fmt(v['full_field']['flux_rel'])}; adaptive max |Δ|/peak "
                          f"{C.fmt(v['adaptive']['max_abs_over_peak'])}, flux "
                          f"{C.fmt(v['adaptive']['flux_rel'])}")
        md += ["", f"Error against the reference ({sc['reference']}); matched supersampling "
               f"(smallest of {PEER_SS} with max |Δ|/σ ≤ hybrid's, [ss, reached]): "
               f"{sc['ss_matched']}", "",
               C.markdown_table([dict(setting=k, **v) for k, v in sc["errors_30_clumps"].items()],
                                err_cols), ""]
        cols = [("clumps", "N"), ("ours_hybrid_warm_s", "ours hybrid warm"),
                ("ours_default_warm_s", "ours grid warm"),
                ("ours_sub1_analytic_warm_s", "ours sub=1 warm")]
        for p in peers:
            cols += [(f"{p}_ss", f"{p} ss"), (f"{p}_matched_warm_s", f"{p} matched warm"),
                     (f"{p}_ratio_warm", f"**{p} ratio warm**")]
            if any(f"{p}_near_ss" in r for r in rows if r["lens"] == lens):
                cols += [(f"{p}_near_ss", f"{p} ss just short (≤ 1.1× hybrid's error)"),
                         (f"{p}_near_warm_s", f"{p} just short warm"),
                         (f"{p}_near_ratio_warm", f"{p} just short ratio warm")]
        cols += [("ours_hybrid_cold_s", "ours hybrid cold")]
        for p in peers:
            cols += [(f"{p}_matched_cold_s", f"{p} matched cold"),
                     (f"{p}_ratio_cold", f"{p} ratio cold"),
                     (f"{p}_ss12_warm_s", f"{p} ss=12 warm"),
                     (f"{p}_ratio_same_rays", f"{p} ss=12 / ours sub=1")]
        for p in peers:
            if any(f"{p}_ratio_cold_vs_our_warm" in r for r in rows if r["lens"] == lens):
                cols += [(f"{p}_ratio_cold_vs_our_warm",
                          f"{p} one call / ours hybrid warm (single-call rows)")]
        cols += [("load_avg_start", "load avg")]
        md += [C.markdown_table([r for r in rows if r["lens"] == lens], cols), ""]
    C.write_text("jax_peers.md", "\n".join(md))


if __name__ == "__main__":
    main()
