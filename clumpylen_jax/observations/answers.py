"""Physical answers of a fit of observations: positions, sizes, magnitudes, masses, intrinsic values.

Per clump (SCENE.md `fit.ecsv` columns; every value followed by `<name>_err`, 1σ
from the Fisher covariance, or the posterior samples' one where sampled (sample.py),
propagated linearly):
- `x_pix`, `y_pix` (0-based pixels of the first observation), `theta1_arcsec`,
  `theta2_arcsec` (DESIGN.md θ frame, relative to the first observation's centre),
  `ra_deg`, `dec_deg` where there is a celestial WCS;
- `re_arcsec` (observed; intrinsic where a local lens is given), `re_pc` with z_source;
  where the size is unresolved (flag 16), `re_arcsec_ul` (and `re_pc_ul`), its one-sided
  95 % upper limit from the profile of χ² in R_e (`inference.size_limits`), NaN elsewhere;
- `flux_<F>` (data units summed), `mag_<F>` (observed AB). A band where
  flux/σ < detection_snr does not detect the clump: `mag_<F>` is then the upper
  limit ZP − 2.5 log10(max(F, 0) + snr·σ), `mag_<F>_err` NaN and `uplim_<F>` true;
- with a lens (`[lens.local]`, or a lens model placed on the cutout: `observations.lens`):
  `beta1_arcsec`, `beta2_arcsec` (β = A θ; for a model β = θ_L − α(θ_L) from the lens centre),
  `magnification` |μ| at each clump, intrinsic `re_arcsec`/`q_src` (the image ellipse mapped
  through the clump's A), `source_id` and `n_images` (clumps the lens maps to one β:
  images of one source clump, multiple_images.py) and `mag_int_<F>` = mag + 2.5 log10 |μ|;
- with ≥ 2 bands and z_source: `mass_msun`, `age_myr` from the SPS model
  (`photometry.band_fluxes_ujy`): the posterior on a grid of log age × log mass, flat
  in log mass, ages from p(t) ∝ t^α on [t_min, t_max] (the clump population's law, by
  default the simulator's: `defaults.AGES`, scene key `[sps] ages`) cut at the age of the
  universe at z_source; Gaussian flux likelihood with the fit's covariance of the clump's
  fluxes between bands (negative fluxes and upper limits included as they are) and a 5 %
  calibration floor; median, half the 16–84 % width (`_err`) and the 16 and 84 %
  points themselves (`mass_msun_p16`, `mass_msun_p84`, `age_myr_p16`, `age_myr_p84`:
  with two bands the posterior is skewed, several tenths of a dex).
- `flag` (bits of `inference.auto.FLAGS`, as in mock-image fits): 0 fine; 1 the fit did
  not converge (sampled: R̂ of one of the clump's parameters above `sample.RHAT_MAX`); 2
  the R_e hit a prior bound; 4 the clump sits within a pixel of the field's edge; 16 the
  size is unresolved (σ(R_e) > R_e: read `re_arcsec_ul`); 64 the counting found the
  host's light shared otherwise nearly as well (`clumps = "auto"`: a host move rejected for
  its extra clump only) with this clump's flux > 2σ away or gone: its magnitude holds a
  systematic error its σ does not (`inference.auto.FLAGS`);
- where the counting kept such alternatives: `mag_alt_<F>`, the clump's observed AB mag in
  the alternative that moves it most (the range between `mag_<F>` and it is the systematic
  flag 64 warns of); NaN for a clump no alternative moves, and for one the alternative
  gives to the host (flag 64 set, no clump there).
"""

from __future__ import annotations

import numpy as np

from ..inference.catalog import ab_magnitude, ab_magnitude_err
from ..inference.size_limits import re_upper_limits
CALIBRATION_FLOOR = 0.05   # fractional flux error added in quadrature for the SED fit
AGE_GRID = 60
MASS_GRID = 241


def _index(labels):
    return {lab: i for i, lab in enumerate(labels)}


