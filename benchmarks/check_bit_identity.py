"""Bit-for-bit check of a refactoring: render the same scenes with the old and the new code.

``render OUT``: writes under OUT

- ``cli/<scene>-noise``: `clumpylen simulate` of every built-in scene; ``-nonoise``: with
  ``--no-noise`` (single-sersic, cosmic-archipelago); ``cli/single-sersic-f32``: with
  ``render.dtype = "float32"`` (a copy of the built-in TOML in OUT);
- ``api/<case>.npz``: the Python API on the single-sersic scene (``prepare`` → the model's
  band_images, noiseless, observe, variances, lens_plane, clump_magnifications,
  source_magnification_map) and on small synthetic scenes that reach the paths the
  built-in scenes do not (source_mode analytic / grid / hybrid, host_subsampling, an
  effective and an optical PSF, arms and texture on a lensed disk, float32).

``compare REF NEW``: every FITS HDU (data with np.array_equal, NaN = NaN; header cards
too, except DATE), every catalog.ecsv column, every summary.json value except timings,
every PNG's pixels and every npz array must agree exactly. Exit status 1 on any mismatch.

Run with the cache in a folder of its own (``CLUMPYLEN_CACHE=/tmp/x``): compiled programs
are keyed by their HLO and traced rays by the tracing code, so a cache hit is the same
computation (benchmarks/README.md, issue 21).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

SCENES = ("single-sersic", "cosmic-archipelago", "a2744-system3")
NO_NOISE = ("single-sersic", "cosmic-archipelago")
# the two big scenes through the CLI only (each API call is a compile: 15 min on a busy host)
API_SCENES = ("single-sersic",)
F32 = ("single-sersic",)


def _cli():
    return str(Path(sys.executable).with_name("clumpylen"))


def _f32_scene(name, out: Path) -> Path:
    from clumpylen_jax.scene import builtin_scene_text
    text = builtin_scene_text(name)
    if 'dtype = "float64"' in text:
        text = text.replace('dtype = "float64"', 'dtype = "float32"')
    else:
        text = text.replace("[render]\n", '[render]\ndtype = "float32"\n')
    path = out / f"{name}-f32.toml"
    path.write_text(text)
    return path


def render_cli(out: Path):
    runs = [(f"{s}-noise", s, []) for s in SCENES]
    runs += [(f"{s}-f32", str(_f32_scene(s, out)), []) for s in F32]
    runs += [(f"{s}-nonoise", s, ["--no-noise"]) for s in NO_NOISE]
    for tag, scene, extra in runs:
        print("cli", tag, flush=True)
        subprocess.run([_cli(), "simulate", scene, "--out", str(out / "cli" / tag), *extra],
                       check=True, stdout=subprocess.DEVNULL)


def _model_outputs(model, source, key):
    import equinox as eqx
    out = {}
    for k, img in enumerate(eqx.filter_jit(model.band_images)(source)):
        out[f"band_images_{k}"] = img
    noisy, clean, var = eqx.filter_jit(model.observe)(source, key)
    for k in range(len(noisy)):
        out[f"noisy_{k}"], out[f"clean_{k}"], out[f"var_{k}"] = noisy[k], clean[k], var[k]
    for k, img in enumerate(eqx.filter_jit(model.noiseless)(source)):
        out[f"noiseless_{k}"] = img
    if model.lensed:
        out["lens_plane"] = eqx.filter_jit(model.lens_plane)(source)
        if source.clumps is not None and source.clumps.count > 0:
            out["clump_magnifications"] = eqx.filter_jit(model.clump_magnifications)(source)
        if model.clump_grid is not None:
            out["source_magnification_map"] = eqx.filter_jit(
                lambda m: m.source_magnification_map())(model)
    return {k: np.asarray(v) for k, v in out.items()}


def _synthetic_cases():
    """(name, source, bands, build_model kwargs): small scenes for the paths the built-in
    scenes do not take."""
    import jax.numpy as jnp
    from clumpylen_jax.lensing.analytic import SIS, ExternalShear, LensSum
    from clumpylen_jax.model import Accuracy, Band
    from clumpylen_jax.source import Clumps, Disk, Sersic, Source, SpiralArms, Texture

    def src(dtype, arms=False):
        f = lambda x: jnp.asarray(x, dtype)  # noqa: E731
        rng = np.random.default_rng(3)
        n = 12
        cc = np.array([0.3, 0.05]) + rng.normal(0, 0.06, (n, 2))
        clumps = Clumps(f(cc), f(rng.uniform(1, 5, (n, 2))), f(rng.uniform(0.002, 0.01, n)),
                        f(rng.uniform(0.5, 2, n)), f(rng.uniform(0.4, 1, n)),
                        f(rng.uniform(0, 3, n)))
        bulge = Sersic(f([30.0, 40.0]), f(0.01), f(4.0), f(0.7), f(0.3), f([0.3, 0.05]))
        dsk = Sersic(f([60.0, 50.0]), f(0.05), f(1.0), f(1.0), f(0.0), f([0.3, 0.05]))
        disk = Disk(dsk, f(0.6),
                    arms=SpiralArms(2, f(0.5), f(2.0), f(0.4), f(0.05), f(0.0)) if arms else None,
                    texture=Texture(f(0.3), f(0.01), 3, jnp.asarray(7, jnp.uint32)) if arms else None)
        return Source(bulge=bulge, disk=disk, clumps=clumps)

    y, x = np.mgrid[:15, :15] - 7
    psf = np.exp(-(x**2 + y**2) / (2 * 2.0**2))
    bands = [Band("F1", 0.03, 1000.0, 0.1, psf=psf, psf_pixel_arcsec=0.01),
             Band("F2", 0.06, 2000.0, 0.2, psf=psf, psf_pixel_arcsec=0.02, psf_effective=True)]
    lens = LensSum((SIS(jnp.asarray(1.0), jnp.asarray([0.0, 0.0])),
                    ExternalShear(jnp.asarray(0.05), jnp.asarray(0.02))))
    field = ((-0.9, 1.6), (-0.8, 0.8))
    kw = dict(lens=lens, field_arcsec=field, lens_pixel_arcsec=0.005, source_pixel_arcsec=0.001)
    cases = []
    for mode in ("analytic", "grid", "hybrid"):
        cases.append((f"sis-{mode}", src(jnp.float64), bands,
                      dict(kw, accuracy=Accuracy(source_mode=mode))))
    cases.append(("sis-hybrid-hostsub", src(jnp.float64), bands,
                  dict(kw, accuracy=Accuracy(source_mode="hybrid", host_subsampling=True))))
    cases.append(("sis-arms", src(jnp.float64, arms=True), bands,
                  dict(kw, accuracy=Accuracy(source_mode="hybrid"))))
    cases.append(("sis-hybrid-f32", src(jnp.float32), bands,
                  dict(kw, accuracy=Accuracy(source_mode="hybrid"), dtype=jnp.float32)))
    cases.append(("unlensed", src(jnp.float64, arms=True), bands, dict(accuracy=Accuracy())))
    cases.append(("unlensed-nostrip", src(jnp.float64), bands[:1],
                  dict(accuracy=Accuracy(thin_strip=False))))
    cases.append(("unlensed-f32-nopsf", src(jnp.float32), [Band("F3", 0.03, 500.0, 0.1)],
                  dict(accuracy=Accuracy(), dtype=jnp.float32)))
    return cases


def render_api(out: Path, scenes=API_SCENES, cases=None):
    import jax
    import clumpylen_jax as cl
    from clumpylen_jax.model import build_model
    cl.enable_float64()
    (out / "api").mkdir(parents=True, exist_ok=True)
    key = jax.random.key(11)
    for name in scenes:
        print("api", name, flush=True)
        prep = cl.prepare(cl.load_scene(name))
        np.savez(out / "api" / f"{name}.npz", **_model_outputs(prep.model, prep.source, key))
    by_name = {c[0]: c for c in _synthetic_cases()}
    for name in (by_name if cases is None else cases):
        _, source, bands, kw = by_name[name]
        print("api", name, flush=True)
        model = build_model(source, bands, **kw)
        np.savez(out / "api" / f"{name}.npz", **_model_outputs(model, source, key))


# ------------------------------------------------------------------ comparing


def _equal(a, b):
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    if a.dtype.kind in "fc":
        return bool(np.array_equal(a, b, equal_nan=True))
    return bool(np.array_equal(a, b))


def _json_diff(a, b, path=""):
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if "timing" in k:
                continue
            if k not in a or k not in b:
                out.append(f"{path}/{k}: missing on one side")
            else:
                out += _json_diff(a[k], b[k], f"{path}/{k}")
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return sum((_json_diff(x, y, f"{path}[{i}]") for i, (x, y) in enumerate(zip(a, b))), [])
    same = (a == b) or (isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b))
    return [] if same else [f"{path}: {a!r} != {b!r}"]


def compare_file(ref: Path, new: Path):
    """List of differences between two files of the same kind."""
    if ref.suffix == ".fits":
        from astropy.io import fits
        out = []
        with fits.open(ref) as ha, fits.open(new) as hb:
            if len(ha) != len(hb):
                return [f"{len(ha)} vs {len(hb)} HDUs"]
            for k, (x, y) in enumerate(zip(ha, hb)):
                if (x.data is None) != (y.data is None) or (
                        x.data is not None and not _equal(x.data, y.data)):
                    out.append(f"HDU {k} ({x.name}) data differ")
                cards = lambda h: {c: v for c, v in h.header.items() if c not in ("DATE",)}  # noqa: E731
                if cards(x) != cards(y):
                    out.append(f"HDU {k} ({x.name}) header differs")
        return out
    if ref.suffix == ".ecsv":
        from astropy.table import Table
        ta, tb = Table.read(ref), Table.read(new)
        if ta.colnames != tb.colnames or len(ta) != len(tb):
            return ["columns or length differ"]
        return [f"column {c} differs" for c in ta.colnames if not _equal(ta[c], tb[c])]
    if ref.name == "summary.json":
        return _json_diff(json.loads(ref.read_text()), json.loads(new.read_text()))
    if ref.suffix == ".npz":
        a, b = np.load(ref), np.load(new)
        if set(a.files) != set(b.files):
            return [f"arrays {sorted(set(a.files) ^ set(b.files))} on one side only"]
        return [f"{k} differs" for k in a.files if not _equal(a[k], b[k])]
    if ref.suffix == ".png":
        import matplotlib.image as mpimg
        return [] if _equal(mpimg.imread(ref), mpimg.imread(new)) else ["pixels differ"]
    return []   # manifest.json etc.: run metadata (times, paths)


def compare(ref: Path, new: Path) -> int:
    bad = 0
    files = sorted(p.relative_to(ref) for p in ref.rglob("*") if p.is_file())
    checked = 0
    for rel in files:
        if rel.suffix == ".toml":
            continue
        if not (new / rel).is_file():
            print(f"MISSING {rel}")
            bad += 1
            continue
        diffs = compare_file(ref / rel, new / rel)
        checked += 1
        for d in diffs:
            print(f"DIFF {rel}: {d}")
        bad += bool(diffs)
    extra = [p for p in new.rglob("*") if p.is_file() and not (ref / p.relative_to(new)).exists()]
    for p in extra:
        print(f"EXTRA {p.relative_to(new)}")
    print(f"{checked} files compared, {bad} differ or are missing, {len(extra)} extra")
    return 1 if bad or extra else 0


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["render"] and len(argv) >= 2:
        out = Path(argv[1])
        out.mkdir(parents=True, exist_ok=True)
        what = argv[2:] or ["cli", "api"]
        if "api" in what:
            render_api(out)
        for w in what:
            if w.startswith("synthetic"):      # synthetic[:case,case,...]
                render_api(out, scenes=(), cases=w.partition(":")[2].split(",") if ":" in w
                           else None)
        if "cli" in what:
            render_cli(out)
        return 0
    if argv[:1] == ["compare"] and len(argv) == 3:
        return compare(Path(argv[1]), Path(argv[2]))
    print(__doc__)
    return 2


if __name__ == "__main__":
    sys.exit(main())
