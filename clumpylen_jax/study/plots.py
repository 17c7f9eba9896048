"""Figures of a completeness study: completeness against mass and size per band, the
empirical completeness against the Fisher-forecast S/N, and S/N maps over the source plane."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _save(fig, path: Path) -> Path:
    from ..io import atomic_write

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    return path


def plot_completeness(table, out_dir) -> dict:
    """Per variant and band: completeness vs mass (one line per size), and vs Fisher S/N."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = {}
    for v in np.unique(table["variant"]):
        for band in np.unique(table["band"]):
            t = table[(table["variant"] == v) & (table["band"] == band)]
            fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
            for re in np.unique(t["re_pc"]):
                s = t[t["re_pc"] == re]
                s = s[np.argsort(s["mass_msun"])]
                a.semilogx(s["mass_msun"], s["completeness"], "o-", label=f"R_e = {re:g} pc")
                b.semilogx(s["fisher_snr_median"], s["completeness"], "o-", label=f"R_e = {re:g} pc")
            a.set_xlabel("clump mass (M$_\\odot$)")
            a.set_ylabel("completeness (injection–recovery)")
            a.set_title(f"{band}, variant {v}")
            a.set_ylim(-0.05, 1.05)
            a.legend(fontsize=8)
            b.axvline(5.0, color="k", ls=":", lw=1)
            b.set_xlabel("Fisher-forecast S/N of the flux (median over positions)")
            b.set_ylim(-0.05, 1.05)
            b.set_title("checked against the gradient forecast")
            name = f"completeness_v{v}_{band}"
            files[name] = _save(fig, Path(out_dir) / f"{name}.png")
            plt.close(fig)
    return files


def plot_fisher_maps(datasets: dict, out_dir) -> dict:
    """Per variant and band: S/N map over the source plane for each (mass, size) (up to 4 × 4)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = {}
    for group, ds in datasets.items():
        v = group or "v0"
        snr = ds["fisher_snr"]
        mi = np.unique(np.linspace(0, snr.sizes["mass_msun"] - 1, 4).round().astype(int))
        si = np.unique(np.linspace(0, snr.sizes["re_pc"] - 1, 4).round().astype(int))
        x = ds["dx_arcsec"].values
        ext = [x[0], x[-1], x[0], x[-1]]
        for b, band in enumerate(ds["band"].values):
            fig, axes = plt.subplots(len(si), len(mi), figsize=(2.6 * len(mi), 2.4 * len(si)),
                                     squeeze=False)
            for r, j in enumerate(si):
                for c, i in enumerate(mi):
                    ax = axes[r, c]
                    img = ax.imshow(snr.values[i, j, b], origin="lower", extent=ext, cmap="viridis")
                    ax.contour(snr.values[i, j, b], levels=[5.0], colors="w", extent=ext,
                               origin="lower", linewidths=1)
                    fig.colorbar(img, ax=ax, shrink=0.8)
                    ax.set_title(f"{snr['mass_msun'].values[i]:.2g} M$_\\odot$, "
                                 f"{snr['re_pc'].values[j]:g} pc", fontsize=8)
                    ax.tick_params(labelsize=6)
            fig.suptitle(f"{band}: Fisher S/N of the flux over the source plane "
                         "(Δβ, arcsec from the host centre; white: S/N = 5)", fontsize=9)
            name = f"fisher_map_{v}_{band}"
            files[name] = _save(fig, Path(out_dir) / f"{name}.png")
            plt.close(fig)
    return files