def _cov_block(cov, idx, labels_):
    ii = [idx.get(lab) for lab in labels_]
    out = np.full((len(ii), len(ii)), np.nan)
    for a, i in enumerate(ii):
        for b, j in enumerate(ii):
            if i is not None and j is not None:
                out[a, b] = cov[i, j]
    return out


def _theta_jacobian(frame, phi):
    """dθ/dφ [2, 2] at φ (numerically: the WCS is smooth)."""
    eps = 1e-3
    J = np.empty((2, 2))
    for k in range(2):
        d = np.zeros(2)
        d[k] = eps
        J[:, k] = (frame.theta(phi + d) - frame.theta(phi - d)) / (2 * eps)
    return J


def _ellipse_through(A, re, q, pa):
    """(R_e major, q, pa) of the ellipse (re, q, pa) mapped linearly by A."""
    c, s = np.cos(pa), np.sin(pa)
    R = np.array([[c, -s], [s, c]])
    C = R @ np.diag([re**2, (q * re) ** 2]) @ R.T
    w, v = np.linalg.eigh(A @ C @ A.T)
    w = np.maximum(w, 0.0)
    return float(np.sqrt(w[1])), float(np.sqrt(w[0] / w[1])) if w[1] > 0 else 1.0, \
        float(np.arctan2(v[1, 1], v[0, 1]))


def _param_err(cov, idx, label):
    """1σ of a fitted parameter from the covariance; NaN where `label` was not fitted."""
    i = idx.get(label)
    return float(np.sqrt(cov[i, i])) if i is not None else np.nan


def clump_rows(fit, observations, frame, scene, lens=None, alternatives=()):
    """An astropy Table of the fitted clumps (see the module doc); `lens` as
    `observations.lens.place_lens` returns it (None: no lens); alternatives: the counting's
    `inference.auto.host_alternatives` (flag 64)."""
    from astropy.table import Table

    opts = scene.fit
    t = Table()
    n = fit.n_clumps
    t["id"] = np.arange(n)
    if n == 0:
        return t
    idx = _index(fit.param.labels)
    cov = np.asarray(fit.uncertainty.cov, float)
    cl = fit.state.source.clumps
    phi = np.asarray(cl.center_arcsec, float)
    re = np.asarray(cl.re_arcsec, float)
    q = np.asarray(cl.q, float)
    pa = np.asarray(cl.pa_rad, float)
    # columns are added in fit.ecsv's order: positions, sizes, shapes, photometry, masses, flag
    pix, theta, th_cov = _position_columns(t, frame, phi, cov, idx)
    re_err = np.array([_param_err(cov, idx, f"clumps.re_arcsec[{i}]") for i in range(n)])
    unresolved = re_err > re
    # the σ of an unresolved R_e says nothing: the profile of χ² in R_e bounds it above
    model, state = fit.drawing()
    re_ul = re_upper_limits(model, fit.data, state, np.where(unresolved, np.arange(n), -1),
                            opts.clump_re_max_arcsec)
    pa_theta = np.array([frame.pa_theta(phi[i], pa[i])[0] for i in range(n)])
    mu = None
    if lens is not None:
        from .lens import source_plane
        sp = source_plane(lens, theta)
        mu = np.abs(sp.mu)
        re_obs = re
        re, re_err, b_cov = _source_plane_columns(t, sp, th_cov, re, re_err, q, pa_theta)
        t["re_obs_arcsec_ul"] = re_ul
        re_ul = re_ul * re / re_obs          # through each clump's A, as R_e itself
        from .multiple_images import group_images
        sid = group_images(sp.beta, b_cov, sp.mu, theta, opts.image_match_arcsec,
                           opts.image_separation_min_arcsec)
        t["source_id"] = sid
        t["n_images"] = np.bincount(sid)[sid]
    _size_columns(t, re, re_err, re_ul, scene)
    if opts.clump_shape == "elliptical":
        t["q"] = q
        t["q_err"] = [_param_err(cov, idx, f"clumps.q[{i}]") for i in range(n)]
        t["pa_rad"] = pa_theta
        t["pa_rad_err"] = [_param_err(cov, idx, f"clumps.pa_rad[{i}]") for i in range(n)]
    flux = np.asarray(cl.flux, float)
    f_cov = np.stack([_cov_block(cov, idx, [f"clumps.flux[{i},{b}]"
                                            for b in range(len(observations))])
                      for i in range(n)])                                    # [N, B, B]
    f_err = np.sqrt(np.diagonal(f_cov, axis1=1, axis2=2))
    _photometry_columns(t, flux, f_err, observations, opts.detection_snr, mu)
    if len(observations) >= 2 and scene.z_source is not None:
        _mass_columns(t, flux, f_cov, observations, scene, mu)
    alt = None
    if len(alternatives):
        from ..inference.auto import host_alternative_fluxes
        finest = min(g.pixel_arcsec for g in frame.grids)
        alt, alt_flux = host_alternative_fluxes(phi, flux, f_err, np.asarray(cl.re_arcsec, float),
                                                alternatives, 2.0 * finest)
        _alternative_columns(t, alt_flux, observations)
    t["flag"] = _flags(fit, frame, pix, opts, unresolved, alt)
    return t


