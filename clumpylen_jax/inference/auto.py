"""Fit clumps without knowing the answer: host first, clumps found, seeded and counted.

    fit_without_truth(make_model, data, variances, masks=None, *, host_start=None, lens=None,
                      zeropoints_ab=None, options=AutoOptions()) -> AutoFit

1. The smooth light: one Sérsic (or the components of `host_start`) and a background
   level per band, started from the data's moments (`seeding.host_from_moments`) and
   fitted alone (every clump slot inactive).
2. Candidates: peaks of the matched-filtered S/N of the residual in the stack of the
   finest-pixel bands, with aperture fluxes and moment sizes; through a lens, mapped to
   the source plane and merged when they are images of one clump (`seeding`).
3. Counting: at each step the `n_starts` best remaining candidates are each tried in the
   next free slot (vmapped Levenberg–Marquardt over the whole model, every active clump
   and the host free); the best is kept when the criterion accepts it, and candidates
   are found again in the new residual (a faint clump behind a bright one shows up only
   once the bright one is modelled). Stop at `max_clumps` or at the first rejection.
   Then clumps whose removal (without refit, which can only flatter them) the criterion
   would accept are removed. Merge and shape moves (`_refine`, `AutoOptions.merge`): each
   pair of clumps closer than MERGE_SEPARATION (R_e,i + R_e,j) is tried as one clump (flux
   summed, centre flux-weighted, ellipse from the pair's second moment) and each round
   clump as an elliptical one (where the renderer draws q and PA); the criterion decides.
   Then the final configuration is refitted from the counting's optimum, and from
   `final_starts` − 1 starts drawn about the optimum that refit finds, at 3 times its Fisher
   errors (best kept, spread reported: `_final`), where shape moves are made with every
   kept clump's q and PA free (`AutoOptions.final_shape`).
4. Errors from the Fisher matrix of the final fit; a catalogue row per clump with a
   `flag` (0 = fine; bits in `FLAGS`) and blend columns.

Criterion (`AutoOptions.criterion`), with k = B + 3 parameters per clump (fluxes, β, R_e;
B + 5 with q and PA) and n the number of fitted pixels:
- "bic": ΔBIC = k ln n − 2 Δln L; a clump is kept when ΔBIC < −threshold (default 0:
  BIC itself prefers it; its penalty is already a ≈ 7σ detection for 10⁴ pixels and
  4 parameters, so no extra margin is needed);
- "lr": likelihood ratio 2 Δln L > threshold (default 36: a 6σ single-parameter
  equivalent, above the ≈ 4.5σ highest noise peak of a 10⁴-pixel field).

No recompiles: the model has a fixed capacity of `max_clumps` slots (`capacity.py`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import Optional

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .. import profiles
from ..errors import require
from ..source import Clumps, Sersic, Source
from . import capacity, seeding
from .catalog import fit_table, host_meta
from .likelihood import chi2_and_images, make_data
from .params import (Free, FitState, Parametrization, entry_kinds, make_state, parametrize,
                     take_rows)
from .size_limits import re_upper_limits
from .transforms import Transform
from .uncertainty import Uncertainty, covariance_from_fisher_u

CRITERIA = ("bic", "lr")
DEFAULT_THRESHOLD = {"bic": 0.0, "lr": 36.0}
RE_MAX_PIXELS = 2.0        # default upper bound of clump R_e: 2 finest detector pixels
LOCAL_SLOTS = 3            # clumps free in a counting step: the new one and its 2 nearest
MERGE_SEPARATION = 3.0     # pairs tried as one clump: centres within 3 (R_e,i + R_e,j)
SHAPE_START_Q = 0.6        # axis ratio a shape move starts from
RE_MIN_FRACTION = 1e-3     # lower bound of clump R_e, as a fraction of the upper one
CLUMP_Q_RANGE = (0.2, 1.0)
HOST_N_RANGE = (0.3, 6.0)
# the final refit's perturbed starts get at most this many times the unperturbed start's LM
# steps (at least FINAL_MIN_STEPS): on a SIS mock they took 42–73 steps against its 17 and
# ended 488–908 lower in ln L (benchmarks/README.md)
FINAL_STEP_FACTOR = 2
FINAL_MIN_STEPS = 10
# the perturbed starts are drawn from N(u*, FINAL_START_SIGMA² Cov_u) about the unperturbed
# optimum u* (Cov_u from its JᵀJ: they probe its basin at the scale of its errors), each entry
# clipped to ±FINAL_START_MAX_U (a direction the data do not constrain has a huge variance).
# Perturbed by 0.1 in every entry instead, none came within Δln L 2 of it in a SIS mock
# (488–908 below), so the table's spread held one start only
FINAL_START_SIGMA = 3.0
FINAL_START_MAX_U = 0.1
LOG = logging.getLogger(__name__)
# the `flag` bits of fit.ecsv, for mock-image and observation fits alike; "size_unresolved":
# σ(R_e) > R_e, the data do not measure the size (a clump far below the PSF): the table's
# `re_arcsec_ul` bounds it (`size_limits`), and q and PA are unmeasured too
FLAGS = {"not_converged": 1, "re_at_bound": 2, "position_at_box_edge": 4,
         "unstable_across_starts": 8, "size_unresolved": 16, "shape_degenerate": 32,
         "host_alternative": 64}
# "host_alternative" (set by `observations.answers` from `host_alternatives`): a host move
# (`_rehost`) that the criterion rejected for its extra clump, not for its fit (ln L within
# ALTERNATIVE_DLNL of the kept one, or above it), gives this clump a flux more than
# ALTERNATIVE_SIGMA σ away, or none (its light the host's): the data allow the host's light
# and the clump's to be shared otherwise, a systematic error the Fisher σ does not hold
# (a JWST mock: magnitudes 10σ too bright, the host on a missed clump, benchmarks/
# results/observation_pulls_jwst_s0_11.md seed 4)
ALTERNATIVE_DLNL = 2.0
ALTERNATIVE_SIGMA = 2.0
# the cusp move (`_host_moves`): a clump of this share of the host's flux and this fraction
# of its R_e at its centre, the host's n back to the moments'
CUSP_FLUX_FRACTION = 0.3
CUSP_RE_FRACTION = 0.1
# "shape_degenerate": the profile of R_e (`_profile`) found the R_e error more than
# PROFILE_FLAG_RATIO times the Fisher one: R_e, q and PA trade off along a curved valley (one
# axis of the clump unresolved, e.g. across an arc), the R_e and flux errors are then the
# profile's and q and PA are unmeasured
# R_e held at f·R_e (f, start): the same orientation keeping the minor axis ("minor"), the same
# orientation from q = SHAPE_START_Q ("open": the minor axis free to grow; seed 2 of the SIS
# recovery had an equally good optimum at 1.15 R_e and twice the q, not reached from q/f), or
# the major axis turned by 90° so that the measured axis becomes the minor one ("turned")
PROFILE_TRIALS = ((1.15, "minor"), (1.15, "open"), (0.87, "minor"), (1.15, "turned"),
                  (1.35, "turned"))
PROFILE_FLAG_RATIO = 2.0
# LM steps of each profile refit: any point with R_e held gives `profile_sigma` a valid bound
# (ln L there is at most the profile's), converged or not, and a batch of refits runs as long
# as its slowest; in a SIS mock they took 4–45 steps, most under 16
PROFILE_MAX_STEPS = 15


@dataclasses.dataclass(frozen=True)
class AutoOptions:
    """Settings of `fit_without_truth` (the scene's [fit] table); defaults here only.

    max_clumps: capacity (slots compiled once) and the most clumps kept.
    criterion: "bic" or "lr" (module doc).  threshold: None: DEFAULT_THRESHOLD[criterion].
    n_starts: starts per step (candidates tried at once) and for the final refit.
    final_starts: starts of the final refit (the first unperturbed, the others perturbed),
        at most n_starts; None: n_starts. 1 suits a caller that refits the optimum with every
        parameter free and makes its own errors (`observations.run.auto_starts`): the
        perturbed starts serve the spread of the table (`errors`) and a better optimum,
        which on S1063 (15 clumps) they never gave (ln L 98–633 below the unperturbed one)
        while taking 4–9 times its steps: a third of the automatic stage.
    re_max_arcsec: upper bound of clump R_e (None: RE_MAX_PIXELS finest detector pixels).
    seed: of the final perturbed starts.  clump_n: Sérsic index of every clump (fixed).
    detect_snr: candidates are matched-filtered S/N peaks above it.
    rtol: Levenberg–Marquardt convergence of every fit here (`lm.py`: an accepted step gaining
        less than rtol·χ²). A caller that refits the optimum with every parameter free may
        take a looser one (`observations.run.AUTO_RTOL`): the steps that gain the last
        rtol·χ² are then made once, by that refit.
    max_steps: Levenberg–Marquardt steps per fit (trials that are rejected count too). 40 was
        too few: a clump started at R_e = 1 px that converges to 5 px needs 44 (it stopped
        16 in ln L short, flagged not converged); a fit that converges earlier stops there.
    fit_shape: also fit each clump's q and PA (else round: most clumps are unresolved, and
        q, PA of an unresolved clump are degenerate directions that slow every fit).
    round_clumps: the clumps are known to be round (a scene whose clumps' q_range is
        [1, 1]): no shape moves, and unlensed the separable round renderers
        (`fit_clump_pixels`), 3-4 times faster. Else clumps are counted round and the
        shape moves try each one elliptical: fitted round, an unlensed clump of q 0.5-0.7
        came back with an R_e between its major axis and its circularised one, 7 of 46 R_e
        pulls beyond 3 (unlensed seeds 0-7), none with the shape moves
        (benchmarks/results/unl5_round.md, unl5_shapes.md).
    errors: Fisher errors and the catalogue table of the final fit. False: AutoFit.uncertainty
        and .table None, for a caller that refits from the optimum and makes its own
        (`observations.run.auto_starts`): one compiled program of the whole model fewer.
    merge: after pruning, the merge and shape moves (`_refine`): close pairs tried as one
        clump, round clumps tried elliptical (where the renderer draws q and PA: a lensed
        fit, or clump_pixels "sersic"), each kept by the criterion.
    final_shape: where shape moves are made (merge on, a renderer that draws q and PA), the
        final refit frees every kept clump's q and PA, a round one started from its best
        shape trial: R_e (of the major axis), q and PA are then reported with errors
        marginalised over the shape. A round clump's R_e error holds the shape fixed: for
        elliptical clumps seen through a lens it was several times too small
        (benchmarks/results/recovery_final_shape.md).
    profile_errors: where shapes are fitted, the R_e and flux errors of each kept clump are
        at least the profile-likelihood bound from refits with its R_e held at other values
        (`_profile`, `profile_sigma`): the Fisher errors assume a quadratic ln L, which fails
        when one axis is unresolved (issue 18: R_e errors 7–13 times too small).
    diffuse_spacing_arcsec: a smooth diffuse light per band on B-spline nodes this far apart,
        profiled out of every fit (diffuse.py): the part of an arc or ring that a Sérsic host
        cannot draw, which the counting would otherwise fill with clumps. It contains the
        background level, which is then not a parameter. None: no diffuse light.
    host_re_range_arcsec: (lo, hi) bounds of the host's R_e, or None (free, log). With a
        diffuse light, a host smaller than its nodes would take the brightest clump
        (seen on a mock arc): `observations` bounds it below by the node spacing.
    host: fit a smooth Sérsic host (from the moments, or `host_start`). False: none (an arc
        whose smooth light is the diffuse light alone; a cuspy Sérsic beside it drew the
        brightest clump of a mock arc).
    """

    max_clumps: int = 20
    criterion: str = "bic"
    threshold: Optional[float] = None
    n_starts: int = 4
    final_starts: Optional[int] = None
    re_max_arcsec: Optional[float] = None
    seed: int = 0
    clump_n: float = 0.5
    detect_snr: float = 4.0
    rtol: float = 1e-6
    max_steps: int = 100
    fit_shape: bool = False
    round_clumps: bool = False
    errors: bool = True
    merge: bool = True
    final_shape: bool = True
    profile_errors: bool = True
    diffuse_spacing_arcsec: Optional[float] = None
    host_re_range_arcsec: Optional[tuple] = None
    host: bool = True

    def validate(self) -> "AutoOptions":
        require(isinstance(self.max_clumps, (int, np.integer)) and 1 <= self.max_clumps <= 1000,
                "fit.max_clumps", self.max_clumps, "an integer in [1, 1000]")
        require(self.criterion in CRITERIA, "fit.criterion", self.criterion, '"bic" or "lr"')
        require(self.threshold is None or np.isfinite(self.threshold), "fit.threshold",
                self.threshold, "a finite number")
        require(isinstance(self.n_starts, (int, np.integer)) and 1 <= self.n_starts <= 64,
                "fit.n_starts", self.n_starts, "an integer in [1, 64]")
        require(self.final_starts is None or (isinstance(self.final_starts, (int, np.integer))
                                              and 1 <= self.final_starts <= self.n_starts),
                "fit.final_starts", self.final_starts, f"an integer in [1, n_starts = {self.n_starts}]")
        require(self.re_max_arcsec is None or (np.isfinite(self.re_max_arcsec)
                                               and self.re_max_arcsec > 0),
                "fit.re_max_arcsec", self.re_max_arcsec, "a radius > 0 arcsec")
        require(0.2 <= self.clump_n <= 10, "fit.clump_n", self.clump_n, "a Sérsic index in [0.2, 10]")
        require(self.detect_snr > 0, "fit.detect_snr", self.detect_snr, "a S/N > 0")
        require(np.isfinite(self.rtol) and 0 < self.rtol < 1, "fit.rtol", self.rtol,
                "a relative χ² gain in (0, 1)")
        require(isinstance(self.max_steps, (int, np.integer)) and self.max_steps >= 1,
                "fit.max_steps", self.max_steps, "an integer ≥ 1")
        require(isinstance(self.merge, (bool, np.bool_)), "fit.merge", self.merge, "true or false")
        require(isinstance(self.final_shape, (bool, np.bool_)), "fit.final_shape",
                self.final_shape, "true or false")
        require(isinstance(self.round_clumps, (bool, np.bool_)), "fit.round_clumps",
                self.round_clumps, "true or false")
        require(isinstance(self.profile_errors, (bool, np.bool_)), "fit.profile_errors",
                self.profile_errors, "true or false")
        require(self.diffuse_spacing_arcsec is None or (np.isfinite(self.diffuse_spacing_arcsec)
                                                         and self.diffuse_spacing_arcsec > 0),
                "fit.diffuse_spacing_arcsec", self.diffuse_spacing_arcsec, "a spacing > 0 arcsec")
        r = self.host_re_range_arcsec
        require(r is None or (len(r) == 2 and np.all(np.isfinite(r)) and 0 < r[0] < r[1]),
                "fit.host_re_range_arcsec", r, "(lo, hi) arcsec with 0 < lo < hi")
        require(isinstance(self.host, (bool, np.bool_)), "fit.host", self.host, "true or false")
        return self

    @property
    def resolved_threshold(self) -> float:
        return DEFAULT_THRESHOLD[self.criterion] if self.threshold is None else float(self.threshold)


@dataclasses.dataclass
class AutoFit:
    """What `fit_without_truth` returns.

    state: the FitState with the kept clumps only.  param: the fixed-capacity
    Parametrization (every slot).  u, active: its optimum and mask.  uncertainty: Fisher
    errors of the free entries of kept clumps, host and background.  table: `fit_table`
    columns + flag, n_images, blend_corr, blend_with, spread columns (both None when
    `AutoOptions.errors` is False).  steps: one dict per
    step.  model: the SceneModel.  log_likelihood, success: of the final fit.
    """

    state: FitState
    param: Parametrization
    uncertainty: Uncertainty
    table: object
    steps: list
    model: object
    u: np.ndarray
    active: np.ndarray
    log_likelihood: float
    success: bool


# ---------------------------------------------------------------------------- set-up


def _host_source(host_start, moments, nb, re_range=None):
    if host_start is not None:
        require(host_start.bulge is not None or host_start.disk is not None, "host_start",
                "no bulge or disk", "a Source with the smooth component(s)")
        return Source(bulge=host_start.bulge, disk=host_start.disk)
    m = moments
    re = float(m["re_arcsec"])
    if re_range is not None:   # strictly inside: a bounded transform has no inverse on its edge
        lo, hi = re_range
        re = float(np.clip(re, lo + 1e-3 * (hi - lo), hi - 1e-3 * (hi - lo)))
    return Source(bulge=Sersic(jnp.asarray(m["flux"], float).reshape(nb), jnp.asarray(re),
                               jnp.asarray(m["n"]), jnp.asarray(m["q"]), jnp.asarray(m["pa_rad"]),
                               jnp.asarray(m["center_arcsec"], float)))


def _with_slots(host: Source, cap: int, nb: int, re_max: float, clump_n: float, center):
    """host + `cap` clump slots at the largest R_e (stamps sized for the prior range)."""
    cl = Clumps(jnp.tile(jnp.asarray(center, float)[None], (cap, 1)), jnp.full((cap, nb), 1e-6),
                jnp.full(cap, re_max), jnp.full(cap, clump_n), jnp.ones(cap), jnp.zeros(cap))
    return Source(bulge=host.bulge, disk=host.disk, clumps=cl)


def _host_free(source: Source, box_lo, box_hi, re_range=None):
    free = {}
    for name, comp in (("bulge", source.bulge),
                       ("disk.sersic", None if source.disk is None else source.disk.sersic)):
        if comp is None:
            continue
        free[f"{name}.flux"] = True
        free[f"{name}.re_arcsec"] = True if re_range is None else \
            Free(True, Transform("log_bounded", *re_range))
        free[f"{name}.n"] = Free(True, Transform("bounded", *HOST_N_RANGE))
        free[f"{name}.q"] = Free(True, Transform("bounded", *CLUMP_Q_RANGE))
        free[f"{name}.pa_rad"] = True
        free[f"{name}.center_arcsec"] = Free(True, Transform("bounded", box_lo, box_hi))
    return free


def _free(source: Source, re_lo, re_hi, box_lo, box_hi, shape_free: bool, background: bool,
          host_re_range=None):
    """Free entries; shape_free: every clump's q and PA in the parametrization (fitted for all
    with fit_shape; for the shape moves, only those of a clump made elliptical); background:
    a level per band (not with a diffuse light, whose span holds it)."""
    free = _host_free(source, box_lo, box_hi, host_re_range)
    free.update({"clumps.flux": True,
                 "clumps.center_arcsec": Free(True, Transform("bounded", box_lo, box_hi)),
                 "clumps.re_arcsec": Free(True, Transform("log_bounded", re_lo, re_hi))})
    if shape_free:
        free.update({"clumps.q": Free(True, Transform("bounded", *CLUMP_Q_RANGE)),
                     "clumps.pa_rad": True})
    if background:
        free["background"] = True
    return free


def _box(model, lens, host: Source, pad_arcsec):
    """Square (lo, hi) bounding clump and host centres: the field's (source-plane) extent."""
    pts = []
    for k in range(len(model.layouts)):
        b1, b2, _ = seeding.pixel_betas(model, k, lens)
        pts.append(np.c_[b1.ravel(), b2.ravel()])
    pts = np.concatenate(pts)
    lo = float(pts.min()) - pad_arcsec
    hi = float(pts.max()) + pad_arcsec
    return lo, hi


