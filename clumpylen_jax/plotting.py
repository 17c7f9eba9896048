"""The paper's figures for a finished run, as PNGs in RUN/plots/.

`plot_run(run_dir)` reads catalog.ecsv, bands/*.fits and summary.json and
draws what the run has:

- clump_mass_function.png — histogram of clump masses in log bins;
- clump_size_mass.png — R_e against mass with Brown & Gnedin (2021),
  R_e = 2.55 (M / 1e4 M☉)^0.24 pc;
- clump_ages.png — age histogram and the mass–age plane;
- lens_planes.png — lens plane (image + critical curves) and source plane
  (caustics, clumps, source centre); lensed runs only;
- mosaic.png — every band, asinh stretch, with the unlensed source inset
  at the same pixel scale (as the white squares of the paper's figures);
- paper_rgb.png — the paper's colour figure: HR lensed, HR convolved with a
  band's PSF, the detector composites, the clump of interest circled
  (paperfig.py).

Matplotlib runs on the Agg backend (no display); every file is written via
io.atomic_write.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["plot_run", "brown_gnedin_re_pc", "asinh_norm"]


def brown_gnedin_re_pc(mass_msun):
    """Brown & Gnedin (2021) cluster size–mass relation: R_e [pc] = 2.55 (M / 1e4 M☉)^0.24."""
    return 2.55 * (np.asarray(mass_msun, float) / 1e4) ** 0.24


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)  # never open a window; no-op if already Agg
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path, dpi=110) -> Path:
    from .io import atomic_write

    plt = _pyplot()
    try:
        with atomic_write(path) as tmp:
            fig.savefig(tmp, format="png", dpi=dpi)
    finally:
        plt.close(fig)
    return path


def asinh_norm(image, *, lo_pct=1.0, hi_pct=99.7, a=0.05):
    """An asinh ImageNormalize over the image's [lo, hi] percentiles (sky-dominated images stay readable)."""
    from astropy.visualization import AsinhStretch, ImageNormalize

    finite = np.asarray(image)[np.isfinite(image)]
    if finite.size == 0:
        return None
    lo, hi = np.percentile(finite, [lo_pct, hi_pct])
    if not hi > lo:
        hi = lo + 1.0
    return ImageNormalize(vmin=lo, vmax=hi, stretch=AsinhStretch(a))


# ------------------------------------------------------------------ catalogue figures


def _log_bins(values, per_decade=8):
    v = np.asarray(values, float)
    v = v[np.isfinite(v) & (v > 0)]
    lo, hi = np.floor(np.log10(v.min()) * per_decade), np.ceil(np.log10(v.max()) * per_decade)
    return 10 ** (np.arange(lo, max(hi, lo + 1) + 1) / per_decade)


def plot_mass_function(catalog, path):
    """Histogram of clump masses (log bins, dN per bin)."""
    plt = _pyplot()
    m = np.asarray(catalog["mass_msun"], float)
    fig, ax = plt.subplots(figsize=(5.5, 4.2))
    ax.hist(m, bins=_log_bins(m), histtype="stepfilled", alpha=0.6, color="tab:blue", edgecolor="k")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(r"clump mass [M$_\odot$]")
    ax.set_ylabel("N per bin")
    ax.set_title(f"clump mass function ({len(m)} clumps)")
    fig.tight_layout()
    return _save(fig, path)


def plot_size_mass(catalog, path):
    """R_e against mass, with the Brown & Gnedin (2021) relation."""
    plt = _pyplot()
    m = np.asarray(catalog["mass_msun"], float)
    re = np.asarray(catalog["re_pc"], float)
    fig, ax = plt.subplots(figsize=(5.5, 4.2))
    ax.scatter(m, re, s=4, alpha=0.5, color="tab:blue", label="clumps")
    grid = np.logspace(np.log10(m.min()), np.log10(m.max()), 50) if len(m) else np.logspace(4, 7, 50)
    ax.plot(grid, brown_gnedin_re_pc(grid), "r-", lw=1.5,
            label=r"Brown & Gnedin 2021: $2.55\,(M/10^4)^{0.24}$ pc")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(r"clump mass [M$_\odot$]")
    ax.set_ylabel(r"$R_e$ [pc]")
    ax.legend(fontsize=8)
    ax.set_title("size–mass relation")
    fig.tight_layout()
    return _save(fig, path)