def _position_columns(t, frame, phi, cov, idx):
    """Add x/y_pix (first observation's pixels), θ [arcsec] and RA/Dec [deg] with errors;
    returns (pixels [N, 2], θ [N, 2] arcsec, θ covariances [N][2, 2] arcsec²)."""
    n = len(phi)
    pix = frame.pixel_of(phi, 0)
    theta = frame.theta(phi)
    pos_cov = [_cov_block(cov, idx, [f"clumps.center_arcsec[{i},0]", f"clumps.center_arcsec[{i},1]"])
               for i in range(n)]
    J = [_theta_jacobian(frame, phi[i]) for i in range(n)]
    p0 = frame.grids[0].pixel_arcsec
    t["x_pix"] = pix[:, 0]
    t["x_pix_err"] = [np.sqrt(c[0, 0]) / p0 for c in pos_cov]
    t["y_pix"] = pix[:, 1]
    t["y_pix_err"] = [np.sqrt(c[1, 1]) / p0 for c in pos_cov]
    th_cov = [j @ c @ j.T for j, c in zip(J, pos_cov)]
    t["theta1_arcsec"] = theta[:, 0]
    t["theta1_arcsec_err"] = [np.sqrt(c[0, 0]) for c in th_cov]
    t["theta2_arcsec"] = theta[:, 1]
    t["theta2_arcsec_err"] = [np.sqrt(c[1, 1]) for c in th_cov]
    radec = frame.radec(phi)
    if radec is not None:
        cosd = np.cos(np.radians(radec[1]))
        t["ra_deg"] = radec[0]
        t["ra_deg_err"] = np.asarray(t["theta1_arcsec_err"]) / 3600.0 / cosd
        t["dec_deg"] = radec[1]
        t["dec_deg_err"] = np.asarray(t["theta2_arcsec_err"]) / 3600.0
    return pix, theta, th_cov


def _source_plane_columns(t, sp, th_cov, re, re_err, q, pa_theta):
    """Add β [arcsec], |μ| (the lens's, not fitted), the observed R_e and the intrinsic q from
    `sp` (lens.SourcePlane at the clumps); returns the intrinsic (R_e [arcsec], its error): the
    image ellipse mapped through each clump's A; and the β covariances [N][2, 2] arcsec²."""
    n = len(re)
    beta = sp.beta
    b_cov = [A @ c @ A.T for A, c in zip(sp.A, th_cov)]
    t["beta1_arcsec"] = beta[:, 0]
    t["beta1_arcsec_err"] = [np.sqrt(c[0, 0]) for c in b_cov]
    t["beta2_arcsec"] = beta[:, 1]
    t["beta2_arcsec_err"] = [np.sqrt(c[1, 1]) for c in b_cov]
    t["magnification"] = np.abs(sp.mu)
    t["magnification_err"] = np.zeros(n)   # the lens model's, not fitted
    t["re_obs_arcsec"] = re
    t["re_obs_arcsec_err"] = re_err
    src = [_ellipse_through(sp.A[i], re[i], q[i], pa_theta[i]) for i in range(n)]
    scale = np.array([s[0] / re[i] for i, s in enumerate(src)])
    t["q_src"] = [s[1] for s in src]
    return np.array([s[0] for s in src]), re_err * scale, b_cov


