"""The fit of observed bands: a smooth host and clumps, jointly, in every band, on the data's pixels.

    fit_observations(observations, frame, options, clump_starts=None) -> ObservedFit

1. the model: `model.build_model` on each band's own `Grid` (frame.py), PSF per
   band, no lens (the fit is in the image plane; a local lens maps the answers
   to the source plane afterwards, answers.py). It is built from a template whose
   clumps have the largest R_e the fit may reach (`clump_re_max_arcsec`) and whose
   host has the smallest axis ratio, so stamps and exact strips cover every value
   the bounded transforms allow: a clump that grows is never truncated.
2. starts, never from any truth: the host from the light's moments (centre,
   second moments → R_e, q, PA; total flux per band), n = 1; clumps from
   `clump_starts` (φ positions, optional R_e) with fluxes from the residual of the
   host-only fit in a 5 × 5-pixel box. When `clump_starts` carries a fitted "host"
   (and "flux", "background": the auto fit's optimum) the joint fit starts there and
   the host-only stage is skipped; its "render" (model, clump capacity) then draws the
   final images with a program compiled already (`_chi2`).
3. stage "host": host + background by Levenberg–Marquardt (lm.py); stage "joint":
   host, clumps (flux per band, centre, R_e [, q, PA]) and background together. With
   a noise model, σ² = rms² + μ/t is refreshed from the model and the joint fit
   rerun once.
4. errors: the Fisher matrix in physical parameters at the optimum, from the
   solver's last Jacobian (no further compile).

Clump fluxes are linear (identity transform: they may go negative, so a band
where a clump is not detected gives an unbiased flux and an honest upper limit);
host flux and sizes are positive (log / log-bounded), n, q bounded.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Optional

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from ..inference.likelihood import chi2_and_images, make_data
from ..inference.optimize import fit_map
from ..inference.params import Free, make_state, parametrize, take_rows
from ..inference.transforms import IDENTITY, LOG, Transform
from ..inference.uncertainty import Uncertainty, covariance_from_fisher_u, fisher_uncertainty
from ..model import Accuracy, Band, build_model
from ..source import Clumps, Sersic, Source
from ..inference.auto import CLUMP_Q_RANGE, SHAPE_START_Q, fit_clump_pixels
from ..inference.lm import lm_fit

HOST_N = (0.3, 8.0)          # host Sérsic index range
HOST_Q_MIN = 0.08            # thinnest host (an arc seen edge-on is thin)
CLUMP_Q_MIN = CLUMP_Q_RANGE[0]
POSITION_BOX_PIXELS = 3.0   # clump centres stay within this many finest pixels of their start
RESIDUAL_BOX = 2             # half-side (pixels) of the box whose residual starts a clump's flux


@dataclasses.dataclass
class ObservedFit:
    """What `fit_observations` returns (numpy where it is a result, JAX objects to re-render)."""

    model: object                 # SceneModel of the joint fit
    data: object                  # inference ImageData (final variances)
    param: object                 # Parametrization
    state: object                 # FitState at the optimum
    uncertainty: object           # Uncertainty (physical free parameters)
    images: tuple                 # model μ per band (numpy)
    success: bool
    steps: list                   # [{stage, n_steps, chi2, success, seconds}]
    timings_s: dict
    n_clumps: int
    # per clump, True where a sampler's chains did not mix (R̂ above sample.RHAT_MAX for one
    # of its parameters): flag bit 1, as a fit that did not converge; None after a MAP fit
    clump_unconverged: Optional[np.ndarray] = None
    # (model, clump capacity) of the counting whose compiled program draws the result
    # (`_chi2`), or None: `model` draws it
    render: Optional[tuple] = None

    def drawing(self):
        """(model, state) that draw this fit's light with a program compiled already."""
        return _drawing(self.model, self.state, self.render)


def bands_for(observations, frame) -> list:
    """`model.Band` per observation on the frame's pixel scales (exposure unused: no noise drawn)."""
    out = []
    for ob, g in zip(observations, frame.grids):
        psf = ob.psf
        out.append(Band(ob.name, pixel_arcsec=g.pixel_arcsec, exptime_s=1.0,
                        psf=None if psf is None else np.asarray(psf.array),
                        psf_pixel_arcsec=None if psf is None else psf.pixel_arcsec,
                        psf_effective=False if psf is None else psf.effective))
    return out