def plot_ages(catalog, path):
    """Age histogram (log bins) and the mass–age plane."""
    plt = _pyplot()
    age = np.asarray(catalog["age_myr"], float)
    m = np.asarray(catalog["mass_msun"], float)
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(10, 4.2))
    a0.hist(age, bins=_log_bins(age), histtype="stepfilled", alpha=0.6, color="tab:orange", edgecolor="k")
    a0.set_xscale("log")
    a0.set_xlabel("age [Myr]")
    a0.set_ylabel("N per bin")
    a0.set_title("clump ages")
    a1.scatter(m, age, s=4, alpha=0.5, color="tab:orange")
    a1.set_xscale("log")
    a1.set_yscale("log")
    a1.set_xlabel(r"clump mass [M$_\odot$]")
    a1.set_ylabel("age [Myr]")
    a1.set_title("mass–age")
    fig.tight_layout()
    return _save(fig, path)


# ------------------------------------------------------------------ images


def _extent(band):
    """imshow extent in θ (arcsec) of a band image (pixel edges), from its CRPIX and scale."""
    ny, nx = band["image"].shape
    p = band["pixel_arcsec"]
    x0 = (0.5 - band["crpix"][0]) * p  # left edge of pixel 0: θ1 = (1 − CRPIX − ½) p
    y0 = (0.5 - band["crpix"][1]) * p
    return (x0, x0 + nx * p, y0, y0 + ny * p)


def _band_norm(band):
    """Asinh from −1σ of the sky noise (black) to the brightest noiseless light (at least 20σ): the
    sky reads dark grey and the source keeps its structure, whatever the band's depth."""
    from astropy.visualization import AsinhStretch, ImageNormalize

    sigma = float(np.sqrt(np.median(band["variance"])))
    top = float(np.percentile(band["noiseless"] - band["sky"], 99.9))
    top = max(top, 20.0 * sigma) if sigma > 0 else (top or 1.0)
    return ImageNormalize(vmin=-1.0 * sigma, vmax=top, stretch=AsinhStretch(0.2))


