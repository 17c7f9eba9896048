"""`fit_observation_scene`: the whole path of `clumpylen fit` for a scene with [[observations]].

read and check every band (before any compilation) → fit frame → clump starts
("auto": inference.auto; a catalogue; "none") → joint fit → [posterior sampled from its
optimum: `[fit] method` "nuts" / "emcee", sample.py] → answers → files.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..inference.diffuse import require_spacing
from .answers import clump_rows, host_summary
from .config import ObservationScene, load_observation_scene
from .fit import fit_observations
from .frame import fit_frame
from .lens import place_lens
from .read import read_observation

# LM tolerance of the automatic stage (`AutoOptions.rtol`, 1e-6 there): its optimum only starts
# the joint fit, which refits every parameter to lm_fit's rtol (1e-7); S1063 (10 clumps): 30–40 % fewer LM
# steps in the counting and final refit, the same clumps and joint χ² (Δχ² 0.001)
AUTO_RTOL = 1e-4


def read_scene_data(scene: ObservationScene):
    """(observations, frame): every band read and checked, and placed in one fit frame."""
    obs = [read_observation(s) for s in scene.observations]
    frame = fit_frame([o.frame for o in obs], [o.name for o in obs], [o.path for o in obs])
    if scene.z_source is not None and len(obs) >= 2:   # masses need every filter's throughput
        from ..filters import load_filter
        for o in obs:
            try:
                load_filter(o.name)
            except ConfigError as exc:
                raise ConfigError(f"observations[{o.name}].filter", o.name,
                                  f"a known filter for masses at z_source ({exc.expected})") from None
    return obs, frame


def catalogue_starts(path: str, frame) -> dict:
    """Clump starting guesses from a catalogue (ECSV/CSV/FITS table): positions as x_pix/y_pix
    (first observation, 0-based), ra_deg/dec_deg or theta1_arcsec/theta2_arcsec; optional
    re_arcsec. Returns {"phi": [N, 2], "re_arcsec": [N]}."""
    from astropy.table import Table
    if not Path(path).is_file():
        raise ConfigError("fit.clumps", path, '"auto", "none" or an existing catalogue file')
    try:
        t = Table.read(path, format="ascii.csv" if path.endswith(".csv") else None)
    except Exception as exc:
        raise ConfigError("fit.clumps", path, f"a readable table (ECSV, CSV, FITS): {exc}") from None
    cols = set(t.colnames)
    if {"x_pix", "y_pix"} <= cols:
        phi = frame.phi_of_pixel(np.stack([np.asarray(t["x_pix"], float),
                                           np.asarray(t["y_pix"], float)], -1), 0)
    elif {"ra_deg", "dec_deg"} <= cols:
        phi = frame.phi_of_radec(np.asarray(t["ra_deg"], float), np.asarray(t["dec_deg"], float))
    elif {"theta1_arcsec", "theta2_arcsec"} <= cols:
        phi = frame.phi_of_theta(np.stack([np.asarray(t["theta1_arcsec"], float),
                                           np.asarray(t["theta2_arcsec"], float)], -1))
    else:
        raise ConfigError("fit.clumps", path, "columns x_pix, y_pix or ra_deg, dec_deg or "
                          f"theta1_arcsec, theta2_arcsec (it has {sorted(cols)})")
    if not np.all(np.isfinite(phi)):
        raise ConfigError("fit.clumps", path, "finite clump positions")
    re = np.asarray(t["re_arcsec"], float) if "re_arcsec" in cols else np.full(len(t), np.nan)
    return {"phi": np.asarray(phi, float).reshape(-1, 2), "re_arcsec": re}


def auto_starts(observations, frame, scene):
    """Clumps found and counted in the data by `inference.auto.fit_without_truth` (its seeding,
    criterion and multi-start), on this module's model of the data's pixels; its clumps then
    start the joint fit here, which gives the reported answers. Returns (the starts, None
    without clumps; the counting's steps, `AutoFit.steps`: what summary.json's "counting"
    lists)."""
    import dataclasses

    from ..inference.auto import AutoOptions, fit_without_truth
    from .fit import host_re_bounds, make_model_factory
    opts = scene.fit
    if opts.max_clumps == 0:
        return None, []
    # no Fisher errors there: only the optimum is used, the joint fit below gives the errors;
    # merge and shape moves only for elliptical clumps, whose q and PA the joint fit then
    # starts from: started at q = 1 (its bound, where PA has no gradient), 17 of 19 clumps
    # of the elliptical pulls mocks stayed round (benchmarks/results/pulls_ell_elliptical.md)
    # a looser tolerance (AUTO_RTOL): the joint fit refits every parameter from this optimum;
    # and for the same reason one final start, unperturbed (`AutoOptions.final_starts`)
    wanted = dict(max_clumps=opts.max_clumps, re_max_arcsec=opts.clump_re_max_arcsec,
                  clump_n=opts.clump_n, seed=scene.seed, max_steps=opts.max_steps, errors=False,
                  final_starts=1, merge=opts.clump_shape == "elliptical", rtol=AUTO_RTOL,
                  diffuse_spacing_arcsec=opts.diffuse_spacing_arcsec,
                  host_re_range_arcsec=None if opts.diffuse_spacing_arcsec is None
                  else host_re_bounds(frame, opts.diffuse_spacing_arcsec),
                  host=opts.host == "sersic")
    names = {f.name for f in dataclasses.fields(AutoOptions)}
    auto = fit_without_truth(make_model_factory(observations, frame, opts),
                             # with a noise model, σ² from the data (rms² + max(d, 0)/t): its
                             # rms² alone would turn every bright knot into a clump
                             [o.data for o in observations],
                             [o.variance_for(np.where(o.mask, o.data, 0.0)) for o in observations],
                             [o.mask for o in observations],
                             zeropoints_ab={o.name: o.zeropoint_ab for o in observations},
                             options=AutoOptions(**{k: v for k, v in wanted.items() if k in names}))
    cl = auto.state.source.clumps
    if cl is None or cl.count == 0:
        return None, auto.steps
    # the whole optimum of the counting fit starts the joint fit: host, background and fluxes
    # too, so fit_observations skips its host-only stage (one compile and one fit fewer); its
    # model and clump capacity draw the joint fit's images (their program is compiled)
    return {"phi": np.asarray(cl.center_arcsec, float), "re_arcsec": np.asarray(cl.re_arcsec, float),
            "flux": np.asarray(cl.flux, float), "q": np.asarray(cl.q, float),
            "pa_rad": np.asarray(cl.pa_rad, float), "host": auto.state.source.bulge,
            "background": np.asarray(auto.state.background_counts_per_s, float),
            "render": (auto.model, int(auto.param.template.source.clumps.count))}, auto.steps


def fit_observation_scene(scene, out_dir=None, *, progress=None):
    """Fit a scene with [[observations]] (a path or an ObservationScene); write the files to
    out_dir (None: nothing written). Returns (fit, table, host, files)."""
    if not isinstance(scene, ObservationScene):
        scene = load_observation_scene(str(scene))
    t0 = time.perf_counter()
    obs, frame = read_scene_data(scene)
    if scene.fit.diffuse_spacing_arcsec is not None:   # before anything compiles
        require_spacing(scene.fit.diffuse_spacing_arcsec, [g.pixel_arcsec for g in frame.grids],
                        "fit.diffuse_spacing_arcsec")
    lens = place_lens(scene, frame)
    read_s = time.perf_counter() - t0
    opts = scene.fit
    starts, counting = None, None
    if opts.clumps == "auto":
        if progress:    # the longest stage: say so before it starts
            progress(f"read {len(obs)} bands in {read_s:.1f} s; finding and counting clumps "
                     f"(auto, up to {opts.max_clumps})")
        starts, counting = auto_starts(obs, frame, scene)
        if progress:
            progress(f"auto: {0 if starts is None else len(starts['phi'])} clumps in "
                     f"{time.perf_counter() - t0 - read_s:.1f} s; joint fit")
    elif opts.clumps != "none":
        starts = catalogue_starts(opts.clumps, frame)
    starts_s = time.perf_counter() - t0 - read_s
    if progress and opts.clumps != "auto":
        progress(f"read {len(obs)} bands in {read_s:.1f} s; fitting")
    fit = fit_observations(obs, frame, opts, starts)
    fit.timings_s["read"] = round(read_s, 3)
    fit.timings_s["clump_starts" if opts.clumps != "auto" else "auto"] = round(starts_s, 3)
    sampled = None
    if opts.method != "map":
        if progress:
            progress(f"joint fit: {fit.n_clumps} clumps, {len(fit.param.labels)} parameters; "
                     f"sampling the posterior ({opts.method}, {opts.sampler_warmup} warmup + "
                     f"{opts.sampler_samples} draws)")
        from .sample import sample_observed_fit
        sampled = sample_observed_fit(fit, opts.method, opts, scene.seed, progress)
        fit = sampled.fit
        if progress:
            progress(sampled.describe())
    fit.timings_s["command_total"] = round(time.perf_counter() - t0, 3)
    from ..inference.auto import host_alternatives
    table = clump_rows(fit, obs, frame, scene, lens, host_alternatives(counting or []))
    host = host_summary(fit, obs, frame)
    files = []
    if out_dir is not None:
        from .outputs import write_all
        # the counting's steps (clump added, removed, host moves; Δ ln L, criterion,
        # χ²/dof), so that a user sees why a clump is in or out (issue 18)
        extra = {} if counting is None else {"counting": counting}
        table.meta["errors"] = "fisher" if sampled is None else f"posterior ({opts.method})"
        if sampled is not None:
            extra["sampler"] = sampled.summary
        if "source_id" in table.colnames:   # images of one source clump, their colours
            from .multiple_images import image_groups
            extra["multiple_images"] = image_groups(table, [o.name for o in obs])
        files = write_all(out_dir, scene, obs, frame, fit, table, host, extra=extra, lens=lens)
        if sampled is not None:
            from ..inference.run import write_chains
            files.append(write_chains(Path(out_dir) / "chains.npz", sampled.chains))
    return fit, table, host, files