def host_start(observations, frame) -> Sersic:
    """A host Sérsic from the light's moments in the summed S/N image (no truth involved)."""
    g0 = frame.grids[0]
    snr = np.zeros(g0.shape)
    for k, ob in enumerate(observations):
        if ob.data.shape == g0.shape and frame.grids[k] == g0:
            snr += np.where(ob.mask, ob.data / np.sqrt(ob.variance), 0.0)
    if not np.any(snr):
        snr = np.where(observations[0].mask, observations[0].data, 0.0)
    w = np.where(snr > 2.0, snr, 0.0)
    if w.sum() <= 0:
        w = np.clip(snr, 0, None) + 1e-12
    y, x = np.mgrid[: g0.ny, : g0.nx]
    px, py = g0.x0_arcsec + x * g0.pixel_arcsec, g0.y0_arcsec + y * g0.pixel_arcsec
    W = w.sum()
    cx, cy = (w * px).sum() / W, (w * py).sum() / W
    ixx, iyy = (w * (px - cx) ** 2).sum() / W, (w * (py - cy) ** 2).sum() / W
    ixy = (w * (px - cx) * (py - cy)).sum() / W
    lam, vec = np.linalg.eigh(np.array([[ixx, ixy], [ixy, iyy]]))
    lam = np.maximum(lam, (0.5 * g0.pixel_arcsec) ** 2)
    re = float(np.clip(1.18 * np.sqrt(lam[1]), 1.5 * g0.pixel_arcsec,
                       0.25 * min(g0.nx, g0.ny) * g0.pixel_arcsec))
    q = float(np.clip(np.sqrt(lam[0] / lam[1]), 0.15, 1.0))
    pa = float(np.arctan2(vec[1, 1], vec[0, 1]))
    flux = [max(float(np.sum(ob.data[ob.mask])), 3.0 * float(np.sqrt(np.sum(ob.variance[ob.mask]))))
            for ob in observations]
    f = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
    return Sersic(flux=f(flux), re_arcsec=f(re), n=f(1.0), q=f(q), pa_rad=f(pa),
                  center_arcsec=f([cx, cy]))


def host_re_bounds(frame, diffuse_spacing_arcsec=None):
    """(lo, hi) of the host's R_e (arcsec): half a pixel to half the image's diagonal; with a
    diffuse light, at least its node spacing (a smaller host would draw the brightest clump,
    the diffuse light the rest of the arc)."""
    g0 = frame.grids[0]
    lo = 0.5 * min(g.pixel_arcsec for g in frame.grids)
    hi = 0.5 * np.hypot(*g0.shape) * g0.pixel_arcsec
    if diffuse_spacing_arcsec is not None:
        lo = max(lo, min(float(diffuse_spacing_arcsec), 0.5 * hi))
    return lo, hi


def host_within_bounds(host: Sersic, frame, options) -> Sersic:
    """A host start (e.g. the auto fit's, fitted under other bounds) moved just inside this
    fit's bounds: a bounded transform has no inverse on its edge."""
    lo, hi = host_re_bounds(frame, options.diffuse_spacing_arcsec)
    f = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
    inside = lambda v, a, b: f(np.clip(np.asarray(v, float), a + 1e-6 * (b - a), b - 1e-6 * (b - a)))  # noqa: E731
    flux = np.asarray(host.flux, float)     # positive here (log transform); free in auto
    return Sersic(flux=f(np.maximum(flux, 1e-6 * np.max(np.abs(flux)) + 1e-30)),
                  re_arcsec=inside(host.re_arcsec, lo, hi), n=inside(host.n, *HOST_N),
                  q=inside(host.q, HOST_Q_MIN, 1.0), pa_rad=f(host.pa_rad),
                  center_arcsec=f(host.center_arcsec))