def _size_columns(t, re, re_err, re_ul, scene):
    """Add R_e [arcsec] with its error and upper limit and, with z_source, the same in pc."""
    t["re_arcsec"] = re
    t["re_arcsec_err"] = re_err
    t["re_arcsec_ul"] = re_ul
    if scene.z_source is not None:
        from ..cosmology import arcsec_per_pc, make_cosmology
        app = arcsec_per_pc(scene.z_source, make_cosmology(*scene.cosmology))
        t["re_pc"] = re / app
        t["re_pc_err"] = re_err / app
        t["re_pc_ul"] = re_ul / app


def _photometry_columns(t, flux, f_err, observations, detection_snr, mu):
    """Add flux (data units), observed AB mag (upper limit below detection_snr σ), uplim and,
    with |μ| per clump (None: no lens), the intrinsic mag per band."""
    for b, ob in enumerate(observations):
        F, s = flux[:, b], f_err[:, b]
        det = F >= detection_snr * s
        t[f"flux_{ob.name}"] = F
        t[f"flux_{ob.name}_err"] = s
        with np.errstate(divide="ignore", invalid="ignore"):
            mag = np.where(det, ab_magnitude(np.abs(F), ob.zeropoint_ab),
                           ab_magnitude(np.maximum(F, 0) + detection_snr * s, ob.zeropoint_ab))
            mag_err = np.where(det, ab_magnitude_err(np.abs(F), s), np.nan)
        t[f"mag_{ob.name}"] = mag
        t[f"mag_{ob.name}_err"] = mag_err
        t[f"uplim_{ob.name}"] = ~det
        if mu is not None:
            t[f"mag_int_{ob.name}"] = mag + 2.5 * np.log10(mu)
            t[f"mag_int_{ob.name}_err"] = mag_err


def _alternative_columns(t, alt_flux, observations):
    """Add, per band, the observed AB mag each clump has in the counting's host alternative
    that moves it most (flag 64; `inference.auto.host_alternative_fluxes`): NaN where no
    alternative moves it and where the alternative gives its light to the host."""
    for b, ob in enumerate(observations):
        F = alt_flux[:, b]
        t[f"mag_alt_{ob.name}"] = np.where(F > 0, ab_magnitude(np.where(F > 0, F, 1.0),
                                                               ob.zeropoint_ab), np.nan)


def _mass_columns(t, flux, f_cov, observations, scene, mu):
    """Add mass [M☉] and age [Myr] from the SED fit of the fluxes (in μJy) delensed by |μ| per
    clump (None: no lens), with their covariance f_cov [N, B, B] between bands."""
    mu = np.ones(len(flux)) if mu is None else np.asarray(mu, float)
    from ..photometry import AB_ZERO_UJY
    ujy = np.array([10 ** (-0.4 * (ob.zeropoint_ab - AB_ZERO_UJY)) for ob in observations])
    masses = sed_fit(flux * ujy / mu[:, None],
                     f_cov * np.outer(ujy, ujy) / (mu ** 2)[:, None, None],
                     [ob.name for ob in observations], scene.z_source, dict(scene.sps),
                     scene.cosmology, scene.age_prior)
    for key, val in masses.items():
        t[key] = val


def _flags(fit, frame, pix, opts, unresolved, host_alternative=None):
    """The flag bits (module doc; `inference.auto.FLAGS`); `unresolved`: σ(R_e) > R_e;
    `host_alternative`: `inference.auto.host_alternative_fluxes`' flags, or None."""
    from ..inference.auto import FLAGS
    flag = np.zeros(len(pix), int)
    if not fit.success:
        flag |= FLAGS["not_converged"]
    if fit.clump_unconverged is not None:
        flag |= np.where(fit.clump_unconverged, FLAGS["not_converged"], 0)
    g0 = frame.grids[0]
    edge = (pix[:, 0] < 1) | (pix[:, 1] < 1) | (pix[:, 0] > g0.nx - 2) | (pix[:, 1] > g0.ny - 2)
    flag |= np.where(edge, FLAGS["position_at_box_edge"], 0)
    r_obs = np.asarray(fit.state.source.clumps.re_arcsec, float)
    at_bound = (r_obs < 1.02 * opts.clump_re_min_arcsec) | (r_obs > 0.98 * opts.clump_re_max_arcsec)
    flag |= np.where(at_bound, FLAGS["re_at_bound"], 0)
    flag |= np.where(unresolved, FLAGS["size_unresolved"], 0)
    if host_alternative is not None:
        flag |= np.where(host_alternative, FLAGS["host_alternative"], 0)
    return flag