def _criterion(opts: AutoOptions, delta_lnl: float, k: int, n_pix: int):
    """(value, accepted) of adding k parameters that raise ln L by delta_lnl."""
    if opts.criterion == "bic":
        v = k * np.log(n_pix) - 2.0 * delta_lnl
        return float(v), bool(v < -opts.resolved_threshold)
    v = 2.0 * delta_lnl
    return float(v), bool(v > opts.resolved_threshold)


@dataclasses.dataclass
class _Ctx:
    """What every step shares (made once by `_setup`)."""

    model: object
    data: object
    param: Parametrization
    opts: AutoOptions
    lens: object
    variances: list
    masks: list
    n_pix: int
    k_clump: int
    n_host: int
    psf_sigma: np.ndarray
    re_bounds: tuple
    host_index: np.ndarray     # entries of u that are not clumps' (host, background)
    slot_index: np.ndarray     # [capacity, k_clump]: entries of u of each clump slot
    shape_index: Optional[np.ndarray] = None   # [capacity, 2]: q, PA entries (shape moves)
    shaped: Optional[np.ndarray] = None        # bool [capacity]: q, PA fitted for this slot

    @property
    def cap(self):
        return self.opts.max_clumps


def _setup(make_model, data, variances, masks, host_start, lens, opts: AutoOptions):
    nb = len(data)
    require(nb >= 1 and len(variances) == nb, "variances", len(variances),
            f"one variance map per image ({nb})")
    data = [np.asarray(d, float) for d in data]
    variances = [np.asarray(v, float) for v in variances]
    masks = ([np.isfinite(d) & np.isfinite(v) & (v > 0) for d, v in zip(data, variances)]
             if masks is None else [np.asarray(m, bool) & np.isfinite(d) for m, d in zip(masks, data)])
    for k, (d, v, m) in enumerate(zip(data, variances, masks)):
        require(d.shape == v.shape == m.shape, f"variances[{k}] / masks[{k}] (shape)",
                (v.shape, m.shape), f"the image's shape {d.shape}")
    masks = [m.astype(float) for m in masks]
    variances = [np.where(m > 0, v, 1.0) for v, m in zip(variances, masks)]
    data = [np.where(m > 0, d, 0.0) for d, m in zip(data, masks)]
    # a probe model (host only, capacity 1) gives the grids, PSFs and the host moments
    # (a lensed probe's host must land in the field: host_start, or one wide enough for any)
    probe_src = Source(bulge=host_start.bulge, disk=host_start.disk) if host_start is not None \
        else Source(bulge=Sersic(jnp.ones(nb), jnp.asarray(0.1 if lens is None else 100.0),
                                 jnp.asarray(1.0), jnp.asarray(1.0), jnp.asarray(0.0), jnp.zeros(2)))
    grids = _probe_grids(make_model, probe_src, data)
    pix = min(g.pixel_arcsec for g in grids)
    re_hi = float(opts.re_max_arcsec or RE_MAX_PIXELS * pix)
    re_lo = RE_MIN_FRACTION * re_hi
    moments, sky = seeding.host_from_moments(_GridsOnly(grids), data, variances, masks, lens)
    host = _host_source(host_start, moments, nb, opts.host_re_range_arcsec) if opts.host \
        else Source()
    center = np.asarray(moments["center_arcsec"] if not opts.host
                        else (host.bulge or host.disk.sersic).center_arcsec, float)
    src = _with_slots(host, opts.max_clumps, nb, re_hi, opts.clump_n, center)
    model = make_model(src)
    require(tuple(model.band_names) and len(model.layouts) == nb, "make_model", len(model.layouts),
            f"a SceneModel with {nb} bands in the order of the data")
    lo, hi = _box(model, lens, host, 2 * re_hi)
    state = make_state(src, nb, background_counts_per_s=sky - np.array(
        [lay.sky_counts_per_s for lay in model.layouts]))
    shape_moves = _shape_moves(model, opts)
    param = parametrize(state, _free(src, re_lo, re_hi, lo, hi, opts.fit_shape or shape_moves,
                                     background=opts.diffuse_spacing_arcsec is None,
                                     host_re_range=opts.host_re_range_arcsec))
    idata = make_data(model, data, variances, masks, kind="gaussian",
                      diffuse_spacing_arcsec=opts.diffuse_spacing_arcsec)
    k_clump = nb + (5 if opts.fit_shape else 3)
    host_index, slot_index, shape_index = _index_tables(param, opts.max_clumps,
                                                        split_shape=shape_moves)
    ctx = _Ctx(model, idata, param, opts, lens, variances, masks, idata.n_pixels, k_clump,
               int(host_index.size), capacity.psf_sigma_pixels(model), (re_lo, re_hi),
               host_index, slot_index, shape_index, np.zeros(opts.max_clumps, bool))
    return ctx, param.initial()