def _clumps(centers, flux, re, options, q=None, pa_rad=None) -> Optional[Clumps]:
    """Round clumps, or elliptical ones (`options.clump_shape`) at q, pa_rad: the starts'
    (the automatic stage's shape moves) or, without them, q = SHAPE_START_Q and PA 0. q is
    kept just inside its bounds: a bounded transform has no inverse on its edge, and at
    q = 1 the PA has no gradient."""
    n = len(centers)
    if n == 0:
        return None
    f = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
    if options.clump_shape == "round":
        q, pa_rad = np.ones(n), np.zeros(n)
    else:
        q = np.clip(np.full(n, SHAPE_START_Q) if q is None else np.asarray(q, float),
                    CLUMP_Q_MIN + 1e-3, 1.0 - 1e-3)
        pa_rad = np.zeros(n) if pa_rad is None else np.asarray(pa_rad, float)
    return Clumps(center_arcsec=f(np.reshape(centers, (n, 2))), flux=f(flux), re_arcsec=f(re),
                  n=f(np.full(n, options.clump_n)), q=f(q), pa_rad=f(pa_rad))


def make_model_factory(observations, frame, options):
    """make_model(source) → SceneModel on the data's grids, stamps sized for the prior bounds;
    round n = 0.5 and n = 1 clumps drawn as Gaussian mixtures without stamps
    (`inference.auto.fit_clump_pixels`)."""
    bands = bands_for(observations, frame)
    acc = Accuracy(psf_oversampling=options.psf_oversampling, stamp_flux_fraction=0.999,
                   clump_pixels=fit_clump_pixels(options.clump_n, options.clump_shape == "round",
                                                 lensed=False))
    host_lo, host_hi = host_re_bounds(frame, options.diffuse_spacing_arcsec)

    def make_model(source: Source):
        tmpl = source
        if source.clumps is not None and source.clumps.count:
            c = source.clumps
            q_build = 1.0 if options.clump_shape == "round" else CLUMP_Q_MIN
            tmpl = eqx.tree_at(lambda s: (s.clumps.re_arcsec, s.clumps.q), tmpl,
                               (jnp.full_like(c.re_arcsec, options.clump_re_max_arcsec),
                                jnp.full_like(c.q, q_build)))
        if source.bulge is not None:
            tmpl = eqx.tree_at(lambda s: (s.bulge.q, s.bulge.re_arcsec), tmpl,
                               (jnp.asarray(HOST_Q_MIN, jnp.float64),
                                jnp.asarray(host_hi, jnp.float64)))
        return build_model(tmpl, bands, grids=frame.grids, accuracy=acc)

    return make_model


def free_parameters(source: Source, frame, options, *, clumps=True) -> dict:
    """The `free` mapping: host (flux, R_e, n, q, PA, centre), clumps, background."""
    lo, hi = host_re_bounds(frame, options.diffuse_spacing_arcsec)
    free = {}
    if source.bulge is not None:
        free.update({"bulge.flux": Free(True, LOG),
                     "bulge.re_arcsec": Free(True, Transform("log_bounded", lo, hi)),
                     "bulge.n": Free(True, Transform("bounded", *HOST_N)),
                     "bulge.q": Free(True, Transform("bounded", HOST_Q_MIN, 1.0)),
                     "bulge.pa_rad": True, "bulge.center_arcsec": True})
    if clumps and source.clumps is not None and source.clumps.count:
        # each centre within a box of ±POSITION_BOX_PIXELS finest pixels around its start: a
        # clump whose light the host takes over cannot wander off the image (seen in a mock)
        c = np.asarray(source.clumps.center_arcsec, float).ravel()
        box = POSITION_BOX_PIXELS * min(g.pixel_arcsec for g in frame.grids)
        free.update({"clumps.flux": Free(True, IDENTITY),
                     "clumps.center_arcsec": Free(True, Transform(
                         "bounded", tuple(float(v) for v in c - box),
                         tuple(float(v) for v in c + box))),
                     "clumps.re_arcsec": Free(True, Transform(
                         "log_bounded", options.clump_re_min_arcsec, options.clump_re_max_arcsec))})
        if options.clump_shape == "elliptical":
            free.update({"clumps.q": Free(True, Transform("bounded", CLUMP_Q_MIN, 1.0)),
                         "clumps.pa_rad": True})
    if options.background and options.diffuse_spacing_arcsec is None:   # else in the diffuse light
        free["background"] = True
    return free


def _padded(state, n_rows: int):
    """The state with its clumps padded to n_rows by copies of the first row with zero flux
    (dark: the same light)."""
    cl = state.source.clumps
    rows = take_rows(cl, np.r_[np.arange(cl.count), np.zeros(n_rows - cl.count, int)])
    flux = np.asarray(rows.flux).copy()
    flux[cl.count:] = 0.0
    return eqx.tree_at(lambda s: s.source.clumps, state,
                       eqx.tree_at(lambda c: c.flux, rows, jnp.asarray(flux)))


