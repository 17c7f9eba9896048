"""Files of a fit of observations (SCENE.md): fit.ecsv, residuals_<FILTER>.fits, clumps.reg,
summary.json and fit.png — each written atomically."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import atomic_write, write_catalog, write_json, write_residual_fits
from .lens import describe as describe_lens


def _wcs_header(ob, frame_band):
    from astropy.io import fits
    h = fits.Header()
    if frame_band.wcs is not None:
        h.update(frame_band.wcs.to_header())
    h["PIXSCALE"] = (frame_band.pixel_arcsec, "arcsec/pixel")
    if frame_band.pixel_matrix_arcsec is not None:     # the orientation the fit used, complete
        for i, row in enumerate(frame_band.pixel_matrix_arcsec, 1):
            for j, v in enumerate(row, 1):
                h[f"PIX2A{i}{j}"] = (v, "pixel-to-angle matrix (arcsec; East, North)")
    h["FILTER"] = ob.name
    h["BUNIT"] = ob.units
    h["ZP_AB"] = (ob.zeropoint_ab, "AB mag of one data unit per pixel")
    return h


def chi_map(ob, fit, k):
    """(data − model)/σ of band k on the data's pixels, NaN where masked: the one place the
    residual files, the figure and χ²/dof compute it."""
    mu = np.asarray(fit.images[k], float)
    return np.where(ob.mask, (ob.data - mu) / np.sqrt(np.asarray(fit.data.variances[k], float)), np.nan)


def write_residuals(out: Path, observations, fit) -> list:
    """residuals_<FILTER>.fits: DATA, MODEL, RESIDUAL, CHI on the data's pixels and WCS."""
    paths = []
    for k, ob in enumerate(observations):
        mu = np.asarray(fit.images[k], float)
        d = np.where(ob.mask, ob.data, np.nan)
        chi = chi_map(ob, fit, k)
        hdr = _wcs_header(ob, ob.frame)
        path = out / f"residuals_{ob.name}.fits"
        write_residual_fits(path, d, mu, chi, header=hdr, chi_bunit="sigma", primary_header=hdr)
        paths.append(path)
    return paths


def write_regions(path: Path, table, frame) -> Path:
    """DS9 regions of the clumps: circles of radius max(R_e, 1.5 pixels), labelled by id."""
    from regions import CirclePixelRegion, CircleSkyRegion, PixCoord, Regions
    p0 = frame.grids[0].pixel_arcsec
    regs = []
    for row in table:
        r_pix = max(float(row["re_obs_arcsec"] if "re_obs_arcsec" in table.colnames
                          else row["re_arcsec"]) / p0, 1.5)
        meta = {"text": str(int(row["id"]))}
        if "ra_deg" in table.colnames:
            import astropy.units as u
            from astropy.coordinates import SkyCoord
            regs.append(CircleSkyRegion(SkyCoord(row["ra_deg"] * u.deg, row["dec_deg"] * u.deg),
                                        r_pix * p0 * u.arcsec, meta=meta))
        else:
            regs.append(CirclePixelRegion(PixCoord(float(row["x_pix"]), float(row["y_pix"])),
                                          r_pix, meta=meta))
    with atomic_write(path, "w") as fh:
        fh.write(Regions(regs).serialize(format="ds9") if regs else
                 "# Region file format: DS9\n# no clumps\nimage\n")
    return path


def _stretch(img, lo, hi):
    return np.arcsinh(np.clip((img - lo) / max(hi - lo, 1e-30), -0.05, None) * 10) / np.arcsinh(10)


