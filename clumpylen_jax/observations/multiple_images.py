"""Images of one source clump: fitted clumps that the lens maps to one β, grouped afterwards.

    group_images(beta, beta_cov, mu, theta, match_arcsec, min_separation_arcsec) -> source_id [N]
    image_groups(table, band_names) -> [dict]: each group's members, β, colours and their χ²

The fit is in the image plane (each image with its own parameters); this is the step an
astronomer takes after it. Two clumps are linked as images of one source clump when their
β agree within √(match² + 9 (σ²_β,i + σ²_β,j)) (`match_arcsec`: the lens model's precision
in the source plane; σ_β from the fit; a clump with σ_β > match_arcsec is matched to
nothing) and they can be different images: opposite parity (sign of μ: the two sides of a
fold critical curve) or at least `min_separation_arcsec` apart. The second condition keeps neighbouring clumps of one highly magnified image apart,
whose β differ by their separation / μ, which can be below any model precision. Groups
grow from the closest matches first, and two groups join only when every pair across them
could be two images: a neighbour of one image cannot join through the counter-image.

Lensing is achromatic, so the images of one clump share its colours: `image_groups` gives
each member's colours (first band − each other band) and the χ² of their agreement about
the inverse-variance mean, a check of the match and of the photometry (what outside checks
of issue 17 compare). The fit does not tie the images (each keeps its own fluxes and sizes).
"""

from __future__ import annotations

import numpy as np


def group_images(beta, beta_cov, mu, theta, match_arcsec: float,
                 min_separation_arcsec: float) -> np.ndarray:
    """source_id [N] (0, 1, … in order of first appearance): one id per source clump.

    beta, theta: [N, 2] arcsec (source and image plane); beta_cov: [N, 2, 2] arcsec² (NaN:
    treated as 0); mu: [N] signed magnification."""
    beta = np.asarray(beta, float).reshape(-1, 2)
    theta = np.asarray(theta, float).reshape(-1, 2)
    n = len(beta)
    var = np.nan_to_num(0.5 * np.trace(np.asarray(beta_cov, float).reshape(n, 2, 2),
                                       axis1=1, axis2=2))
    parity = np.sign(np.asarray(mu, float))
    sep = np.hypot(*(theta[:, None, :] - theta[None, :, :]).transpose(2, 0, 1))
    distinct = (parity[:, None] != parity[None, :]) | (sep >= min_separation_arcsec)
    d_beta = np.hypot(*(beta[:, None, :] - beta[None, :, :]).transpose(2, 0, 1))
    tol = np.sqrt(match_arcsec ** 2 + 9.0 * (var[:, None] + var[None, :]))
    group = [{i} for i in range(n)]
    member_of = list(range(n))
    # a clump whose β is known worse than the match (σ_β > match_arcsec: a position the fit
    # did not measure) is matched to nothing: its 3σ would reach any clump
    known = np.sqrt(var) <= match_arcsec
    # closest matches first; two groups join only when every pair across them can be two
    # images (distinct): a neighbour of one image cannot join through the counter-image
    pairs = sorted(((d_beta[i, j] / max(tol[i, j], 1e-300), i, j) for i in range(n)
                    for j in range(i + 1, n)
                    if d_beta[i, j] <= tol[i, j] and distinct[i, j] and known[i] and known[j]))
    for _, i, j in pairs:
        gi, gj = member_of[i], member_of[j]
        if gi == gj or not all(distinct[a, b] for a in group[gi] for b in group[gj]):
            continue
        group[gi] |= group[gj]
        for b in group[gj]:
            member_of[b] = gi
        group[gj] = set()
    ids, out = {}, np.empty(n, int)
    for i in range(n):
        out[i] = ids.setdefault(member_of[i], len(ids))
    return out


def image_groups(table, band_names) -> list:
    """Per source clump with two or more images in `table` (fit.ecsv's rows, with
    `source_id`, β and `mag_<F>`/`mag_<F>_err`): {source_id, members (clump ids), beta_arcsec
    (mean), colours: {"F1-F2": [per member]}, colour_errors, colour_chi2, colour_dof}.
    Upper limits (NaN errors) take no part in the colour χ²."""
    out = []
    sid = np.asarray(table["source_id"])
    for s in np.unique(sid):
        rows = np.flatnonzero(sid == s)
        if len(rows) < 2:
            continue
        g = {"source_id": int(s), "members": [int(table["id"][r]) for r in rows],
             "beta_arcsec": [float(np.mean(table["beta1_arcsec"][rows])),
                             float(np.mean(table["beta2_arcsec"][rows]))],
             "colours": {}, "colour_errors": {}}
        chi2, dof = 0.0, 0
        first = band_names[0]
        for other in band_names[1:]:
            key = f"{first}-{other}"
            c = np.asarray(table[f"mag_{first}"][rows] - table[f"mag_{other}"][rows], float)
            e = np.hypot(np.asarray(table[f"mag_{first}_err"][rows], float),
                         np.asarray(table[f"mag_{other}_err"][rows], float))
            g["colours"][key] = [float(v) for v in c]
            g["colour_errors"][key] = [float(v) for v in e]
            ok = np.isfinite(c) & np.isfinite(e) & (e > 0)
            if ok.sum() >= 2:
                w = 1.0 / e[ok] ** 2
                mean = np.sum(w * c[ok]) / np.sum(w)
                chi2 += float(np.sum(w * (c[ok] - mean) ** 2))
                dof += int(ok.sum()) - 1
        g["colour_chi2"], g["colour_dof"] = chi2, dof
        out.append(g)
    return out