def _drawing(model, state, render):
    """(model, state): the counting's model with the state padded to its capacity by dark
    clumps where `render` (model, capacity) holds it (`_chi2`), else (model, state)."""
    if render is not None and state.source.clumps is not None and \
            0 < state.source.clumps.count <= render[1]:
        return render[0], _padded(state, render[1])
    return model, state


def _chi2(model, data, state, render=None):
    """(χ² per band, μ per band with the fitted diffuse light, numpy) from one compiled
    program (`likelihood.chi2_and_images`; op by op, ~260 one-op compiles). render: (model,
    clump capacity) of the automatic stage or None (`_drawing`): the counting's program
    is compiled already, and its model draws the same light (the same factory and bands)."""
    model, state = _drawing(model, state, render)
    chi2, images = chi2_and_images(model, data, state)
    return [float(c) for c in chi2], [np.asarray(m) for m in images]


def _data(model, observations, mu=None, diffuse_spacing_arcsec=None):
    var = [ob.variance_for(None if mu is None else mu[k]) for k, ob in enumerate(observations)]
    return make_data(model, [ob.data for ob in observations], var,
                     [ob.mask.astype(float) for ob in observations],
                     diffuse_spacing_arcsec=diffuse_spacing_arcsec)


class _StageResult(eqx.Module):
    state: object
    x: jnp.ndarray
    uncertainty: object


def _uncertainty_from_jacobian(param, u, jac):
    """`Uncertainty` of the physical free parameters at u from the whitened residuals'
    Jacobian in u there (`uncertainty.covariance_from_fisher_u`)."""
    x, dxdu = param.physical_and_slope(u)
    return Uncertainty(param.labels, x, covariance_from_fisher_u(jac.T @ jac, dxdu))


def run_stage(name, model, observations, source, free, steps, *, mu=None, background=None,
              max_steps=200, solver="lm", diffuse_spacing_arcsec=None, render=None):
    """One fit; appends a record to `steps`; returns (result, param, data, μ).

    solver: "lm" (lm.py: one Jacobian per step, errors from the last one) or
    "optimistix-lm" / "optimistix-bfgs" (then a Fisher matrix): compared in
    benchmarks/bench_optimizers.py. render: see `_chi2`."""
    t0 = time.perf_counter()
    c0 = time.process_time()
    data = _data(model, observations, mu, diffuse_spacing_arcsec)
    state0 = make_state(source, len(observations), background_counts_per_s=background)
    param = parametrize(state0, free)
    if solver == "lm":
        r = lm_fit(model, data, param, param.initial(), int(max_steps))
        unc = _uncertainty_from_jacobian(param, r.u, r.jacobian)
        res = _StageResult(param.state(r.u), unc.x, unc)
        n_steps, ok = int(r.n_steps), bool(r.success)
    else:
        method = {"optimistix": "lm", "optimistix-lm": "lm", "optimistix-bfgs": "bfgs"}[solver]
        m = fit_map(model, data, param, method=method, max_steps=max_steps, rtol=1e-6, atol=1e-6)
        res = _StageResult(m.state, m.x, fisher_uncertainty(model, param, m.x, data))
        n_steps, ok = int(m.n_steps), bool(m.success)
    chi2, mu = _chi2(model, data, res.state, render)
    steps.append(dict(stage=name, solver=solver, n_steps=n_steps, success=ok,
                      chi2=float(sum(chi2)), seconds=round(time.perf_counter() - t0, 3),
                      cpu_seconds=round(time.process_time() - c0, 3)))
    return res, param, data, mu


def _clump_fluxes(observations, frame, centers, mu):
    """Start fluxes [N, B]: the residual (data − host model) summed in a box around each clump."""
    out = np.zeros((len(centers), len(observations)))
    for k, ob in enumerate(observations):
        r = np.where(ob.mask, ob.data - mu[k], 0.0)
        xy = np.rint(frame.pixel_of(np.asarray(centers), k)).astype(int)
        for i, (x, y) in enumerate(xy):
            b = RESIDUAL_BOX
            box = r[max(y - b, 0): y + b + 1, max(x - b, 0): x + b + 1]
            noise = np.sqrt(np.sum(ob.variance[max(y - b, 0): y + b + 1, max(x - b, 0): x + b + 1]))
            out[i, k] = max(float(box.sum()), float(noise)) if box.size else float(noise)
    return out