def _shape_moves(model, opts: AutoOptions) -> bool:
    """Whether `_refine` may make a round clump elliptical: merges on, clumps otherwise round
    but not known to be, and a renderer that draws q and PA (the separable round ones do not)."""
    return bool(opts.merge and not opts.fit_shape and not opts.round_clumps
                and getattr(model.accuracy, "clump_pixels", "sersic") == "sersic")


def _index_tables(param: Parametrization, cap: int, split_shape: bool = False):
    """(entries of u outside the clumps, [cap, k] entries of each clump slot, [cap, 2] q and PA
    entries of each slot or None). split_shape: q and PA are kept out of the [cap, k] table
    (held unless a shape move frees them); else they are in it when free."""
    host, slots, shape, start = [], [[] for _ in range(cap)], [[] for _ in range(cap)], 0
    for leaf in param.leaves:
        pos = start + np.arange(leaf.size)
        if leaf.path.startswith("clumps."):
            per_row = int(np.prod(leaf.shape[1:])) if len(leaf.shape) > 1 else 1
            table = shape if split_shape and leaf.path in ("clumps.q", "clumps.pa_rad") else slots
            for p, i in zip(pos, leaf.index):
                table[i // per_row].append(int(p))
        else:
            host.extend(int(p) for p in pos)
        start += leaf.size
    return (np.asarray(host, int), np.asarray(slots, int),
            np.asarray(shape, int) if split_shape else None)


@dataclasses.dataclass
class _GridsOnly:
    """Stands in for a model where only the detector grids are read (before the model exists)."""

    grids: list

    @property
    def layouts(self):
        return [dataclasses.make_dataclass("L", ["grid"])(g) for g in self.grids]


def _probe_grids(make_model, probe_src, data):
    """Detector grids of the scene model (a host-only build: cheap, no clumps)."""
    model = make_model(probe_src)
    grids = [lay.grid for lay in model.layouts]
    require(len(grids) == len(data), "make_model", len(grids),
            f"a SceneModel with one band per image ({len(data)})")
    for k, (g, d) in enumerate(zip(grids, data)):
        require(tuple(g.shape) == d.shape, f"data[{k}] (shape)", d.shape,
                f"the model's detector grid {tuple(g.shape)} (set the field of make_model)")
    return grids


# ---------------------------------------------------------------------------- steps


def _step_limits(ctx: _Ctx, m: int, max_steps=None):
    """LM steps of each start of the compiled batch: max_steps (default the options') for the
    m real starts, 0 for the padding (a counting step with fewer candidates than n_starts
    solves only those)."""
    n = int(ctx.opts.max_steps if max_steps is None else max_steps)
    return jnp.asarray(np.where(np.arange(ctx.opts.n_starts) < m, n, 0), jnp.int32)


def _solve_layout(ctx: _Ctx, slots, shaped=None):
    """(entries, rows) of a local solve in `capacity.solve_local_batch`'s layout: host and
    background entries, then for each row of `slots`, padded with the row ctx.cap to a
    whole number of LOCAL_SLOTS chunks over the capacity, its flux, β and R_e entries and,
    where shape moves are on, its q and PA (freed where shaped[slot], default ctx.shaped);
    u.size marks an entry held or padding. The same shapes for every solve: one program."""
    shaped = ctx.shaped if shaped is None else shaped
    n_rows = -(-ctx.cap // LOCAL_SLOTS) * LOCAL_SLOTS
    rows = np.full(n_rows, ctx.cap)
    rows[:len(slots)] = slots
    none = ctx.param.size
    parts = [ctx.host_index]
    for i in rows:
        parts.append(ctx.slot_index[i] if i < ctx.cap else np.full(ctx.slot_index.shape[1], none))
        if ctx.shape_index is not None:
            parts.append(ctx.shape_index[i] if i < ctx.cap and shaped[i] else np.full(2, none))
    return np.concatenate(parts), rows


def _fit_local(ctx: _Ctx, us, slot_sets, actives, shaped_sets=None, held_sets=None,
               normal=False, max_steps=None):
    """LM over host, background and the clump slots slot_sets[s] of each start only (their
    q, PA too where shaped_sets[s][slot]; default ctx.shaped): `_solve_layout`. held_sets[s]:
    entries of u held at their start values in start s (same program: marked as padding).
    normal: also return each start's JᵀJ at its optimum [m, K, K] and the entries of u it
    is over [m, K] (u.size: padding or held). max_steps: LM steps per start (default the
    options')."""
    s = ctx.opts.n_starts
    us, actives = np.asarray(us), np.asarray(actives, float)
    idxs, slots = (np.stack(a) for a in zip(*(_solve_layout(ctx, sl, shaped) for sl, shaped in
                                              zip(slot_sets, shaped_sets or [None] * len(slot_sets)))))
    for k, held in enumerate(held_sets or []):
        idxs[k][np.isin(idxs[k], np.asarray(held, int))] = ctx.param.size
    m = us.shape[0]
    pad = np.arange(s) % m
    t0 = time.perf_counter()
    out, lnl, ok, steps, jtj = capacity.solve_local_batch(
        ctx.model, ctx.data, ctx.param, jnp.asarray(us[pad]), jnp.asarray(idxs[pad]),
        jnp.asarray(slots[pad]), jnp.asarray(actives[pad]), ctx.opts.rtol, _step_limits(ctx, m, max_steps),
        int(ctx.host_index.size), LOCAL_SLOTS, _layout_kinds(ctx))
    lnl = np.where(np.isfinite(np.asarray(lnl)), np.asarray(lnl), -np.inf)
    LOG.info("local fit of %d start(s), %d clump(s): %.2f s, ln L %s, steps %s", m,
             int(actives[0].sum()), time.perf_counter() - t0, np.round(lnl[:m], 1),
             np.asarray(steps)[:m])
    res = np.asarray(out)[:m], lnl[:m], np.asarray(ok)[:m], np.asarray(steps)[:m]
    return res + (np.asarray(jtj)[:m], idxs[:m]) if normal else res


def _layout_kinds(ctx: _Ctx):
    """(kinds of the host entries, kinds of a row's entries) of `_solve_layout`
    (`params.entry_kinds`; every row alike: flux, β, R_e, and q, PA where shape moves are
    on), for the per-band linear columns of `capacity._local_normal`."""
    row = ctx.slot_index[0] if ctx.shape_index is None else np.r_[ctx.slot_index[0],
                                                                  ctx.shape_index[0]]
    return entry_kinds(ctx.param, ctx.host_index), entry_kinds(ctx.param, row)


def _local_slots(ctx: _Ctx, u, active, new_slot: int, beta):
    """The new slot, its nearest active slots, padded with other inactive ones: LOCAL_SLOTS."""
    n_local = min(LOCAL_SLOTS, ctx.cap)
    c = np.asarray(ctx.param.state(jnp.asarray(u)).source.clumps.center_arcsec)
    d = np.where(active > 0, np.hypot(*(c - np.asarray(beta)).T), np.inf)
    d[new_slot] = -1.0
    near = [int(i) for i in np.argsort(d) if np.isfinite(d[i])][:n_local]
    rest = [i for i in range(ctx.cap) if i not in near and active[i] == 0]
    return (near + rest)[:n_local]


def masked_state(param: Parametrization, u, active) -> FitState:
    """The state at u with clump k's fluxes times active[k], the product made in numpy
    (`params.masked_clumps` outside a trace compiles its multiply op by op)."""
    state = param.state(jnp.asarray(u))
    flux = np.asarray(state.source.clumps.flux) * np.asarray(active, float)[:, None]
    return eqx.tree_at(lambda s: s.source.clumps.flux, state, jnp.asarray(flux))


def _rendered(ctx: _Ctx, u, active):
    """(χ² per band, μ plus the best diffuse light per band) at u with the mask `active`, no
    refit (`likelihood.chi2_and_images`: the program the observation fit's images reuse)."""
    chi2, images = chi2_and_images(ctx.model, ctx.data, masked_state(ctx.param, u, active))
    return [float(c) for c in chi2], [np.asarray(m) for m in images]


def _residuals(ctx: _Ctx, u, active):
    """d − μ per band, less the best diffuse light where there is one (what is left to seed)."""
    return [np.asarray(d) - m for d, m in zip(ctx.data.images, _rendered(ctx, u, active)[1])]


def _log_likelihood(ctx: _Ctx, u, active):
    """ln L at u with the mask `active`, no refit: −χ²/2 from the program the counting compiles
    anyway for its residuals (one program of the whole model fewer than a ln L program). Its
    χ² is the fit's, profiled over the diffuse light where there is one: no second sum here."""
    return -0.5 * sum(_rendered(ctx, u, active)[0])


def _chi2_dof(ctx: _Ctx, lnl, n_active):
    dof = max(ctx.n_pix - ctx.n_host - sum(ctx.data.n_diffuse) - n_active * ctx.k_clump, 1)
    return float(-2.0 * lnl / dof)


def _seed_slot(ctx: _Ctx, u, slot: int, cand: seeding.Candidates, i: int):
    """u with slot `slot` set to candidate i's source-plane values."""
    re_lo, re_hi = ctx.re_bounds
    flux = np.asarray(cand.flux[i], float)
    flux = np.clip(flux, 1e-3 * max(flux.max(), 1e-12), None)
    # a seed starts well inside the size bounds (a move may start up to 0.9 re_hi)
    re = float(np.clip(cand.re_arcsec[i], 3 * re_lo, 0.5 * re_hi))
    q, pa = (float(cand.q[i]), float(cand.pa_rad[i])) if ctx.opts.fit_shape else (1.0, 0.0)
    return _set_clump(ctx, u, slot, cand.beta_arcsec[i], flux, re, q, pa)


def _candidates(ctx: _Ctx, u, active):
    return seeding.find_candidates(ctx.model, _residuals(ctx, u, active), ctx.variances, ctx.masks,
                                   lens=ctx.lens, psf_sigma_pix=ctx.psf_sigma,
                                   threshold_snr=ctx.opts.detect_snr,
                                   max_candidates=max(ctx.opts.n_starts, 1))


def _fit_host(ctx: _Ctx, u0, steps):
    """Host and background alone (no clump active), from the moments and rescaled sizes."""
    re_scale = np.array([1.0, 0.5, 2.0, 1.5, 0.7, 3.0])
    starts = []
    for s in range(ctx.opts.n_starts):
        st = ctx.param.state(jnp.asarray(u0))
        for name in ("bulge", "disk"):
            comp = getattr(st.source, name)
            if comp is None:
                continue
            get = (lambda x, nm=name: getattr(x.source, nm).re_arcsec) if name == "bulge" else \
                (lambda x: x.source.disk.sersic.re_arcsec)
            st = eqx.tree_at(get, st, get(st) * re_scale[s % re_scale.size])
        starts.append(np.asarray(ctx.param.initial(st)))
    active = np.zeros((len(starts), ctx.cap))
    if ctx.host_index.size == 0:    # no host and no background: the diffuse light alone
        u = np.asarray(u0)
        us, lnl = u[None], np.array([_log_likelihood(ctx, u, active[0])])
        ok, n = np.array([True]), np.array([0])
    else:
        # no clump rows: every slot is dark, its columns would be zeros pushed through the
        # clumps' rendering at every step (`capacity._local_normal` skips padding rows)
        us, lnl, ok, n = _fit_local(ctx, np.stack(starts), [[]] * len(starts), active)
    b = int(np.argmax(lnl))
    steps.append(dict(step=0, action="host", slot=-1, n_clumps=0, delta_lnL=np.nan,
                      criterion=np.nan, accepted=True, lnL=float(lnl[b]),
                      chi2_dof=_chi2_dof(ctx, lnl[b], 0), converged=bool(ok[b]), n_steps=int(n[b])))
    return us[b], float(lnl[b])


def _count(ctx: _Ctx, u, lnl, steps):
    """Add clumps one at a time while the criterion accepts them (module doc)."""
    active = np.zeros(ctx.cap)
    n_images = np.zeros(ctx.cap, int)
    while active.sum() < ctx.cap:
        cand = _candidates(ctx, u, active)
        if len(cand) == 0:
            steps.append(dict(step=len(steps), action="stop", slot=-1, n_clumps=int(active.sum()),
                              delta_lnL=np.nan, criterion=np.nan, accepted=False, lnL=lnl,
                              chi2_dof=_chi2_dof(ctx, lnl, active.sum()), converged=True,
                              n_steps=0, reason=f"no residual peak above S/N {ctx.opts.detect_snr}"))
            break
        slot = int(np.argmin(active))
        trial = active.copy()
        trial[slot] = 1.0
        tries = min(len(cand), ctx.opts.n_starts)
        LOG.info("candidates: beta %s flux %s re %s snr %s", np.round(cand.beta_arcsec[:tries], 3),
                 np.round(cand.flux[:tries], 2), np.round(cand.re_arcsec[:tries], 4),
                 np.round(cand.snr[:tries], 1))
        u0s = np.stack([_seed_slot(ctx, u, slot, cand, i) for i in range(tries)])
        sets = [_local_slots(ctx, u, active, slot, cand.beta_arcsec[i]) for i in range(tries)]
        us, lnls, oks, n = _fit_local(ctx, u0s, sets, np.tile(trial, (tries, 1)))
        b = int(np.argmax(lnls))
        value, ok = _criterion(ctx.opts, lnls[b] - lnl, ctx.k_clump, ctx.n_pix)
        steps.append(dict(step=len(steps), action="add" if ok else "reject", slot=slot,
                          n_clumps=int(active.sum() + ok), delta_lnL=float(lnls[b] - lnl),
                          criterion=value, accepted=ok, lnL=float(max(lnls[b], lnl) if ok else lnl),
                          chi2_dof=_chi2_dof(ctx, lnls[b] if ok else lnl, active.sum() + ok),
                          converged=bool(oks[b]), n_steps=int(n[b]),
                          candidate_beta_arcsec=[float(v) for v in cand.beta_arcsec[b]],
                          candidate_snr=float(cand.snr[b]), n_images=int(cand.n_images[b])))
        if not ok:
            break
        u, lnl, active = us[b], float(lnls[b]), trial
        n_images[slot] = int(cand.n_images[b])
    return u, lnl, active, n_images


def _prune(ctx: _Ctx, u, lnl, active, steps):
    """Remove, worst first, clumps the criterion would not keep even without a refit."""
    while active.sum() > 0:
        masks = np.tile(active, (ctx.cap, 1)) * (1.0 - np.eye(ctx.cap))
        without = np.array([_log_likelihood(ctx, u, m) if a > 0 else -np.inf
                            for m, a in zip(masks, active)])
        gain = np.where(active > 0, lnl - without, np.inf)
        i = int(np.argmin(gain))
        value, keep = _criterion(ctx.opts, float(gain[i]), ctx.k_clump, ctx.n_pix)
        if keep:
            break
        active = masks[i]
        lnl = float(without[i])
        steps.append(dict(step=len(steps), action="remove", slot=i, n_clumps=int(active.sum()),
                          delta_lnL=-float(gain[i]), criterion=value, accepted=True, lnL=lnl,
                          chi2_dof=_chi2_dof(ctx, lnl, active.sum()), converged=True, n_steps=0))
    return lnl, active


def _host_moves(ctx: _Ctx, u, u0, active):
    """Trials that give the host and a clump each other's roles: [(kind, slot, u start, active
    after, local slots)]. With one Sérsic host (not `host_start`'s components).

    Why: fitted alone first, the host takes whatever light gains most χ², and a compact
    clump of about the host's flux gains more than the host's own diffuse light. It then sits
    on that clump with the clump's size, and the counting gives the real host's light to a
    clump at the largest R_e and to its neighbours (a mock: host R_e 0.05″ on the brightest
    clump, truth 0.26″; the other clumps' magnitudes 2–4σ too bright). No local step undoes
    that: it takes the host across the image.
    - ("swap", i): clump i is broader than the host: the host starts at clump i's centre
      and flux with R_e max(R_e,i, the moments' R_e) and the moments' n, q, PA; clump i
      at the host's centre, flux and R_e (clipped into the clumps' bounds). The same
      parameters: accepted when ln L rises.
    - ("reseed", slot): the host from the data's moments again (flux: the moments' less the
      clumps'), the old host a new clump in a free slot: judged as an added clump.
    - ("cusp", slot): a compact clump near the host's centre holds its light in the host's
      cusp (a Sérsic n above the moments'): the host's n back to the moments', a clump of
      CUSP_FLUX_FRACTION of its flux and CUSP_RE_FRACTION of its R_e at its centre, in a
      free slot: judged as an added clump, and made only where no swap or reseed is
      accepted (`_rehost`). The cluster arc's seed 0: an S/N 30 clump 7.5 mas from the
      host's centre was missed, the truth ΔBIC 69 better than the fit.
    At most n_starts moves: the swaps (broadest clump first), the reseed, the cusp, in that
    order; with n_starts − 1 swaps or more the cusp is not tried (a host that many clumps
    are broader than sits on a clump: the swaps are the moves for it)."""
    if ctx.opts.host is False:
        return []
    st, st0 = ctx.param.state(jnp.asarray(u)), ctx.param.state(jnp.asarray(u0))
    if st.source.disk is not None:
        return []
    host, host0, cl = st.source.bulge, st0.source.bulge, st.source.clumps
    if host is None or host0 is None:
        return []
    re_host, re0 = float(host.re_arcsec), float(host0.re_arcsec)
    if ctx.opts.host_re_range_arcsec is not None:
        lo, hi = ctx.opts.host_re_range_arcsec
        re0 = float(np.clip(re0, lo + 1e-3 * (hi - lo), hi - 1e-3 * (hi - lo)))

    def with_host(centre, flux, re):
        new = eqx.tree_at(lambda h: (h.center_arcsec, h.flux, h.re_arcsec, h.n, h.q, h.pa_rad),
                          host, (jnp.asarray(centre, float), jnp.asarray(flux, float),
                                 jnp.asarray(re, float), host0.n, host0.q, host0.pa_rad))
        return np.asarray(ctx.param.initial(eqx.tree_at(lambda x: x.source.bulge, st, new)))

    moves = []
    centres, fluxes, res = (np.asarray(cl.center_arcsec), np.asarray(cl.flux),
                            np.asarray(cl.re_arcsec))
    for i in np.nonzero(active > 0)[0]:
        if res[i] > re_host:
            v = with_host(centres[i], np.clip(fluxes[i], 1e-12, None), max(res[i], re0))
            v = _set_clump(ctx, v, int(i), np.asarray(host.center_arcsec), np.asarray(host.flux),
                           re_host)
            moves.append(("swap", int(i), v, active.copy(),
                          _local_slots(ctx, v, active, int(i), np.asarray(host.center_arcsec))))
    free = np.nonzero(active == 0)[0]
    if free.size:
        j = int(free[0])
        rest = np.asarray(host0.flux) - (fluxes * active[:, None]).sum(0)
        v = with_host(host0.center_arcsec, np.maximum(rest, 0.1 * np.asarray(host0.flux)), re0)
        v = _set_clump(ctx, v, j, np.asarray(host.center_arcsec), np.asarray(host.flux), re_host)
        act = active.copy()
        act[j] = 1.0
        moves.append(("reseed", j, v, act, _local_slots(ctx, v, act, j, np.asarray(host.center_arcsec))))
        if float(host.n) > float(host0.n):
            f = np.asarray(host.flux)
            new = eqx.tree_at(lambda h: (h.flux, h.n), host,
                              (jnp.asarray((1.0 - CUSP_FLUX_FRACTION) * f, float), host0.n))
            v = np.asarray(ctx.param.initial(eqx.tree_at(lambda x: x.source.bulge, st, new)))
            v = _set_clump(ctx, v, j, np.asarray(host.center_arcsec), CUSP_FLUX_FRACTION * f,
                           CUSP_RE_FRACTION * re_host)
            moves.append(("cusp", j, v, act,
                          _local_slots(ctx, v, act, j, np.asarray(host.center_arcsec))))
    # the broadest clumps first: n_starts moves are solved (one batch, no compile)
    return sorted(moves, key=lambda m: -res[m[1]] if m[0] == "swap" else np.inf)[:ctx.opts.n_starts]


def _rehost(ctx: _Ctx, u, u0, lnl, active, n_images, steps):
    """The host moves (`_host_moves`), the best accepted one made (a cusp move only where
    no swap or reseed is accepted), then pruning again (a clump that held the host's light is
    redundant once the host has it). Each move is a step."""
    moves = _host_moves(ctx, u, u0, active)
    if not moves:
        return u, lnl, active, n_images
    us, lnls, oks, n = _fit_local(ctx, np.stack([m[2] for m in moves]), [m[4] for m in moves],
                                  np.stack([m[3] for m in moves]))
    judged = []
    for (kind, _, _, act, _), v in zip(moves, lnls):
        if kind == "swap":
            judged.append((float(-2.0 * (v - lnl)), bool(v > lnl)))
        else:
            judged.append(_criterion(ctx.opts, float(v - lnl), ctx.k_clump, ctx.n_pix))
    ok = [b for b in range(len(moves)) if judged[b][1]]
    # a cusp move only where no swap or reseed is accepted: those put a host that sits on a
    # clump back on the diffuse light, which a cusp move would keep compact with one clump
    # more (a JWST pulls mock: the cusp ahead of the reseed by Δln L 0.3 kept the host's R_e
    # at 0.06″ for 0.3″ and moved two clumps' magnitudes by 1.6σ)
    first = [b for b in ok if moves[b][0] != "cusp"] or ok
    best = max(first, key=lambda b: lnls[b]) if first else -1
    for b, (kind, slot, _, act, _) in enumerate(moves):
        made = b == best
        after_act, after_lnl = (act, lnls[b]) if made else (active, lnl)
        step = dict(step=len(steps), action=kind if made else f"reject_{kind}", slot=slot,
                    n_clumps=int(after_act.sum()), delta_lnL=float(lnls[b] - lnl),
                    criterion=judged[b][0], accepted=judged[b][1], made=made,
                    lnL=float(after_lnl), chi2_dof=_chi2_dof(ctx, after_lnl, after_act.sum()),
                    converged=bool(oks[b]), n_steps=int(n[b]))
        if not made and best < 0 and lnls[b] > lnl - ALTERNATIVE_DLNL:
            cl = ctx.param.state(jnp.asarray(us[b])).source.clumps
            on = np.nonzero(act > 0)[0]
            step["alternative"] = {"center_arcsec": np.asarray(cl.center_arcsec)[on].tolist(),
                                   "flux": np.asarray(cl.flux)[on].tolist()}
        steps.append(step)
    if best < 0:
        return u, lnl, active, n_images
    u, lnl, active = us[best], float(lnls[best]), moves[best][3]
    if moves[best][0] in ("reseed", "cusp"):   # the new clump's light: seen at least once
        n_images = n_images.copy()
        n_images[moves[best][1]] = 1
    lnl, active = _prune(ctx, u, lnl, active, steps)
    return u, lnl, active, n_images


def host_alternatives(steps) -> list:
    """The clumps (centre [n, 2] arcsec, flux [n, B]) of each rejected host move whose ln L
    came within ALTERNATIVE_DLNL of the kept configuration (`FLAGS` "host_alternative")."""
    return [(np.asarray(st["alternative"]["center_arcsec"], float).reshape(-1, 2),
             np.asarray(st["alternative"]["flux"], float))
            for st in steps if "alternative" in st]


def host_alternative_fluxes(center_arcsec, flux, flux_err, re_arcsec, alternatives,
                            match_arcsec: float):
    """([N] bool: clump i (centre [N, 2] arcsec, flux and its σ [N, B], R_e [N] arcsec) has,
    in one of `alternatives` (`host_alternatives`), no clump within max(match_arcsec, R_e,i)
    or the nearest one's flux more than ALTERNATIVE_SIGMA σ away in a band (flag 64); the
    flux [N, B] each flagged clump has in the alternative that moves it most): a clump the
    alternative has no clump for has 0 there (its light is the host's); one no alternative
    flags, NaN. "Most": the largest flux change in σ over the bands (no counterpart: more
    than any)."""
    center_arcsec = np.asarray(center_arcsec, float).reshape(-1, 2)
    flux, flux_err = np.asarray(flux, float), np.asarray(flux_err, float)
    out = np.zeros(len(center_arcsec), bool)
    alt_flux = np.full(flux.shape, np.nan)
    moved = np.full(len(center_arcsec), -np.inf)      # the flagging alternative's change, σ
    for centres, fluxes in alternatives:
        for i, c in enumerate(center_arcsec):
            d = np.hypot(*(centres - c).T) if len(centres) else np.array([])
            if not d.size or d.min() > max(match_arcsec, float(re_arcsec[i])):
                out[i] = True
                if moved[i] < np.inf:
                    moved[i], alt_flux[i] = np.inf, 0.0
                continue
            other = fluxes[int(np.argmin(d))]
            ok = np.isfinite(flux_err[i]) & (flux_err[i] > 0)
            pull = np.abs(other - flux[i])[ok] / flux_err[i][ok]
            if np.any(pull > ALTERNATIVE_SIGMA):
                out[i] = True
                if pull.max() > moved[i]:
                    moved[i], alt_flux[i] = pull.max(), other
    return out, alt_flux


def merged_clump(beta, flux, re, n: float, q_range=CLUMP_Q_RANGE):
    """One clump with the light of several round ones: (β [2], flux [B], R_e, q, PA).

    beta [m, 2] (arcsec), flux [m, B], re [m] (arcsec, round clumps of Sérsic index n). Fluxes
    summed; centre flux-weighted (first band); the second moment of the light (each clump's
    own σ² = (c·R_e)² per axis, c from `profiles.sersic_axis_rms_per_re_np`, plus its offset)
    gives the ellipse: R_e of the major axis, q = σ_minor/σ_major (clipped into q_range), PA
    counter-clockwise from +β1 (the `Sersic` conventions)."""
    beta, flux, re = np.asarray(beta, float), np.asarray(flux, float), np.asarray(re, float)
    w = np.clip(flux[:, 0], 1e-300, None)
    w = w / w.sum()
    c = w @ beta
    d = beta - c
    k = profiles.sersic_axis_rms_per_re_np(n)
    m2 = np.einsum("i,ij,ik->jk", w, d, d) + np.eye(2) * float(w @ (k * re) ** 2)
    val, vec = np.linalg.eigh(m2)
    q = float(np.clip(np.sqrt(max(val[0], 0.0) / val[1]), q_range[0] + 0.05, q_range[1] - 0.05))
    pa = float(np.arctan2(vec[1, 1], vec[0, 1]))
    return c, flux.sum(axis=0), float(np.sqrt(val[1]) / k), q, pa


def _set_clump(ctx: _Ctx, u, slot: int, beta, flux, re, q=1.0, pa=0.0):
    """u with slot `slot` set to these values (R_e clipped inside its bounds)."""
    st = ctx.param.state(jnp.asarray(u))
    re_lo, re_hi = ctx.re_bounds
    cl = st.source.clumps
    cl = eqx.tree_at(lambda c: (c.center_arcsec, c.flux, c.re_arcsec, c.q, c.pa_rad), cl,
                     (cl.center_arcsec.at[slot].set(jnp.asarray(beta, float)),
                      cl.flux.at[slot].set(jnp.asarray(flux, float)),
                      cl.re_arcsec.at[slot].set(float(np.clip(re, 3 * re_lo, 0.9 * re_hi))),
                      cl.q.at[slot].set(q), cl.pa_rad.at[slot].set(pa)))
    return np.asarray(ctx.param.initial(eqx.tree_at(lambda s: s.source.clumps, st, cl)))


def _close_pairs(ctx: _Ctx, u, active):
    """Active pairs (i, j) whose centres are within MERGE_SEPARATION · (R_e,i + R_e,j) in the
    source plane, closest (in those units) first."""
    cl = ctx.param.state(jnp.asarray(u)).source.clumps
    c, re = np.asarray(cl.center_arcsec), np.asarray(cl.re_arcsec)
    idx = np.nonzero(active > 0)[0]
    pairs = []
    for a, i in enumerate(idx):
        for j in idx[a + 1:]:
            x = np.hypot(*(c[i] - c[j])) / (re[i] + re[j])
            if x < MERGE_SEPARATION:
                pairs.append((x, int(i), int(j)))
    return [(i, j) for _, i, j in sorted(pairs)]


def _n_params(ctx: _Ctx, slots, shaped):
    """Free parameters of these clumps (k per clump, 2 more for each shaped one)."""
    return sum(ctx.k_clump + (2 if shaped[i] else 0) for i in slots)


def _trial(ctx: _Ctx, u, active, move):
    """(u0, active, shaped after, local slots, shaped in the solve) of a move: ("merge", i, j):
    the pair as one clump in slot i (elliptical where shape moves are on; `merged_clump`), j
    emptied; ("shape", i, -1 or -2): clump i elliptical, started at q = SHAPE_START_Q with
    the major axis along β1 or β2 (started at q 0.9, PA 0, 4 of 13 trials ran 100 steps).
    Only slot i's q, PA are solved (other shaped clumps hold theirs): every move's solve has
    as many entries, one compiled program."""
    kind, i, j = move
    cl = ctx.param.state(jnp.asarray(u)).source.clumps
    act, shaped = active.copy(), ctx.shaped.copy()
    if kind == "merge":
        beta, flux, re, q, pa = merged_clump(np.asarray(cl.center_arcsec)[[i, j]],
                                             np.asarray(cl.flux)[[i, j]],
                                             np.asarray(cl.re_arcsec)[[i, j]], ctx.opts.clump_n)
        act[j] = 0.0
        shaped[j] = False
    else:
        # two starts (j = −1, −2): major axis along β1 or β2, the round R_e as R_e√q
        q, pa = SHAPE_START_Q, (0.0 if j == -1 else 0.5 * np.pi)
        beta, flux, re = (np.asarray(cl.center_arcsec)[i], np.asarray(cl.flux)[i],
                          float(cl.re_arcsec[i]) / np.sqrt(q))
    if ctx.shape_index is None:
        q, pa = 1.0, 0.0
    else:
        shaped[i] = True
    u0 = _set_clump(ctx, u, i, beta, flux, re, q, pa)
    solve_shaped = np.zeros(ctx.cap, bool)
    solve_shaped[i] = shaped[i]
    return u0, act, shaped, _local_slots(ctx, u0, act, i, beta), solve_shaped


def _judge(ctx: _Ctx, move, lnl_now, lnl_trial):
    """(criterion value, move accepted). A merge is accepted unless the criterion keeps the
    pair: the same test as adding a clump, for the parameters the pair has beyond the one
    clump (k − 2 when the merged clump is elliptical). A shape move is accepted when the
    criterion accepts its 2 parameters (q, PA)."""
    kind, i, j = move
    if kind == "merge":
        shaped_after = ctx.shaped.copy()
        shaped_after[i] = ctx.shape_index is not None
        k_extra = _n_params(ctx, (i, j), ctx.shaped) - _n_params(ctx, (i,), shaped_after)
        value, keep_pair = _criterion(ctx.opts, lnl_now - lnl_trial, k_extra, ctx.n_pix)
        return value, not keep_pair
    return _criterion(ctx.opts, lnl_trial - lnl_now, 2, ctx.n_pix)


def _refine(ctx: _Ctx, u, lnl, active, n_images, steps):
    """Merge and shape moves after pruning (issue 18: through a lens, one elongated clump was
    fitted as two round ones, each too small and with part of the flux).

    Moves: each close pair (`_close_pairs`) tried as one clump (`merged_clump`), and, where
    the renderer draws q and PA, each round clump tried elliptical. Up to n_starts moves are
    solved at once (local solves from the fixed-capacity batch: one compiled program for all
    moves, none per move); the accepted move (`_judge`) with the best criterion value is made
    (merges first), the other accepted ones are tried again from the new state, a rejected
    move is not tried again; until none is left. Each tried move is a step.

    Returns (u, ln L, active, n_images, shape_trials): shape_trials {slot: (Δln L, R_e, q,
    PA)}, each slot's best shape trial, made or not (the final refit's start for its shape)."""
    tried = set()
    shape_trials = {}
    while True:
        moves = [("merge", i, j) for i, j in _close_pairs(ctx, u, active)]
        if ctx.shape_index is not None:
            moves += [("shape", int(i), s) for i in np.nonzero((active > 0) & ~ctx.shaped)[0]
                      for s in (-1, -2)]
        moves = [m for m in moves if m not in tried][:ctx.opts.n_starts]
        if not moves:
            return u, lnl, active, n_images, shape_trials
        trials = [_trial(ctx, u, active, m) for m in moves]
        us, lnls, oks, n = _fit_local(ctx, np.stack([t[0] for t in trials]), [t[3] for t in trials],
                                      np.stack([t[1] for t in trials]), [t[4] for t in trials])
        judged = [_judge(ctx, m, lnl, float(v)) for m, v in zip(moves, lnls)]
        for b, (kind, i, _) in enumerate(moves):
            if kind == "shape" and lnls[b] - lnl > shape_trials.get(i, (-np.inf,))[0]:
                cl = ctx.param.state(jnp.asarray(us[b])).source.clumps
                shape_trials[i] = (float(lnls[b] - lnl), float(cl.re_arcsec[i]),
                                   float(cl.q[i]), float(cl.pa_rad[i]))
        # a merge's criterion value is the pair's: the most negative is the best kept pair;
        # best move: the merge the pair least justifies, then the shape most justified
        order = sorted((b for b in range(len(moves)) if judged[b][1]),
                       key=lambda b: (moves[b][0] != "merge",
                                      -judged[b][0] if moves[b][0] == "merge" else judged[b][0]))
        best = order[0] if order else -1
        for b, m in enumerate(moves):
            made = b == best
            if made or not judged[b][1]:
                # an accepted move not made is tried again from the new state
                tried.add(m)
            # the state after this step: the move's where it is made, else the current one
            act_after, lnl_after = (trials[b][1], lnls[b]) if made else (active, lnl)
            steps.append(dict(step=len(steps), action=m[0] if made else (
                              f"defer_{m[0]}" if judged[b][1] else f"reject_{m[0]}"),
                              slot=m[1], partner=m[2], n_clumps=int(act_after.sum()),
                              delta_lnL=float(lnls[b] - lnl), criterion=judged[b][0],
                              accepted=bool(judged[b][1]), made=made, lnL=float(lnl_after),
                              chi2_dof=_chi2_dof(ctx, lnl_after, act_after.sum()),
                              converged=bool(oks[b]), n_steps=int(n[b])))
        if best >= 0:
            m = moves[best]
            u, lnl, active = us[best], float(lnls[best]), trials[best][1]
            ctx.shaped = trials[best][2]
            if m[0] == "merge":
                n_images = n_images.copy()
                n_images[m[1]] = max(n_images[m[1]], n_images[m[2]])
                n_images[m[2]] = 0


def _shaped_start(ctx: _Ctx, u, active, shape_trials):
    """u with every kept round clump given the R_e, q and PA of its best shape trial (those
    with none keep theirs), and ctx.shaped set for every kept clump: the final refit then
    frees all their shapes (`AutoOptions.final_shape`). A round start would not do: at q = 1
    the PA has no gradient and q sits on its bound."""
    cl = ctx.param.state(jnp.asarray(u)).source.clumps
    centres, fluxes = np.asarray(cl.center_arcsec), np.asarray(cl.flux)
    for i in np.nonzero((active > 0) & ~ctx.shaped)[0]:
        if int(i) in shape_trials:
            _, re, q, pa = shape_trials[int(i)]
            # a trial that went back to round starts just inside the bound, free to move
            q = float(np.clip(q, CLUMP_Q_RANGE[0] + 0.01, CLUMP_Q_RANGE[1] - 0.01))
            u = _set_clump(ctx, u, int(i), centres[i], fluxes[i], re, q, pa)
    ctx.shaped = ctx.shaped | (active > 0)
    return u


def _final(ctx: _Ctx, u, active, steps):
    """Refit from final_starts (default n_starts) perturbed starts (the first unperturbed);
    best kept, spread kept.

    Over the host, background and the kept clumps' entries only (`_fit_local`): an inactive
    slot's Jacobian columns are zero and its step is zero, so leaving them out gives the
    same iterations without computing them (5 kept of 20 slots: a quarter of the columns).
    The program is the counting steps' (`_solve_layout`): no compile here. The unperturbed
    start first; the perturbed ones start about its optimum (`_start_offsets`: at
    FINAL_START_SIGMA times its Fisher errors) and get at most FINAL_STEP_FACTOR times its
    steps, and one that ends above it (unconverged) is carried on to convergence. Returns (us, lnls,
    oks, b: the best start, its JᵀJ at its optimum and the entries of u that is over:
    `_uncertainty`)."""
    s = ctx.opts.n_starts if ctx.opts.final_starts is None else ctx.opts.final_starts
    kept = [int(i) for i in np.nonzero(active > 0)[0]]

    def fit(u0s, max_steps=None):
        return _fit_local(ctx, u0s, [kept] * len(u0s), np.tile(active, (len(u0s), 1)),
                          normal=True, max_steps=max_steps)
    res = fit(u[None])
    if s > 1:
        cap = min(int(ctx.opts.max_steps),
                  max(FINAL_STEP_FACTOR * int(res[3][0]), FINAL_MIN_STEPS))
        starts = res[0][0] + _start_offsets(res[4][0], res[5][0], u.size, s - 1,
                                            np.random.default_rng(ctx.opts.seed))
        res = tuple(np.concatenate(ab) for ab in zip(res, fit(starts, cap)))
    us, lnls, oks, n, jtj, idxs = (np.array(a) for a in res)
    b = int(np.argmax(lnls))
    if b > 0 and not oks[b]:
        capped_steps = n[b]
        for a, v in zip((us, lnls, oks, n, jtj, idxs), fit(us[b][None])):
            a[b] = v[0]
        n[b] += capped_steps
        b = int(np.argmax(lnls))
    steps.append(dict(step=len(steps), action="final", slot=-1, n_clumps=int(active.sum()),
                      delta_lnL=np.nan, criterion=np.nan, accepted=True, lnL=float(lnls[b]),
                      chi2_dof=_chi2_dof(ctx, lnls[b], active.sum()), converged=bool(oks[b]),
                      n_steps=int(n[b]), starts_lnL=[float(v) for v in lnls],
                      starts_n_steps=[int(v) for v in n]))
    return us, lnls, oks, b, jtj[b], idxs[b]


def _start_offsets(jtj, idx, size: int, n: int, rng):
    """[n, size] offsets in u of the perturbed final starts: N(0, FINAL_START_SIGMA² Cov_u)
    over the fitted entries idx (u.size marks padding), Cov_u the inverse of their JᵀJ at the
    optimum (`safe_inverse`: unconstrained directions get huge variances, hence the clip to
    ±FINAL_START_MAX_U); 0 elsewhere. Where JᵀJ is not finite (a refit that ended so), the
    offsets are N(0, FINAL_START_MAX_U²) in each entry instead."""
    idx = np.asarray(idx)
    keep = idx < size
    k = int(keep.sum())
    jtj = np.asarray(jtj)[np.ix_(keep, keep)]
    z = rng.normal(size=(k, n))
    if np.all(np.isfinite(jtj)):
        cov = np.asarray(covariance_from_fisher_u(jnp.asarray(jtj), jnp.ones(k, jtj.dtype)))
        w, v = np.linalg.eigh(0.5 * (cov + cov.T))
        draw = FINAL_START_SIGMA * (v * np.sqrt(np.clip(w, 0.0, None))) @ z
    else:
        draw = FINAL_START_MAX_U * z
    out = np.zeros((n, size))
    out[:, idx[keep]] = np.clip(draw.T, -FINAL_START_MAX_U, FINAL_START_MAX_U)
    return out


def _spread(ctx: _Ctx, us, lnls, active):
    """Per slot, the spread (std) across starts within Δln L < 2 of the best of β (arcsec)
    and of ln flux in the first band."""
    near = lnls >= lnls.max() - 2.0
    cents, lfl = [], []
    for u in us[near]:
        cl = ctx.param.state(jnp.asarray(u)).source.clumps
        cents.append(np.asarray(cl.center_arcsec))
        lfl.append(np.log(np.maximum(np.asarray(cl.flux[:, 0]), 1e-300)))
    cents, lfl = np.stack(cents), np.stack(lfl)
    return np.hypot(*cents.std(axis=0).T), lfl.std(axis=0), int(near.sum())


def _uncertainty(ctx: _Ctx, u, jtj, idx):
    """Fisher errors of the entries idx of u (host, background and the kept clumps' entries
    of the final refit; u.size marks padding) from that refit's JᵀJ at u, the Fisher matrix
    in u (the residuals are whitened): in physical x, F_x = D⁻¹ JᵀJ D⁻¹ with D = dx/du
    (every transform is elementwise). NaN elsewhere. No program of its own: the refit made
    JᵀJ (it equals the Fisher matrix of those entries, tests/test_inference_auto.py)."""
    keep = np.asarray(idx) < ctx.param.size
    entries = np.asarray(idx)[keep]
    x, dxdu = (np.asarray(a) for a in ctx.param.physical_and_slope(jnp.asarray(u)))
    cov = np.full((x.size, x.size), np.nan)
    cov[np.ix_(entries, entries)] = np.asarray(covariance_from_fisher_u(
        jnp.asarray(np.asarray(jtj)[np.ix_(keep, keep)]), jnp.asarray(dxdu[entries])))
    return Uncertainty(ctx.param.labels, jnp.asarray(x), jnp.asarray(cov))


def re_profile_trials(re, q, pa, trials=PROFILE_TRIALS, q_range=CLUMP_Q_RANGE):
    """Shapes [(R_e, q, PA)] (arcsec, -, rad) at which a clump's R_e is held for its profile
    (`PROFILE_TRIALS`): R_e·f with, in the same orientation, the minor axis q·R_e kept
    (q' = q/f, "minor") or q' = SHAPE_START_Q ("open"), or, turned by 90°, the old major axis
    kept as the new minor one (q' = 1/f, "turned": through a lens the measured axis is the
    magnified one, and the other may be the longer). q' is kept inside q_range."""
    out = []
    for f, start in trials:
        r = f * float(re)
        qq = {"minor": float(q) / f, "open": SHAPE_START_Q, "turned": 1.0 / f}[start]
        out.append((r, float(np.clip(qq, q_range[0] + 0.01, q_range[1] - 0.01)),
                    float(pa) + (0.5 * np.pi if start == "turned" else 0.0)))
    return out


def profile_sigma(sigma, deltas, dlnl):
    """Lower bound of a parameter's profile-likelihood σ: max(σ, max_k |Δx_k| / √max(2Δln L_k, 1)).

    deltas: the parameter's change at refits k with some parameter held away from the
    optimum; dlnl: ln L(optimum) − ln L(refit k). Where the profile ln L is quadratic with
    width σ_p, any point with x' has ln L ≤ ln L_p(x') = ln L_max − Δx²/(2σ_p²), so
    σ_p ≥ |Δx|/√(2Δln L); a refit within 2Δln L < 1 lies inside the 1σ interval (σ_p ≥ |Δx|).
    It never exceeds the σ_p of a quadratic ln L, whatever the trials."""
    d = np.abs(np.asarray(deltas, float))
    if not d.size:
        return float(sigma)
    t = np.sqrt(np.maximum(2.0 * np.asarray(dlnl, float), 1.0))
    ok = np.isfinite(d) & np.isfinite(t)
    return float(max(sigma, np.max(np.where(ok, d / t, 0.0))))


def _re_entries(param: Parametrization, cap: int) -> np.ndarray:
    """[cap] entry of u of each slot's R_e."""
    start, out = 0, np.zeros(cap, int)
    for leaf in param.leaves:
        if leaf.path == "clumps.re_arcsec":
            out[np.asarray(leaf.index)] = start + np.arange(leaf.size)
        start += leaf.size
    return out


def _profile(ctx: _Ctx, u, lnl, active):
    """{slot: (R_e and flux [B] refits: arrays of Δ and Δln L)} of each kept shaped clump: its
    R_e held at each `re_profile_trials` shape, the clump, its nearest neighbours, the host
    and background refitted (`_fit_local`, the counting's program: no compile). Issue 18: a
    S/N 90 clump through the SIS fitted R_e 5.4 ± 0.06 mas (truth 6.1, q 0.86), at q 0.25 with
    its major axis along the arc; held at the truth's shape, ln L fell by 2.1 only: across the
    arc the clump is unresolved and the Fisher error, conditional on that q and PA, was 13
    times too small."""
    cl = ctx.param.state(jnp.asarray(u)).source.clumps
    re_entry = _re_entries(ctx.param, ctx.cap)
    jobs = []
    for i in np.nonzero((active > 0) & ctx.shaped)[0]:
        c = np.asarray(cl.center_arcsec[i])
        for r, q, pa in re_profile_trials(float(cl.re_arcsec[i]), float(cl.q[i]), float(cl.pa_rad[i])):
            u0 = _set_clump(ctx, u, int(i), c, np.asarray(cl.flux[i]), r, q, pa)
            jobs.append((int(i), u0, _local_slots(ctx, u, active, int(i), c)))
    out = {}
    for k in range(0, len(jobs), ctx.opts.n_starts):
        batch = jobs[k:k + ctx.opts.n_starts]
        us, lnls, _, _ = _fit_local(ctx, np.stack([b[1] for b in batch]), [b[2] for b in batch],
                                    np.tile(active, (len(batch), 1)), None,
                                    [[re_entry[b[0]]] for b in batch],
                                    max_steps=min(int(ctx.opts.max_steps), PROFILE_MAX_STEPS))
        for (i, _, _), ut, lt in zip(batch, us, lnls):
            ct = ctx.param.state(jnp.asarray(ut)).source.clumps
            d_re, d_flux, d_lnl = out.setdefault(i, ([], [], []))
            d_re.append(float(ct.re_arcsec[i] - cl.re_arcsec[i]))
            d_flux.append(np.asarray(ct.flux[i] - cl.flux[i], float))
            d_lnl.append(float(lnl - lt))
    return {i: (np.asarray(a), np.asarray(b), np.asarray(c)) for i, (a, b, c) in out.items()}


def _apply_profile(table, prof, idx, band_names):
    """Raise the table's R_e and flux (and mag) errors of the profiled clumps to their
    `profile_sigma` bounds (in place); the Fisher ones kept as `<name>_err_fisher`. Returns
    the "shape_degenerate" bits: where the R_e error grew more than PROFILE_FLAG_RATIO times."""
    from .catalog import ab_magnitude_err
    flag = np.zeros(len(idx), int)
    names = ["re_arcsec"] + [f"flux_{b}" for b in band_names]
    for n in names:
        table[f"{n}_err_fisher"] = np.asarray(table[f"{n}_err"], float).copy()
    for row, i in enumerate(idx):
        if int(i) not in prof:
            continue
        d_re, d_flux, d_lnl = prof[int(i)]
        fisher = float(table["re_arcsec_err_fisher"][row])
        sig = profile_sigma(fisher, d_re, d_lnl)
        table["re_arcsec_err"][row] = sig
        if sig > PROFILE_FLAG_RATIO * fisher:
            flag[row] |= FLAGS["shape_degenerate"]
        for b, name in enumerate(band_names):
            s_f = profile_sigma(float(table[f"flux_{name}_err_fisher"][row]), d_flux[:, b], d_lnl)
            table[f"flux_{name}_err"][row] = s_f
            if f"mag_{name}_err" in table.colnames:
                table[f"mag_{name}_err"][row] = ab_magnitude_err(
                    float(table[f"flux_{name}"][row]), s_f)
    return flag


def _compact(state: FitState, idx) -> FitState:
    """The state with only the clump rows idx."""
    return eqx.tree_at(lambda s: s.source.clumps, state, take_rows(state.source.clumps, idx))


def _blends(unc: Uncertainty, labels, idx, band=0):
    """Per kept clump: max |corr| of its flux (first band) with another kept clump's, and which."""
    pos = {lab: i for i, lab in enumerate(labels)}
    fi = [pos[f"clumps.flux[{s},{band}]"] for s in idx]
    cov = np.asarray(unc.cov)[np.ix_(fi, fi)]
    e = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = np.abs(cov / np.outer(e, e))
    np.fill_diagonal(corr, 0.0)
    if len(idx) < 2:
        return np.zeros(len(idx)), np.full(len(idx), -1)
    return corr.max(axis=1), corr.argmax(axis=1)


def _table(ctx, state, unc, idx, ok, spread, n_images, zeropoints_ab, prof=None):
    err = _compact(ctx.param.scatter(np.asarray(unc.err), fill=np.nan), idx)
    t = fit_table(_compact(state, idx), err, band_names=ctx.model.band_names,
                  zeropoints_ab=zeropoints_ab)
    if not len(idx):
        for name in ("flag", "n_images", "blend_corr", "blend_with", "spread_beta_arcsec",
                     "spread_lnflux", "slot"):
            t[name] = np.zeros(0)
        return t
    re_lo, re_hi = ctx.re_bounds
    cl = take_rows(state.source.clumps, idx)
    lo, hi = next(l.transform for l in ctx.param.leaves if l.path == "clumps.center_arcsec").lo, \
        next(l.transform for l in ctx.param.leaves if l.path == "clumps.center_arcsec").hi
    c = np.asarray(cl.center_arcsec)
    edge = (np.min(np.minimum(c - lo, hi - c), axis=1) < 1e-3 * (hi - lo))
    beta_err = np.hypot(np.asarray(t["beta1_arcsec_err"]), np.asarray(t["beta2_arcsec_err"]))
    # the profile's errors first: the size_unresolved test below reads the final R_e error
    flag = np.where(ok, 0, FLAGS["not_converged"]) | (
        0 if prof is None else _apply_profile(t, prof, idx, ctx.model.band_names))
    flag = flag | np.where(np.asarray(cl.re_arcsec) > 0.99 * re_hi, FLAGS["re_at_bound"], 0)
    flag = flag | np.where(edge, FLAGS["position_at_box_edge"], 0)
    flag = flag | np.where(np.asarray(t["re_arcsec_err"]) > np.asarray(t["re_arcsec"]),
                           FLAGS["size_unresolved"], 0)
    flag = flag | np.where(spread[0][idx] > np.maximum(3 * beta_err, 1e-9),
                           FLAGS["unstable_across_starts"], 0)
    # unresolved: the Fisher σ says nothing; the profile of χ² in R_e bounds it above
    ul = re_upper_limits(ctx.model, ctx.data, state,
                         np.where(flag & FLAGS["size_unresolved"], idx, -1), re_hi)
    t.add_column(ul, name="re_arcsec_ul", index=t.colnames.index("re_arcsec_err") + 1)
    t["re_arcsec_ul"].unit = "arcsec"
    corr, partner = _blends(unc, ctx.param.labels, idx)
    t["flag"] = flag.astype(int)
    t["n_images"] = n_images[idx]
    t["blend_corr"] = corr
    t["blend_with"] = np.where(corr > 0, partner, -1)
    t["spread_beta_arcsec"] = spread[0][idx]
    t["spread_lnflux"] = spread[1][idx]
    t["slot"] = np.asarray(idx)
    return t


def fit_without_truth(make_model, data, variances, masks=None, *, host_start=None, lens=None,
                      zeropoints_ab=None, options: AutoOptions = AutoOptions()) -> AutoFit:
    """Find, seed, count and fit the clumps of images without any catalogue (module doc).

    make_model(source: Source) -> SceneModel whose bands are in the order of `data` (its
        detector grids must match the images: give it a fixed field). For a lensed scene it
        must render clumps anywhere without a rebuild: accuracy source_mode "analytic"
        (`lensed_fit_accuracy`).
    data, variances: sequences of 2-D arrays (counts/s per pixel, the model's units; sky
        subtracted or not: a background level per band is fitted).  masks: sequences of
        bool arrays, True = pixel used (None: every finite pixel with σ² > 0).
    host_start: a Source with the smooth component(s) as a start, or None (one Sérsic
        from the data's moments).  lens: the lens (``deflection(θ1, θ2)``) through which
        candidates are mapped to the source plane, or None.
    zeropoints_ab: {band: AB zero point} for mag columns.  options: `AutoOptions`.
    """
    opts = options.validate()
    ctx, u0 = _setup(make_model, data, variances, masks, host_start, lens, opts)
    if ctx.model.lensed:
        require(ctx.model.accuracy.source_mode == "analytic", "make_model (accuracy.source_mode)",
                ctx.model.accuracy.source_mode, '"analytic" for a lensed scene (clumps that '
                'move must render anywhere without a rebuild; see lensed_fit_accuracy)')
    steps = []
    u, lnl = _fit_host(ctx, u0, steps)
    u, lnl, active, n_images = _count(ctx, u, lnl, steps)
    lnl, active = _prune(ctx, u, lnl, active, steps)
    u, lnl, active, n_images = _rehost(ctx, u, u0, lnl, active, n_images, steps)
    if opts.merge:
        u, lnl, active, n_images, shape_trials = _refine(ctx, u, lnl, active, n_images, steps)
        if opts.final_shape and ctx.shape_index is not None:
            u = _shaped_start(ctx, u, active, shape_trials)
    us, lnls, oks, b, jtj, entries = _final(ctx, u, active, steps)
    u, lnl, ok = us[b], float(lnls[b]), bool(oks[b])
    state = masked_state(ctx.param, u, active)
    idx = np.nonzero(active > 0)[0]
    if not opts.errors:
        return AutoFit(_compact(state, idx), ctx.param, None, None, steps, ctx.model, u, active,
                       lnl, ok)
    spread = _spread(ctx, us, lnls, active)
    unc = _uncertainty(ctx, u, jtj, entries)
    prof = (_profile(ctx, u, lnl, active)
            if opts.profile_errors and ctx.shape_index is not None else None)
    if prof:
        steps.append(dict(step=len(steps), action="profile", slot=-1, n_clumps=int(active.sum()),
                          delta_lnL=np.nan, criterion=np.nan, accepted=True, lnL=lnl,
                          chi2_dof=_chi2_dof(ctx, lnl, active.sum()), converged=ok, n_steps=0,
                          profile={str(i): {"d_re_arcsec": v[0].tolist(),
                                            "d_lnL": v[2].tolist()} for i, v in prof.items()}))
    table = _table(ctx, state, unc, idx, np.full(idx.size, ok), spread, n_images, zeropoints_ab,
                   prof)
    table.meta.update({"method": "auto", "criterion": opts.criterion,
                       "threshold": opts.resolved_threshold, "log_likelihood": lnl,
                       "converged": ok, "n_pixels": ctx.n_pix, "max_clumps": opts.max_clumps,
                       "starts_lnL": [float(v) for v in lnls], "starts_near_best": spread[2],
                       "re_bounds_arcsec": list(ctx.re_bounds), "host": host_meta(state),
                       "background_counts_per_s":
                           np.asarray(state.background_counts_per_s, float).tolist()})
    return AutoFit(_compact(state, idx), ctx.param, unc, table, steps, ctx.model, u, active, lnl, ok)


def lensed_fit_accuracy(accuracy):
    """The accuracy a lensed `make_model` needs here: clumps evaluated at every ray."""
    return dataclasses.replace(accuracy, source_mode="analytic")


def fit_clump_pixels(clump_n: float, round_clumps: bool, lensed: bool) -> str:
    """`Accuracy.clump_pixels` for a fit's model: in an unlensed scene whose clumps are round
    (q = 1, no shape fitted), "round_gaussian" for Gaussians (Sérsic n = 0.5: exact) and
    "exponential_mog" for exponentials (n = 1: 8 Gaussians, within 1e-3 of the peak pixel,
    0.01 σ of the S1063 data, benchmarks/results/mog_accuracy.md); else "sersic".

    The separable renderers need no stamps, which makes a Levenberg–Marquardt step of the
    counting fit several times cheaper and its compilation shorter
    (benchmarks/results/bench_fit_auto.md, fit_observations.json), and no clump is cut by a
    stamp however its R_e grows. Any other clump keeps the general Sérsic renderer."""
    if lensed or not round_clumps:
        return "sersic"
    return {0.5: "round_gaussian", 1.0: "exponential_mog"}.get(float(clump_n), "sersic")
