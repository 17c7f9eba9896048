"""The result store of a study directory, and the gathered products.

    DIR/study.toml              the study file (a different study in DIR is refused)
    DIR/tasks/<task id>.npz     one file per finished task, written atomically (the truth:
                                resuming skips every task whose file exists)
    DIR/dataset.zarr            simulate: the training set (xarray/zarr; one group per
                                variant, "v0", "v1", ... when there are several)
    DIR/catalog.ecsv            simulate: every clump of every sample (the labels)
    DIR/completeness.ecsv       completeness: one row per (variant, band, mass, size)
    DIR/fisher_maps.zarr        completeness: Fisher-forecast S/N maps over the source plane
    DIR/fits.ecsv               fit: one row per fitted clump
    DIR/plots/*.png

Why zarr (through xarray) for the training set: one line loads it lazily
(`xarray.open_zarr(DIR / "dataset.zarr")`), chunks are per sample so a data loader
reads only what it needs, it is a directory of small files (object stores and
parallel file systems handle it; no HDF5 single-writer lock), and dask reads it in
parallel. It is written once, at the end, from the per-task files, into a temporary
directory renamed into place.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..io import atomic_write
from .spec import Study


class Store:
    """Per-task result files under DIR/tasks."""

    def __init__(self, out_dir):
        self.root = Path(out_dir)
        self.tasks_dir = self.root / "tasks"

    def init(self, study: Study) -> None:
        """Create DIR (or check that it holds this same study)."""
        f = self.root / "study.toml"
        if f.exists():
            if f.read_text(encoding="utf-8") != study.text:
                raise ConfigError("--out", str(self.root),
                                  "a new directory, or one holding this same study (study.toml differs)")
        else:
            with atomic_write(f, "w") as fh:
                fh.write(study.text)
        self.tasks_dir.mkdir(parents=True, exist_ok=True)

    def path(self, task_id: str) -> Path:
        return self.tasks_dir / f"{task_id}.npz"

    def done(self, task_id: str) -> bool:
        return self.path(task_id).exists()

    def write(self, task_id: str, result: dict) -> None:
        with atomic_write(self.path(task_id), "wb") as fh:
            np.savez(fh, **result)

    def read(self, task_id: str) -> dict:
        with np.load(self.path(task_id)) as z:
            return {k: z[k] for k in z.files}


def _replace_dir(tmp: Path, final: Path) -> None:
    """Move a finished directory into place (the old one, if any, goes after)."""
    old = None
    if final.exists():
        old = final.with_name(f".{final.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        os.replace(final, old)
    os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _write_zarr(datasets: dict, final: Path) -> None:
    """{group or None: xarray.Dataset} → a zarr directory, atomically."""
    tmp = Path(tempfile.mkdtemp(dir=final.parent, prefix=f".{final.name}."))
    shutil.rmtree(tmp)
    for group, ds in datasets.items():
        # zarr format 2: read by every zarr library and version (format 3 has no spec yet
        # for fixed-length strings such as band names)
        ds.to_zarr(tmp, group=group, mode="a" if tmp.exists() else "w", zarr_format=2,
                   consolidated=True)
    _replace_dir(tmp, final)


def gather(study: Study, store: Store, tasks) -> dict:
    """Read every task file and write the study's products; returns {name: path}."""
    fn = {"simulate": _gather_simulate, "completeness": _gather_completeness,
          "fit": _gather_fit}[study.kind]
    return fn(study, store, tasks)


def _gather_simulate(study, store, tasks) -> dict:
    import xarray as xr
    from astropy.table import Table

    from ..io import write_catalog

    by_variant: dict = {}
    for t in sorted(tasks, key=lambda t: t.sample):
        by_variant.setdefault(t.variant, []).append((t.sample, store.read(t.id)))
    datasets, rows = {}, []
    for v, items in by_variant.items():
        width = max(r["clump_valid"].size for _, r in items)

        def padded(key, r):
            a = r[key]
            pad = [(0, width - a.shape[0])] + [(0, 0)] * (a.ndim - 1)
            return np.pad(a, pad)

        first = items[0][1]
        nb, ny, nx = first["image"].shape
        clump = {k: np.stack([padded(k, r) for _, r in items])
                 for k in ("clump_x_arcsec", "clump_y_arcsec", "clump_mass_msun", "clump_re_pc",
                           "clump_re_arcsec", "clump_flux", "clump_valid")}
        samples = np.array([i for i, _ in items])
        ds = xr.Dataset(
            {k: (("sample", "band", "y", "x"), np.stack([r[k] for _, r in items]))
             for k in ("image", "noiseless", "variance")}
            | {k: (("sample", "clump", "band") if k == "clump_flux" else ("sample", "clump"), a)
               for k, a in clump.items()}
            | {"n_clumps": ("sample", np.array([r["n_clumps"] for _, r in items]))},
            coords={"sample": samples, "band": list(_band_names(study, v))},
            attrs={"study": study.text, "study_seed": study.seed, "variant": v,
                   "units": "images counts/s per pixel (with sky); positions arcsec (source plane); "
                            "clump_flux counts/s; a sample is reproducible from (study_seed, sample)"})
        chunks = {"sample": 1}
        datasets[None if len(by_variant) == 1 else f"v{v}"] = ds.chunk(chunks)
        for (i, r) in items:
            for k in np.flatnonzero(r["clump_valid"]):
                row = {"sample": i, "variant": v, "clump": k,
                       **{c: r[c][k] for c in ("clump_x_arcsec", "clump_y_arcsec", "clump_mass_msun",
                                                "clump_re_pc", "clump_re_arcsec")}}
                for b, name in enumerate(_band_names(study, v)):
                    row[f"flux_{name}"] = r["clump_flux"][k, b]
                rows.append(row)
    _write_zarr(datasets, store.root / "dataset.zarr")
    table = Table(rows=rows) if rows else Table()
    write_catalog(store.root / "catalog.ecsv", table)
    return {"dataset": store.root / "dataset.zarr", "catalog": store.root / "catalog.ecsv"}