def _source_plane_panel(ax, ob, frame, lens, table):
    """The first band's data mapped back to the source plane: every pixel centre's β, the mean
    of the pixels in each β bin (60 × 60 bins over where the > 3σ pixels land); clumps at β."""
    from .lens import source_plane
    ny, nx = ob.data.shape
    xy = np.stack(np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float)), -1)
    use = ob.mask & np.isfinite(ob.data)
    beta = source_plane(lens, frame.theta(frame.phi_of_pixel(xy[use], 0))).beta
    d = ob.data[use]
    bright = d > 3 * np.sqrt(ob.variance[use])
    ref = beta[bright] if bright.sum() >= 10 else beta
    lo, hi = np.percentile(ref, [1, 99], axis=0)
    pad = 0.2 * (hi - lo) + 1e-3
    rng = [(lo[0] - pad[0], hi[0] + pad[0]), (lo[1] - pad[1], hi[1] + pad[1])]
    tot, ex, ey = np.histogram2d(beta[:, 0], beta[:, 1], 60, range=rng, weights=d)
    cnt, _, _ = np.histogram2d(beta[:, 0], beta[:, 1], 60, range=rng)
    with np.errstate(invalid="ignore", divide="ignore"):
        img = (tot / cnt).T
    v0, v1 = np.nanpercentile(img, [5, 99.7])
    # β1 runs West (DESIGN.md): East to the left, as on the sky
    ax.imshow(_stretch(img, v0, v1), origin="lower", cmap="gray_r", vmin=0, vmax=1,
              extent=(ex[0], ex[-1], ey[0], ey[-1]), interpolation="nearest")
    ax.set_title(f"{ob.name} in the source plane")
    if len(table):
        ax.scatter(table["beta1_arcsec"], table["beta2_arcsec"], s=40, facecolors="none",
                   edgecolors="tab:orange", linewidths=1.0)
    ax.set_xlabel("β1 (arcsec, West)")
    ax.set_ylabel("β2 (arcsec, North)")