def fit_observations(observations, frame, options, clump_starts=None, *, solver="lm") -> ObservedFit:
    """Fit host + clumps to the observations (see the module doc). clump_starts: dict with
    "phi" [N, 2] (fit-frame arcsec) and optional "re_arcsec", "q", "pa_rad" [N] (`auto_starts`
    adds the counting's fluxes, host, background and model), or None for none."""
    t_start, c_start = time.perf_counter(), time.process_time()
    timings, steps = {}, []
    make_model = make_model_factory(observations, frame, options)
    host = host_start(observations, frame) if options.host == "sersic" else None
    if host is not None and options.diffuse_spacing_arcsec is not None:   # R_e bounded below
        host = host_within_bounds(host, frame, options)
    nb = len(observations)
    bg = np.zeros(nb)
    mu = None
    warm = clump_starts is not None and clump_starts.get("host") is not None and host is not None
    if warm:    # a host already fitted with these clumps (auto): no host-only stage
        host = host_within_bounds(clump_starts["host"], frame, options)
        bg = np.asarray(clump_starts.get("background", bg), float)
    elif host is not None:
        t0 = time.perf_counter()
        src = Source(bulge=host)
        model = make_model(src)
        timings["build_host_model"] = time.perf_counter() - t0
        res, param, data, mu = run_stage("host", model, observations, src,
                                         free_parameters(src, frame, options), steps,
                                         max_steps=options.max_steps, solver=solver,
                                         diffuse_spacing_arcsec=options.diffuse_spacing_arcsec)
        host = res.state.source.bulge
        bg = np.asarray(res.state.background_counts_per_s)
    n = 0 if clump_starts is None else len(clump_starts["phi"])
    if host is None and n == 0:
        raise ConfigError("fit", "host = \"none\" and no clumps", "something to fit")
    if mu is None:
        mu = [np.zeros(ob.data.shape) for ob in observations]
    if n:
        phi = np.asarray(clump_starts["phi"], float).reshape(n, 2)
        re0 = np.asarray(clump_starts.get("re_arcsec", np.full(n, np.nan)), float)
        pix = min(g.pixel_arcsec for g in frame.grids)
        re0 = np.where(np.isfinite(re0), re0, pix)
        re0 = np.clip(re0, options.clump_re_min_arcsec * 1.01, options.clump_re_max_arcsec * 0.99)
        flux0 = (np.asarray(clump_starts["flux"], float).reshape(n, nb)
                 if clump_starts.get("flux") is not None else _clump_fluxes(observations, frame, phi, mu))
        src = Source(bulge=host, clumps=_clumps(phi, flux0, re0, options, clump_starts.get("q"),
                                                clump_starts.get("pa_rad")))
    else:
        src = Source(bulge=host)
    t0 = time.perf_counter()
    model = make_model(src)
    timings["build_model"] = time.perf_counter() - t0
    free = free_parameters(src, frame, options)
    noise_model = any(ob.noise_exptime_s is not None for ob in observations)
    # the automatic stage's model and capacity: its compiled images program draws the result
    render = clump_starts.get("render") if warm else None
    res, param, data, mu_new = run_stage("joint", model, observations, src, free, steps,
                                         mu=mu if noise_model else None, background=bg,
                                         max_steps=options.max_steps, solver=solver,
                                         diffuse_spacing_arcsec=options.diffuse_spacing_arcsec,
                                         render=render)
    if noise_model:   # σ² from the fitted model, then once more
        res, param, data, mu_new = run_stage(
            "joint (variance from model)", model, observations, res.state.source, free, steps,
            mu=mu_new, background=res.state.background_counts_per_s, max_steps=options.max_steps,
            solver=solver, diffuse_spacing_arcsec=options.diffuse_spacing_arcsec, render=render)
    unc = res.uncertainty
    timings["total"] = time.perf_counter() - t_start
    timings["cpu_total"] = time.process_time() - c_start
    return ObservedFit(model, data, param, res.state, unc, tuple(mu_new),
                       all(s["success"] for s in steps), steps,
                       {k: round(v, 3) for k, v in timings.items()}, n, render=render)
