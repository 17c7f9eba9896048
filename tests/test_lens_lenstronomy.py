"""The analytic lenses against lenstronomy, an independent implementation (issue 21, item 5).

Deflection α, convergence κ, shear (γ1, γ2) and det A = 1/μ of SIS, SIE, NFW, dPIE
and external shear, and of the built-in look-alike clusters, on a grid of points that
includes points near the centres (1e-3 of the scale radius: lenstronomy floors r at
1e-4 for the PJaffe and loses digits to cancellation in the NFW closed form below
x ~ 1e-3, where ours switches to a series) and points on the Einstein radius.

Parameter mapping, ours -> lenstronomy (lenstronomy 1.14 source and docstrings):
- SIS: theta_e_arcsec -> 'SIS' theta_E (|α| = θ_E in both).
- SIE: ours κ = θ_E / (2 sqrt(q x'² + y'²/q)) (intermediate-axis θ_E). lenstronomy
  'EPL' with gamma = 2 has κ = (3−γ)/2 · (θ_E / sqrt(q x² + y²/q))^(γ−1)
  (lenstronomy.LensModel.Profiles.epl.EPL docstring; `_param_conv`: b = θ_E sqrt(q)
  in Tessore & Metcalf 2015's R = sqrt(q² x² + y²)), the same θ_E; its
  deflection (hyp2f1) and Hessian are analytic. lenstronomy's 'SIE' would route
  through the NIE with a finite-difference Hessian, so 'EPL' is the analytic check.
  Ellipticity: e1, e2 = (1−q)/(1+q) (cos 2φ, sin 2φ) with φ = pa_rad
  (`lenstronomy.Util.param_util.phi_q2_ellipticity`; both measure φ CCW from +x,
  `util.rotate` uses x' = x cos φ + y sin φ as our `_to_frame`).
- NFW: ours (κ_s, r_s) -> 'NFW' Rs = r_s, alpha_Rs = 4 κ_s r_s (1 + ln ½)
  (`NFW.alpha2rho0`: ρ0 = α_Rs / (4 Rs² (1 + ln ½)), κ_s = ρ0 Rs).
- dPIE, round: ours κ = (b0/2) r_cut/(r_cut − r_core) [1/sqrt(r_core² + R²) − 1/sqrt(r_cut² + R²)]
  (Elíasdóttir et al. 2007); lenstronomy 'PJAFFE' κ = σ0 Ra Rs/(Rs − Ra) [same bracket]
  (`PseudoJaffe.hessian`), so Ra = r_core, Rs = r_cut, sigma0 = b0 / (2 r_core).
- dPIE, elliptical: the difference of two cored isothermal ellipsoids. lenstronomy's
  'NIE' has κ = θ_E/2 [s² + q x² + y²/q]^(−1/2) (its docstring; `_param_conv`), so
  dPIE = NIE(θ_E = w b0, s = r_core) + NIE(θ_E = −w b0, s = r_cut), w = r_cut/(r_cut − r_core).
  ('PJAFFE_ELLIPSE_POTENTIAL' is elliptical in the potential: a different lens.)
- External shear: 'SHEAR' gamma1, gamma2, ra_0, dec_0 (α = (γ1 x + γ2 y, γ2 x − γ1 y)).
- A `scale` (D_ls/D_s ratio) multiplies θ_E, alpha_Rs, sigma0 and γ (all enter linearly).

Tolerances: where both sides are analytic (all but the NIE's second derivatives),
1e-8 relative, with an absolute floor of 1e-8 × a typical value (components pass through
zero): × 1 for κ, γ and det A, × the largest |α| for α. lenstronomy's NIE Hessian is a one-sided finite difference with step
1e-10 (`NIEMajorAxis.hessian`), good to ~1e-6 only, so for elliptical dPIEs κ, γ and
det A are compared with lenstronomy's central differences of its analytic deflection
(`LensModel.hessian(diff=1e-6, diff_method='cross')`: truncation ~1e-10 relative at these
scales, rounding ~1e-11): 1e-7 relative; and κ also with lenstronomy's analytic NIE κ
(`NIEMajorAxis.kappa`) at 1e-8. μ itself is compared where |μ| < 1e3 (near a critical
line it is ill-conditioned: det A carries the comparison there).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from clumpylen_jax.lensing import DPIE, NFW, SIE, SIS, ExternalShear, LensSum, lensing_quantities
from clumpylen_jax.lensing.clusters import builtin_lens, builtin_names, load_builtin_spec

lenstronomy = pytest.importorskip("lenstronomy", reason="lenstronomy (test extra) not installed")
from lenstronomy.LensModel.lens_model import LensModel  # noqa: E402
from lenstronomy.LensModel.Profiles.nie import NIE, NIEMajorAxis  # noqa: E402
from lenstronomy.Util import param_util  # noqa: E402

RTOL = 1e-8           # both analytic
RTOL_NUMERIC = 1e-7   # against lenstronomy's central differences of its analytic deflection
C = (0.3, -0.2)       # lens centre, arcsec


# --- parameter mapping ---------------------------------------------------------------

def _e1e2(q, pa_rad):
    return param_util.phi_q2_ellipticity(float(pa_rad), float(q))


def _nie_pair(b0, rcore, rcut, q, pa_rad, center, scale=1.0):
    """lenstronomy NIE components of one dPIE (see the module docstring)."""
    w = rcut / (rcut - rcore)
    e1, e2 = _e1e2(q, pa_rad)
    base = dict(e1=e1, e2=e2, center_x=float(center[0]), center_y=float(center[1]))
    return (["NIE", "NIE"],
            [dict(theta_E=scale * w * b0, s_scale=rcore, **base),
             dict(theta_E=-scale * w * b0, s_scale=rcut, **base)])


def to_lenstronomy(kind, p, scale=1.0):
    """(model list, kwargs list) of lenstronomy for one of our components (plain dict)."""
    cx, cy = (float(v) for v in p.get("center_arcsec", (0.0, 0.0)))
    if kind == "sis":
        return ["SIS"], [dict(theta_E=scale * p["theta_e_arcsec"], center_x=cx, center_y=cy)]
    if kind == "sie":
        e1, e2 = _e1e2(p["q"], p["pa_rad"])
        return ["EPL"], [dict(theta_E=scale * p["theta_e_arcsec"], gamma=2.0, e1=e1, e2=e2,
                              center_x=cx, center_y=cy)]
    if kind == "nfw":
        alpha_rs = 4.0 * p["kappa_s"] * p["rs_arcsec"] * (1.0 + np.log(0.5))
        return ["NFW"], [dict(Rs=p["rs_arcsec"], alpha_Rs=scale * alpha_rs, center_x=cx, center_y=cy)]
    if kind == "dpie_round" or (kind == "dpie" and p["q"] == 1.0 and p["rcore_arcsec"] > 0):
        # (lenstronomy's NIE replaces q = 1 by 0.99999999: the round PJaffe is exact)
        return ["PJAFFE"], [dict(sigma0=scale * p["b0_arcsec"] / (2.0 * p["rcore_arcsec"]),
                                 Ra=p["rcore_arcsec"], Rs=p["rcut_arcsec"], center_x=cx, center_y=cy)]
    if kind == "dpie":
        return _nie_pair(p["b0_arcsec"], p["rcore_arcsec"], p["rcut_arcsec"], p["q"], p["pa_rad"],
                         (cx, cy), scale)
    if kind == "shear":
        return ["SHEAR"], [dict(gamma1=scale * p["gamma1"], gamma2=scale * p["gamma2"], ra_0=cx, dec_0=cy)]
    raise KeyError(kind)


# --- the lenses and the points ---------------------------------------------------------

CASES = {
    # name: (kind, our lens, parameters, a radius where something happens: θ_E, r_s or r_core)
    "sis": ("sis", dict(theta_e_arcsec=1.5, center_arcsec=C), 1.5),
    "sie": ("sie", dict(theta_e_arcsec=1.5, q=0.7, pa_rad=0.4, center_arcsec=C), 1.5),
    "sie_flat": ("sie", dict(theta_e_arcsec=0.8, q=0.25, pa_rad=-1.2, center_arcsec=C), 0.8),
    "nfw": ("nfw", dict(kappa_s=0.3, rs_arcsec=5.0, center_arcsec=C), 5.0),
    "dpie_round": ("dpie_round", dict(b0_arcsec=2.0, rcore_arcsec=0.1, rcut_arcsec=20.0, q=1.0,
                                       pa_rad=0.0, center_arcsec=C), 2.0),
    "dpie": ("dpie", dict(b0_arcsec=2.0, rcore_arcsec=0.1, rcut_arcsec=20.0, q=0.6, pa_rad=0.3,
                          center_arcsec=C), 2.0),
    "shear": ("shear", dict(gamma1=0.05, gamma2=-0.03, center_arcsec=C), 1.0),
}


def _ours(kind, p):
    f = {k: jnp.asarray(v, jnp.float64) for k, v in p.items()}
    if kind == "sis":
        return SIS(f["theta_e_arcsec"], f["center_arcsec"])
    if kind == "sie":
        return SIE(f["theta_e_arcsec"], f["q"], f["pa_rad"], f["center_arcsec"])
    if kind == "nfw":
        return NFW(f["kappa_s"], f["rs_arcsec"], f["center_arcsec"])
    if kind in ("dpie", "dpie_round"):
        return DPIE(f["b0_arcsec"], f["rcore_arcsec"], f["rcut_arcsec"], f["q"], f["pa_rad"],
                    f["center_arcsec"])
    return ExternalShear(f["gamma1"], f["gamma2"], f["center_arcsec"])


def _points(center, radius, span):
    """A grid over ±span (offset so that no point is a centre), a ring of 16 points at
    `radius`, and points at 1e-3 `radius` and at (1 ± 1e-4) `radius` from the centre."""
    g = np.linspace(-span, span, 11) + 0.0173 * span
    t1, t2 = np.meshgrid(g, g)
    phi = np.linspace(0, 2 * np.pi, 16, endpoint=False) + 0.1
    r = np.concatenate([np.full(16, radius), [1e-3 * radius, 1e-3 * radius,
                                              (1 - 1e-4) * radius, (1 + 1e-4) * radius]])
    phi = np.concatenate([phi, [0.3, 2.0, 1.0, 1.0]])
    t1 = np.concatenate([t1.ravel(), center[0] + r * np.cos(phi)])
    t2 = np.concatenate([t2.ravel(), center[1] + r * np.sin(phi)])
    return t1, t2


def _close(ours, ref, rtol, name, scale=1.0):
    """|ours − ref| ≤ rtol (|ref| + scale): relative, with a floor of rtol × a typical value
    (components pass through zero): 1 for κ, γ and det A, the largest |α| for α."""
    ours, ref = np.asarray(ours, float), np.asarray(ref, float)
    np.testing.assert_allclose(ours, ref, rtol=rtol, atol=rtol * scale, err_msg=name)


def _kappa_closed_form(models, kwargs, t1, t2):
    """lenstronomy's κ with no numerical derivative: the NIE's closed-form κ (its own
    parameter conversion included), the analytic Hessian of every other profile."""
    nie, kappa = NIE(), 0.0
    for model, kw in zip(models, kwargs):
        if model == "NIE":
            b, s, q, phi = nie.param_conv(kw["theta_E"], kw["e1"], kw["e2"], kw["s_scale"])
            x, y = t1 - kw["center_x"], t2 - kw["center_y"]
            xr, yr = x * np.cos(phi) + y * np.sin(phi), -x * np.sin(phi) + y * np.cos(phi)
            kappa = kappa + NIEMajorAxis.kappa(xr, yr, b, s, q)
        else:
            fxx, _, _, fyy = LensModel([model]).hessian(t1, t2, [kw])
            kappa = kappa + 0.5 * (fxx + fyy)
    return kappa


def _compare(lens, models, kwargs, t1, t2, numeric_hessian=False, label=""):
    lm = LensModel(models)
    # one compiled call: op-by-op dispatch of the jvp costs seconds per lens
    (a1, a2), m = jax.jit(lambda x, y: (lens.deflection(x, y), lensing_quantities(lens, x, y)))(
        jnp.asarray(t1), jnp.asarray(t2))
    r1, r2 = lm.alpha(t1, t2, kwargs)
    amax = float(np.max(np.hypot(r1, r2)))
    _close(a1, r1, RTOL, f"{label} alpha1", amax)
    _close(a2, r2, RTOL, f"{label} alpha2", amax)

    if numeric_hessian:
        fxx, fxy, fyx, fyy = lm.hessian(t1, t2, kwargs, diff=1e-6, diff_method="cross")
        fxy = 0.5 * (fxy + fyx)
        tol = RTOL_NUMERIC
    else:
        fxx, fxy, _, fyy = lm.hessian(t1, t2, kwargs)
        tol = RTOL
    _close(m.kappa, 0.5 * (fxx + fyy), tol, f"{label} kappa")
    _close(m.gamma1, 0.5 * (fxx - fyy), tol, f"{label} gamma1")
    _close(m.gamma2, fxy, tol, f"{label} gamma2")
    det = (1 - fxx) * (1 - fyy) - fxy * fxy
    _close(m.det, det, tol, f"{label} det A")
    ok = np.abs(det) > 1e-3
    np.testing.assert_allclose(np.asarray(m.mu)[ok], 1.0 / det[ok], rtol=1e3 * tol, err_msg=f"{label} mu")
    return m


@pytest.mark.parametrize("name", sorted(CASES))
def test_lens_matches_lenstronomy(name):
    kind, p, radius = CASES[name]
    lens = _ours(kind, p)
    models, kwargs = to_lenstronomy(kind, p)
    t1, t2 = _points(p["center_arcsec"], radius, 3.0 * radius)
    m = _compare(lens, models, kwargs, t1, t2, numeric_hessian=(kind == "dpie"), label=name)
    if kind == "dpie":
        _close(m.kappa, _kappa_closed_form(models, kwargs, t1, t2), RTOL, f"{name} kappa (closed form)")
    if kind in ("sis", "sie"):
        # the Einstein-radius ring of the SIS is a critical line: det A = 0 there
        if kind == "sis":
            np.testing.assert_allclose(np.asarray(m.det)[121:137], 0.0, atol=1e-12)


@pytest.mark.parametrize("name", builtin_names())
def test_builtin_cluster_matches_lenstronomy_sum(name):
    """The look-alike clusters (sums of elliptical dPIEs and a shear, times D_ls/D_s)."""
    z_source = 3.0
    lens = builtin_lens(name, z_source)
    assert isinstance(lens, LensSum)
    scale = float(lens.scale)
    models, kwargs = [], []
    centres = []
    for comp in load_builtin_spec(name)["components"]:
        p = {k: v for k, v in comp.items() if k != "kind"}
        mod, kw = to_lenstronomy(comp["kind"], p, scale=scale)
        models += mod
        kwargs += kw
        if "center_arcsec" in p and comp["kind"] != "shear":
            centres.append((p["center_arcsec"], p["rcore_arcsec"]))
    # A grid over the cluster field and points near every halo centre: 0.5″ and
    # max(1 mas, 2 r_core) (closer in, the central differences of the reference lose digits
    # inside a 3-5 mas core; the single-lens test covers 1e-3 θ_E at analytic precision).
    g = np.linspace(-60, 60, 13) + 0.37
    t1, t2 = (a.ravel() for a in np.meshgrid(g, g))
    near = np.array([[c[0] + d, c[1] - d / 2] for c, rc in centres for d in (max(1e-3, 2 * rc), 0.5)])
    t1 = np.concatenate([t1, near[:, 0]])
    t2 = np.concatenate([t2, near[:, 1]])
    m = _compare(lens, models, kwargs, t1, t2, numeric_hessian=True, label=name)
    _close(m.kappa, _kappa_closed_form(models, kwargs, t1, t2), RTOL, f"{name} kappa (closed form)")