def plot_mosaic(bands, path):
    """All bands (image − sky, asinh), the unlensed source inset bottom-left at the same pixel scale."""
    plt = _pyplot()
    n = len(bands)
    ncol = min(n, 4)
    nrow = math.ceil(n / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.4 * ncol, 3.4 * nrow), squeeze=False)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    for ax, b in zip(axes.ravel(), bands):
        img = b["image"] - b["sky"]
        ax.imshow(img, origin="lower", cmap="gray", norm=_band_norm(b), extent=_extent(b),
                  interpolation="nearest")
        ax.set_title(f"{b['filter']}  ({b['exptime_s']:.0f} s)", fontsize=9)
        ax.tick_params(labelsize=7)
        unl = b.get("unlensed")
        if unl is not None and unl.size:
            # Same pixel scale: the inset spans the fraction of the axes that its pixels would.
            ny, nx = img.shape
            w, h = min(unl.shape[1] / nx, 0.45), min(unl.shape[0] / ny, 0.45)
            ins = ax.inset_axes([0.02, 0.02, w, h])
            ins.imshow(unl, origin="lower", cmap="gray", norm=asinh_norm(unl, lo_pct=0.0))
            ins.set_xticks([])
            ins.set_yticks([])
            for s in ins.spines.values():
                s.set_color("w")
    fig.supxlabel(r"$\theta_1$ [arcsec] (+West)", fontsize=9)
    fig.supylabel(r"$\theta_2$ [arcsec] (+North)", fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def _critical_curves(lens, field, pixel_arcsec=None):
    from .lensing.derived import critical_curves

    (x0, x1), (y0, y1) = field
    return critical_curves(lens, field, pixel_arcsec or max(x1 - x0, y1 - y0) / 400.0)


def plot_lens_planes(lens, field, source_center, catalog, path, *, backdrop=None, pixel_arcsec=None, cc=None):
    """Lens plane with critical curves (over `backdrop`, a band dict) and source plane with caustics."""
    from .lensing.derived import caustics

    plt = _pyplot()
    (x0, x1), (y0, y1) = field
    cc = cc if cc is not None else _critical_curves(lens, field, pixel_arcsec)
    ca = caustics(lens, cc)
    fig, (axl, axs) = plt.subplots(1, 2, figsize=(11, 5.2))
    if backdrop is not None:
        img = backdrop["image"] - backdrop["sky"]
        axl.imshow(img, origin="lower", cmap="gray", norm=asinh_norm(img), extent=_extent(backdrop))
    for name, colour in (("tangential", "tab:red"), ("radial", "tab:cyan")):
        for k, seg in enumerate(cc[name]):
            axl.plot(seg[:, 0], seg[:, 1], color=colour, lw=1, label=f"{name} critical" if k == 0 else None)
        for k, seg in enumerate(ca[name]):
            axs.plot(seg[:, 0], seg[:, 1], color=colour, lw=1, label=f"{name} caustic" if k == 0 else None)
    if catalog is not None and len(catalog):
        axs.scatter(catalog["beta1_arcsec"], catalog["beta2_arcsec"], s=2, alpha=0.4, color="tab:blue",
                    label="clumps")
    axs.scatter([source_center[0]], [source_center[1]], marker="*", s=120, color="m", zorder=3,
                label="source centre")
    axl.set_xlim(x0, x1)
    axl.set_ylim(y0, y1)
    # The lens plane keeps the field's limits (box adjusts); the source plane fits its data.
    axl.set_aspect("equal", adjustable="box")
    axs.set_aspect("equal", adjustable="datalim")
    for ax, lab in ((axl, r"\theta"), (axs, r"\beta")):
        ax.set_xlabel(rf"${lab}_1$ [arcsec] (+West)")
        ax.set_ylabel(rf"${lab}_2$ [arcsec] (+North)")
        ax.legend(fontsize=8, loc="best")
    axl.set_title("lens plane")
    axs.set_title("source plane")
    fig.tight_layout()
    return _save(fig, path)


# ------------------------------------------------------------------ the run


def _rows_with(catalog, *columns):
    """The catalogue rows whose `columns` are all finite and > 0 (none without a catalogue)."""
    if catalog is None or not all(c in catalog.colnames for c in columns):
        return []
    ok = np.ones(len(catalog), bool)
    for c in columns:
        v = np.asarray(catalog[c], float)
        ok &= np.isfinite(v) & (v > 0)
    return catalog[ok]


def plot_run(run_dir, *, out_dir=None) -> list[Path]:
    """Make every figure the run supports; returns the PNG paths (in out_dir, default RUN/plots)."""
    from .analysis import _lens_from_summary, _read_catalog, _read_summary, band_data
    from .paperfig import plot_paper_rgb

    run_dir = Path(run_dir)
    if not (run_dir / "summary.json").exists():
        raise FileNotFoundError(f"not a run directory (no summary.json): {run_dir}")
    out = Path(out_dir) if out_dir is not None else run_dir / "plots"
    summary = _read_summary(run_dir)   # a ConfigError naming the file when it is corrupt
    catalog = _read_catalog(run_dir)
    written = []
    # clumps given by magnitudes have no mass (NaN): those figures show the clumps that have one
    if len(with_mass := _rows_with(catalog, "mass_msun")):
        written.append(plot_mass_function(with_mass, out / "clump_mass_function.png"))
    if len(rows := _rows_with(catalog, "mass_msun", "re_pc")):
        written.append(plot_size_mass(rows, out / "clump_size_mass.png"))
    if len(rows := _rows_with(catalog, "mass_msun", "age_myr")):
        written.append(plot_ages(rows, out / "clump_ages.png"))
    by_file = [band_data(p) for p in sorted((run_dir / "bands").glob("*.fits"))]
    # Bands in the scene's order (blue to red as the user listed them), not alphabetical.
    order = list((summary.get("bands") or {}).keys())
    bands = sorted(by_file, key=lambda b: order.index(b["filter"]) if b["filter"] in order else len(order))
    lens = _lens_from_summary(summary, run_dir)
    field = summary.get("field_arcsec")
    cc = None
    if lens is not None and field:
        cc = _critical_curves(lens, field)
        center = (summary["scene"].get("source") or {}).get("center_arcsec", [0.0, 0.0])
        written.append(plot_lens_planes(lens, field, center, catalog, out / "lens_planes.png",
                                        backdrop=bands[0] if bands else None, cc=cc))
    if bands:
        written.append(plot_mosaic(bands, out / "mosaic.png"))
    curves = [] if cc is None else list(cc["tangential"]) + list(cc["radial"])
    # the run read once: the paper figure gets the same summary, bands, catalogue and lens
    paper = plot_paper_rgb(run_dir, out / "paper_rgb.png", summary=summary, catalog=catalog, lens=lens,
                           bands={b["filter"]: b for b in by_file}, curves=curves)
    if paper is not None:
        written.append(paper)
    return written