def age_grid_myr(age_prior, z, cosmology=(70.0, 0.3)):
    """(ages [Myr] [AGE_GRID], ln prior weight per age): log-spaced nodes over the prior's
    range cut at the age of the universe at z and at the library's oldest node, weighted by
    p(t) ∝ t^slope (t^(slope+1) per log step). age_prior: (slope, min_myr, max_myr), None:
    `defaults.AGES`."""
    from .. import defaults as D
    from ..cosmology import make_cosmology
    from ..sps import default_library

    from ..errors import ConfigError

    if age_prior is None or len(age_prior) == 0:
        age_prior = (D.AGES["slope"], D.AGES["min_myr"], D.AGES["max_myr"])
    if len(age_prior) != 3:
        raise ConfigError("sps.ages", age_prior, "(slope, min_myr, max_myr)")
    slope, lo, hi = map(float, age_prior)
    universe = float(make_cosmology(*cosmology).age(float(z)).to_value("Myr"))
    hi = min(hi, universe, float(default_library().age_range_myr[1]))
    if not 0 < lo < hi:
        raise ConfigError("sps.ages.min_myr", lo, f"an age in (0, {hi:.0f}) Myr: the prior "
                          f"ends there (the universe's age at z = {z}, or the library's oldest)")
    ages = np.geomspace(lo, hi, AGE_GRID)
    return ages, (slope + 1.0) * np.log(ages)