def _band_names(study: Study, v: int) -> tuple:
    from ..scene import scene_from_dict
    from .spec import variant_scene_dict

    d, base = variant_scene_dict(study, v)
    return scene_from_dict(d, base_dir=base).band_names


def completeness_table(study: Study, store: Store, tasks):
    """One row per (variant, band, mass, size): recovered fraction and Fisher S/N of the injections."""
    from astropy.table import Table

    cells: dict = {}
    for t in tasks:
        if t.kind != "inject":
            continue
        r = store.read(t.id)
        c = cells.setdefault((t.variant, t.mass_index, t.size_index), {"rec": [], "det": []})
        c["rec"].append(r["recovered"])
        c["det"].append(r["detected"])
    rows = []
    for (v, i, j), c in sorted(cells.items()):
        rec, det = (np.concatenate(c[k]) for k in ("rec", "det"))
        snr = store.read(f"map-v{v}-m{i}-s{j}")["fisher_snr_injected"]   # the same positions
        for b, name in enumerate(_band_names(study, v)):
            rows.append({"variant": v, "band": name, "mass_msun": study.mass_msun.values[i],
                         "re_pc": study.re_pc.values[j], "n_injected": rec.shape[0],
                         "completeness": rec[:, b].mean(), "detected_fraction": det[:, b].mean(),
                         "fisher_snr_median": np.median(snr[:, b]),
                         "fisher_snr_mean": snr[:, b].mean()})
    return Table(rows=rows)


def _gather_completeness(study, store, tasks) -> dict:
    import xarray as xr

    from ..io import write_catalog
    from .plots import plot_completeness, plot_fisher_maps
    from .tasks import map_offsets

    table = completeness_table(study, store, tasks)
    write_catalog(store.root / "completeness.ecsv", table)
    m = study.options["map_npix"]
    axis = map_offsets(study)[:m, 0]
    datasets = {}
    for v in range(len(study.variants)):
        maps = np.stack([np.stack([store.read(f"map-v{v}-m{i}-s{j}")["fisher_snr_map"]
                                   for j in range(len(study.re_pc.values))])
                         for i in range(len(study.mass_msun.values))])     # [M, S, B, y, x]
        datasets[None if len(study.variants) == 1 else f"v{v}"] = xr.Dataset(
            {"fisher_snr": (("mass_msun", "re_pc", "band", "dy_arcsec", "dx_arcsec"), maps)},
            coords={"mass_msun": list(study.mass_msun.values), "re_pc": list(study.re_pc.values),
                    "band": list(_band_names(study, v)), "dy_arcsec": axis, "dx_arcsec": axis},
            attrs={"about": "Fisher-forecast S/N of a clump's flux (marginalised over R_e and "
                            "centre) against its source-plane offset from the host centre"})
    _write_zarr(datasets, store.root / "fisher_maps.zarr")
    files = {"table": store.root / "completeness.ecsv", "maps": store.root / "fisher_maps.zarr"}
    files.update(plot_completeness(table, store.root / "plots"))
    files.update(plot_fisher_maps(datasets, store.root / "plots"))
    return files


def _gather_fit(study, store, tasks) -> dict:
    from astropy.table import Table

    from ..io import write_catalog

    rows = []
    for t in sorted(tasks, key=lambda t: t.sample):
        r = store.read(t.id)
        names = _band_names(study, t.variant)
        for k in range(r["true_re_arcsec"].size):
            row = {"sample": t.sample, "variant": t.variant, "clump": k, "success": bool(r["success"]),
                   "true_mass_msun": r["true_mass_msun"][k]}
            for c in ("x_arcsec", "y_arcsec", "re_arcsec"):
                row[f"true_{c}"] = r[f"true_{c}"][k]
                row[f"fit_{c}"] = r[f"fit_{c}"][k]
            row["err_re_arcsec"] = r["err_re_arcsec"][k]
            for b, name in enumerate(names):
                row[f"true_flux_{name}"] = r["true_flux"][k, b]
                row[f"start_flux_{name}"] = r["start_flux"][k, b]
                row[f"fit_flux_{name}"] = r["fit_flux"][k, b]
                row[f"err_flux_{name}"] = r["err_flux"][k, b]
            rows.append(row)
    write_catalog(store.root / "fits.ecsv", Table(rows=rows))
    return {"table": store.root / "fits.ecsv"}
