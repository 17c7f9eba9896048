"""Diagnostic figure of a lens: critical curves and images, caustics and source.

Matplotlib with the Agg backend (no display needed). The PNG is written
atomically: to a temporary file in the target folder, then os.replace.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from .derived import caustics, critical_curves
from .images import find_images


def plot_lens(lens, beta, path, *, field, pixel_arcsec, source_radius_arcsec=None,
              images=None, title=None, dpi=110):
    """Draw the lens plane (critical curves, images) and source plane (caustics, source).

    lens: any lens; beta: (β1, β2) of the source, arcsec; path: PNG to write;
    field: lens-plane field ((θ1_min, θ1_max), (θ2_min, θ2_max)), arcsec;
    pixel_arcsec: grid for the curves and the image search; source_radius_arcsec:
    draw a circle of that radius around β; images: precomputed `Images` (else found
    here). +θ1 (West) points right, as in a north-up, east-left image.
    Returns the path.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    cc = critical_curves(lens, field, pixel_arcsec)
    ca = caustics(lens, cc)
    if images is None:
        images = find_images(lens, float(beta[0]), float(beta[1]), field=field, pixel_arcsec=pixel_arcsec)
    valid = np.asarray(images.valid)

    fig, (axl, axs) = plt.subplots(1, 2, figsize=(11, 5.2))
    _draw_curves(axl, axs, cc, ca)
    _draw_images(axl, images, valid)
    axs.scatter([beta[0]], [beta[1]], color="m", zorder=3, label="source")
    if source_radius_arcsec:
        axs.add_patch(plt.Circle((beta[0], beta[1]), source_radius_arcsec, fill=False, color="m"))
    (x0, x1), (y0, y1) = field
    axl.set_xlim(x0, x1)
    axl.set_ylim(y0, y1)
    for ax, lab in ((axl, "θ"), (axs, "β")):
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{lab}1 [arcsec] (+West)")
        ax.set_ylabel(f"{lab}2 [arcsec] (+North)")
        ax.legend(fontsize=8, loc="best")
    axl.set_title("lens plane")
    axs.set_title("source plane")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    try:
        _save_png_atomically(fig, Path(path), dpi)
    finally:
        plt.close(fig)
    return Path(path)


def _draw_curves(axl, axs, cc, ca) -> None:
    """Critical curves on the lens-plane axes, caustics on the source-plane axes (arcsec)."""
    for name, colour in (("tangential", "tab:red"), ("radial", "tab:blue")):
        for k, seg in enumerate(cc[name]):
            axl.plot(seg[:, 0], seg[:, 1], color=colour, lw=1, label=f"{name} critical" if k == 0 else None)
        for k, seg in enumerate(ca[name]):
            axs.plot(seg[:, 0], seg[:, 1], color=colour, lw=1, label=f"{name} caustic" if k == 0 else None)


def _draw_images(axl, images, valid) -> None:
    """The valid images as crosses at θ [arcsec], each labelled with its magnification."""
    t1 = np.asarray(images.theta1)[valid]
    t2 = np.asarray(images.theta2)[valid]
    mu = np.asarray(images.magnification)[valid]
    axl.scatter(t1, t2, marker="x", color="k", zorder=3, label="images")
    for a, b, m in zip(t1, t2, mu):
        axl.annotate(f"μ={m:.1f}", (a, b), textcoords="offset points", xytext=(4, 4), fontsize=8)


def _save_png_atomically(fig, path: Path, dpi) -> None:
    """Write fig as a PNG: to a temporary file beside path, then os.replace (no half file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fig.savefig(fh, format="png", dpi=dpi)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