def write_png(path: Path, observations, fit, table, frame, lens=None) -> Path:
    """Data, model and residual (χ) per band, clumps marked; with a lens, the first band's
    data in the source plane beside them."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    nb = len(observations)
    ncol = 3 if lens is None else 4
    fig, axes = plt.subplots(nb, ncol, figsize=(3.5 * ncol, 3.4 * nb), squeeze=False)
    if lens is not None:
        _source_plane_panel(axes[0, 3], observations[0], frame, lens, table)
        for k in range(1, nb):
            axes[k, 3].axis("off")
    for k, ob in enumerate(observations):
        d = np.where(ob.mask, ob.data, np.nan)
        mu = np.asarray(fit.images[k])
        chi = chi_map(ob, fit, k)
        lo, hi = np.nanpercentile(d, [5, 99.7])
        for j, (img, title, kw) in enumerate((
                (_stretch(d, lo, hi), f"{ob.name} data", dict(cmap="gray_r", vmin=0, vmax=1)),
                (_stretch(mu, lo, hi), "model", dict(cmap="gray_r", vmin=0, vmax=1)),
                (chi, "residual (χ)", dict(cmap="RdBu_r", vmin=-5, vmax=5)))):
            ax = axes[k, j]
            im = ax.imshow(img, origin="lower", interpolation="nearest", **kw)
            ax.set_title(title)
            if j == 2:
                fig.colorbar(im, ax=ax, fraction=0.046)
            if len(table):
                xy = frame.pixel_of(frame.phi_of_pixel(
                    np.stack([np.asarray(table["x_pix"]), np.asarray(table["y_pix"])], -1), 0), k)
                ax.scatter(xy[:, 0], xy[:, 1], s=60, facecolors="none", edgecolors="tab:orange",
                           linewidths=1.0)
                if j == 0:
                    for i, (x, y) in enumerate(xy):
                        ax.annotate(str(i), (x, y), xytext=(4, 4), textcoords="offset points",
                                    color="tab:orange", fontsize=7)
            ax.set_xlabel("x (pixel)")
            ax.set_ylabel("y (pixel)")
    fig.tight_layout()
    with atomic_write(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    return path


def chi2_per_dof(observations, fit) -> dict:
    """χ²/dof per band (dof: the band's used pixels less its share of the free parameters and
    its own diffuse-light coefficients)."""
    n_free = len(fit.param.labels)
    n_pix = [int(ob.mask.sum()) for ob in observations]
    total = sum(n_pix)
    out = {}
    for k, ob in enumerate(observations):
        chi2 = float(np.nansum(chi_map(ob, fit, k) ** 2))
        dof = max(n_pix[k] - n_free * n_pix[k] / total - fit.data.n_diffuse[k], 1.0)
        out[ob.name] = chi2 / dof
    return out


def write_all(out_dir, scene, observations, frame, fit, table, host, extra=None, lens=None) -> list:
    """Every output file of the fit into out_dir; returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    table.meta.update({"scene": scene.name, "success": bool(fit.success),
                       "units": {ob.name: ob.units for ob in observations},
                       "zeropoint_ab": {ob.name: ob.zeropoint_ab for ob in observations}})
    write_catalog(out / "fit.ecsv", table)
    files.append(out / "fit.ecsv")
    files += write_residuals(out, observations, fit)
    files.append(write_regions(out / "clumps.reg", table, frame))
    summary = {
        "scene": scene.name, "path": scene.path, "success": bool(fit.success),
        "n_clumps": int(fit.n_clumps), "chi2_per_dof": chi2_per_dof(observations, fit),
        "free_parameters": list(fit.param.labels), "n_free": len(fit.param.labels),
        "diffuse": None if fit.data.diffuse is None else {
            "spacing_arcsec": scene.fit.diffuse_spacing_arcsec,
            "n_coefficients": {ob.name: int(n) for ob, n in zip(observations, fit.data.n_diffuse)},
            "in": "MODEL of residuals_<FILTER>.fits (profiled out of the fit: inference/diffuse.py)"},
        "timings_s": fit.timings_s, "steps": fit.steps, "host": host,
        "background": "in the diffuse light" if fit.data.diffuse is not None else
        {ob.name: float(fit.state.background_counts_per_s[k]) for k, ob in enumerate(observations)},
        "bands": {ob.name: {"file": ob.path, "units": ob.units, "units_conversion": ob.units_how,
                            "zeropoint_ab": ob.zeropoint_ab, "pixel_arcsec": g.pixel_arcsec,
                            "n_pixels_used": int(ob.mask.sum()),
                            "grid_origin_arcsec": [g.x0_arcsec, g.y0_arcsec],
                            # pixel axes against the first band's (a RotatedGrid: the model
                            # is drawn on aligned pixels and carried onto these by overlaps)
                            "axes_turned_deg": float(np.degrees(getattr(g, "angle_rad", 0.0))),
                            "psf": None if ob.psf is None else ob.psf.source,
                            "noise_model": ob.noise_exptime_s is not None,
                            "noise": ob.noise_how,
                            "orientation": ob.frame_how,
                            "pixel_matrix_arcsec": None if ob.frame.pixel_matrix_arcsec is None
                            else [list(r) for r in ob.frame.pixel_matrix_arcsec],
                            "n_pixels_masked": int((~ob.mask).sum())}
                  for ob, g in zip(observations, frame.grids)},
        "frame": {"wcs": frame.reference.wcs is not None,
                  "center_radec_deg": frame.center_radec(),
                  "theta": "DESIGN.md θ (West, North) from the WCS" if frame.reference.wcs
                  is not None else "DESIGN.md θ (West, North) from the pixel matrix"
                  if frame.reference.pixel_matrix_arcsec is not None
                  else "pixel axes (no WCS): x taken as West, y as North"},
        "fit_options": {k: getattr(scene.fit, k) for k in scene.fit.__dataclass_fields__},
        "lens": describe_lens(lens),
        "z_source": scene.z_source,
    }
    summary.update(extra or {})
    write_json(out / "summary.json", summary)
    files.append(out / "summary.json")
    files.append(write_png(out / "fit.png", observations, fit, table, frame, lens))
    return files