def sed_fit(flux_ujy, cov_ujy, filters, z, sps_options=None, cosmology=(70.0, 0.3),
            age_prior=None):
    """Mass and age of each clump from its band fluxes (μJy [N, B]) on a grid posterior.

    cov_ujy: the fluxes' covariance between bands (μJy² [N, B, B]: the fit's, Fisher or
    posterior samples'), or their σ (μJy [N, B]: independent bands). The bands of one clump
    share its position and R_e, so their errors are correlated (a larger R_e brightens it in
    every band); that common part cancels in the colours, which fix the age. Taken as
    independent, the errors came out too wide: at correlation 0.9 between 5 bands, 78–95 %
    of the truths within ±1σ, against 64–72 % with the covariance
    (tests/test_sed_fit.py). A CALIBRATION_FLOOR of each positive flux is added in
    quadrature (independent per band).

    age_prior: (slope, min_myr, max_myr) of p(t) ∝ t^slope (`age_grid_myr`; None: the
    simulator's clump ages, `defaults.AGES`). Where the colours barely move with age (two
    rest-UV bands) the posterior is the prior's, and M/L spans ~1 dex over 1–100 Myr: the
    prior used before, flat in log age out to the library's 14 Gyr, put the masses of HST
    F606W + F814W mocks at z = 2 0.15–0.4 dex low, depending on the mocks' ages
    (tests/test_sed_fit.py; benchmarks/README.md).

    Returns {mass_msun, mass_msun_err, mass_msun_p16, mass_msun_p84, age_myr, …} arrays
    [N]: median, half the 16–84 % width, the 16 and 84 % points; NaN where no band has
    positive flux or the covariance is not finite.
    """
    from ..cosmology import make_cosmology
    from ..photometry import band_fluxes_ujy

    ages, ln_prior = age_grid_myr(age_prior, z, cosmology)
    model = np.asarray(band_fluxes_ujy(np.ones_like(ages), ages, filters=list(filters), z=float(z),
                                       cosmology=make_cosmology(*cosmology),
                                       **(sps_options or {})), float)      # [A, B] per M☉
    F = np.asarray(flux_ujy, float)
    C = np.asarray(cov_ujy, float)
    if C.ndim == 2:                                       # σ per band: independent bands
        C = C[:, :, None] ** 2 * np.eye(F.shape[1])
    C = C + ((CALIBRATION_FLOOR * np.clip(F, 0, None)) ** 2)[:, :, None] * np.eye(F.shape[1])
    out = {f"{k}{s}": np.full(F.shape[0], np.nan) for k in ("mass_msun", "age_myr")
           for s in ("", "_err", "_p16", "_p84")}
    for i in range(F.shape[0]):
        if not np.any(F[i] > 0) or not np.all(np.isfinite(C[i])):
            continue
        W = np.linalg.pinv(C[i], hermitian=True)
        mwf, mwm = model @ W @ F[i], np.einsum("ab,bc,ac->a", model, W, model)    # [A]
        # the mass grid's centre from independent bands: with correlated ones the best mass
        # at an age can be ≤ 0 (colours no age matches, within tight colour errors)
        w = 1.0 / np.diagonal(C[i])
        mhat = np.clip((model * w) @ F[i] / ((model**2) @ w), 1e-30, None)
        logm = np.log10(np.median(mhat)) + np.linspace(-3, 3, MASS_GRID)
        m = 10 ** logm
        # χ² = (F − m f_a)ᵀ W (F − m f_a), expanded in m   [A, M]
        chi2 = F[i] @ W @ F[i] - 2.0 * mwf[:, None] * m + mwm[:, None] * m ** 2
        ln_post = -0.5 * chi2 + ln_prior[:, None]
        post = np.exp(ln_post - ln_post.max())
        post /= post.sum()
        for key, axis_vals, axis in (("mass_msun", logm, 0), ("age_myr", np.log10(ages), 1)):
            cdf = np.cumsum(post.sum(axis=axis))
            q16, q50, q84 = 10 ** np.interp([0.16, 0.5, 0.84], cdf, axis_vals)
            out[key][i], out[f"{key}_err"][i] = q50, 0.5 * (q84 - q16)
            out[f"{key}_p16"][i], out[f"{key}_p84"][i] = q16, q84
    return out


def host_summary(fit, observations, frame):
    """The fitted host (flux and magnitude per band, R_e, n, q, PA, centre) with 1σ errors."""
    h = fit.state.source.bulge
    if h is None:
        return None
    idx = _index(fit.param.labels)
    cov = np.asarray(fit.uncertainty.cov, float)

    def err(label):
        i = idx.get(label)
        return float(np.sqrt(cov[i, i])) if i is not None else None

    c = np.asarray(h.center_arcsec, float)
    th = frame.theta(c)
    out = dict(re_arcsec=float(h.re_arcsec), re_arcsec_err=err("bulge.re_arcsec[]"),
               n=float(h.n), n_err=err("bulge.n[]"), q=float(h.q), q_err=err("bulge.q[]"),
               pa_rad=float(frame.pa_theta(c, float(h.pa_rad))[0]), pa_rad_err=err("bulge.pa_rad[]"),
               theta1_arcsec=float(th[0]), theta2_arcsec=float(th[1]),
               center_err_arcsec=[err("bulge.center_arcsec[0]"), err("bulge.center_arcsec[1]")],
               x_pix=float(frame.pixel_of(c, 0)[0]), y_pix=float(frame.pixel_of(c, 0)[1]))
    rd = frame.radec(c)
    if rd is not None:
        out.update(ra_deg=float(rd[0]), dec_deg=float(rd[1]))
    for b, ob in enumerate(observations):
        F = float(h.flux[b])
        e = err(f"bulge.flux[{b}]")
        out[f"flux_{ob.name}"] = F
        out[f"flux_{ob.name}_err"] = e
        out[f"mag_{ob.name}"] = float(ab_magnitude(F, ob.zeropoint_ab)) if F > 0 else None
        out[f"mag_{ob.name}_err"] = float(ab_magnitude_err(F, e)) if (e is not None and F > 0) else None
    return out
