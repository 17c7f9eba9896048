"""Surface-brightness profiles: Sérsic (exact b(n)), spiral-arm modulation, Perlin texture.

All profiles are parametrised by total flux (DESIGN.md, "Total flux, not I_e").
Coordinates are arcsec; surface brightness is flux per arcsec². Ellipses follow
DESIGN.md: R_e along the major axis, q = b/a, position angle of the major axis
counter-clockwise from +θ1 (or +β1).

Numerical safety: radii and angles use "double-where" forms so that a sample
exactly at a profile centre, or q = 1, gives finite values and gradients.
"""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammainc, gammaln

from . import incgamma

# ---------------------------------------------------------------- incomplete gamma


def _newton_step(_, state):
    """One Newton step in log x on P(a, x) = p; a and p ride in the loop state."""
    a, p, logx = state
    return a, p, _newton_update(a, p, logx, gammainc)


def _series_newton_step(_, state):
    """`_newton_step` with P by its power series (x ≤ a: `incgamma.p_lower_series`)."""
    a, p, logx = state
    return a, p, _newton_update(a, p, logx, incgamma.p_lower_series)


def _newton_update(a, p, logx, lower_gamma):
    """log x after one Newton step on P(a, x) = p, P by `lower_gamma` (a function (a, x))."""
    x = jnp.exp(logx)
    f = lower_gamma(a, x) - p
    # dP/dlogx = x^a e^-x / Γ(a), evaluated in logs to avoid overflow.
    dlog = jnp.exp(a * logx - x - gammaln(a))
    delta = f / jnp.maximum(dlog, jnp.finfo(x.dtype).tiny)
    return logx - jnp.clip(delta, -2.0, 2.0)


def _newton_gammainc_inverse(a, p, x0, iterations, step=_newton_step):
    """x with P(a, x) = p by Newton steps in log x (keeps x > 0). No gradient.

    The loop body is a module-level function, not a closure: fori_loop caches its
    compiled body by the function object, and a closure made per call recompiled (and
    leaked JIT code memory) on every eager call.
    """
    a = jax.lax.stop_gradient(a)
    p = jax.lax.stop_gradient(p)
    a, p, x0 = jnp.broadcast_arrays(a, p, x0)
    return jnp.exp(jax.lax.fori_loop(0, iterations, step, (a, p, jnp.log(x0)))[2])


def _implicit_polish(a, p, x, lower_gamma=gammainc):
    """One Newton step through which gradients flow: exact implicit derivatives at the root."""
    x = jax.lax.stop_gradient(x)
    dpdx = jnp.exp((a - 1) * jnp.log(x) - x - gammaln(a))
    dpdx = jax.lax.stop_gradient(dpdx)
    return x - (lower_gamma(a, x) - p) / dpdx


@jax.jit
def sersic_b(n):
    """b(n) solving γ(2n, b) = Γ(2n)/2, so that R_e is the half-light radius.

    Exact to float precision for 0.2 ≤ n ≤ 10 (Newton iterations on the
    regularised incomplete gamma function) with an implicit derivative in n.
    Initial guesses: Ciotti & Bertin (1999) asymptotic series for n ≥ 0.36,
    MacArthur, Courteau & Holtzman (2003) polynomial below.
    """
    n = jnp.asarray(n)
    dtype = n.dtype if jnp.issubdtype(n.dtype, jnp.floating) else jnp.float64
    n = n.astype(dtype)
    cb = (2 * n - 1 / 3 + 4 / (405.0 * n) + 46 / (25515.0 * n**2)
          + 131 / (1148175.0 * n**3) - 2194697 / (30690717750.0 * n**4))
    mac = 0.01945 - 0.8902 * n + 10.95 * n**2 - 19.67 * n**3 + 13.43 * n**4
    guess = jnp.where(n >= 0.36, cb, jnp.maximum(mac, 1e-3))
    a = 2 * n
    half = jnp.asarray(0.5, dtype)
    # P by its series: b < 2n = a, where it converges, and compiles in a third of the time
    b = _newton_gammainc_inverse(a, half, jax.lax.stop_gradient(guess), 12,
                                 _series_newton_step)
    return _implicit_polish(a, half, b, incgamma.p_lower_series)


@jax.jit
def gammainc_inverse(a, p):
    """x with P(a, x) = p, 0 < p < 1, differentiable (implicit) in a and p."""
    a = jnp.asarray(a)
    p = jnp.asarray(p, a.dtype)
    # Wilson–Hilferty start, clipped positive; Newton in log x does the rest.
    from jax.scipy.special import ndtri
    z = ndtri(p)
    wh = a * (1 - 1 / (9 * a) + z / (3 * jnp.sqrt(a))) ** 3
    small = (p * jnp.exp(gammaln(a + 1))) ** (1 / a)
    guess = jnp.where(wh > 0.5, wh, jnp.maximum(small, 1e-30))
    x = _newton_gammainc_inverse(a, p, jax.lax.stop_gradient(guess), 40)
    return _implicit_polish(a, p, x)


# ---------------------------------------------------------------- geometry


def safe_sqrt(x2):
    """sqrt with a zero (not NaN) gradient at 0."""
    ok = x2 > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x2, 1.0)), 0.0)


def safe_pow(x, p):
    """x**p for x ≥ 0 with a finite gradient at x = 0 (returns 0 there).

    float64 as exp(p ln x): XLA's CPU code calls libm's scalar pow per element (48 ns
    against 20 ns, ~4 % of a cold `simulate`'s CPU), and exp(p ln x) is within 1.2e-14 of
    it for the profiles' p ≤ 5. float32 keeps pow: exp(p ln x) is 6e-6 off there."""
    ok = x > 0
    xs = jnp.where(ok, x, 1.0)
    if jnp.result_type(xs) == jnp.float64:
        return jnp.where(ok, jnp.exp(p * jnp.log(xs)), 0.0)
    return jnp.where(ok, xs ** p, 0.0)


def safe_atan2(y, x):
    """arctan2 with a finite gradient at the origin (angle 0 there)."""
    ok = (x != 0) | (y != 0)
    return jnp.where(ok, jnp.arctan2(jnp.where(ok, y, 0.0), jnp.where(ok, x, 1.0)), 0.0)


def to_ellipse_frame(x1, x2, center1, center2, pa_rad):
    """Coordinates along the major (u) and minor (v) axes of an ellipse centred at `center`."""
    dx = x1 - center1
    dy = x2 - center2
    c = jnp.cos(pa_rad)
    s = jnp.sin(pa_rad)
    return dx * c + dy * s, -dx * s + dy * c


def elliptical_radius2(x1, x2, center1, center2, q, pa_rad):
    """Squared circularised radius u² + (v/q)² (arcsec²); R_e is measured along the major axis."""
    u, v = to_ellipse_frame(x1, x2, center1, center2, pa_rad)
    return u * u + (v / q) ** 2


# ---------------------------------------------------------------- Sérsic


def sersic_log_norm(flux, re_arcsec, n, q, b):
    """log of I(r=0)/flux for a Sérsic of unit flux: I(r) = flux·exp(lognorm − b (r/R_e)^(1/n)).

    Total flux F = 2π q R_e² n Γ(2n) e^{b} b^{-2n} I_e (Graham & Driver 2005).
    """
    return (-jnp.log(2 * jnp.pi * q * re_arcsec**2 * n) - gammaln(2 * n)
            + 2 * n * jnp.log(b))


def sersic_brightness(x1, x2, *, flux, re_arcsec, n, q, pa_rad, center1, center2, b=None):
    """Surface brightness (flux/arcsec²) of an elliptical Sérsic at (x1, x2) arcsec."""
    if b is None:
        b = sersic_b(n)
    r2 = elliptical_radius2(x1, x2, center1, center2, q, pa_rad)
    s = safe_pow(r2 / re_arcsec**2, 0.5 / n)
    return flux * jnp.exp(sersic_log_norm(flux, re_arcsec, n, q, b) - b * s)


def sersic_radius_enclosing_np(fraction, re_arcsec, n):
    """Major-axis radius (arcsec) holding `fraction` of a Sérsic's light (numpy, scipy;
    for build-time decisions such as stamp and field sizes)."""
    from scipy.special import gammaincinv
    n = np.asarray(n, float)
    return np.asarray(re_arcsec, float) * (gammaincinv(2 * n, fraction)
                                           / gammaincinv(2 * n, 0.5)) ** n


def sersic_axis_rms_per_re_np(n) -> float:
    """Per-axis rms radius of a round Sérsic of index n, in units of its R_e (numpy, scipy;
    build time): √(Γ(4n) / (2 b²ⁿ Γ(2n))) (0.849 for n = 0.5, 1.03 for n = 1)."""
    from scipy.special import gammaincinv, gammaln
    b = gammaincinv(2 * n, 0.5)
    return float(np.sqrt(0.5 * np.exp(gammaln(4 * n) - gammaln(2 * n) - 2 * n * np.log(b))))


def sersic_radius_enclosing(fraction, re_arcsec, n, b=None):
    """Major-axis radius (arcsec) enclosing `fraction` of a Sérsic's flux."""
    if b is None:
        b = sersic_b(n)
    x = gammainc_inverse(2 * n, fraction)
    return re_arcsec * (x / b) ** n


# ---------------------------------------------------------------- exact pixel integrals

_FAN_NODES = 16
_FAR_RE = 1e7        # fan rays are cut at this many R_e


def _edge_spans(ax, ay, bx, by):
    """Signed angle (radians) subtended at the origin by segment A→B; 0 if degenerate."""
    cross = ax * by - ay * bx
    dot = ax * bx + ay * by
    degenerate = (cross == 0) | ((ax == 0) & (ay == 0)) | ((bx == 0) & (by == 0))
    dphi = jnp.arctan2(jnp.where(degenerate, 0.0, cross), jnp.where(degenerate, 1.0, dot))
    return jnp.where(degenerate, 0.0, dphi), degenerate


def _edge_light(ax, ay, bx, by, dphi, degenerate, re, n, b, nodes, weights, q_or_p, lower):
    """∫ dφ Q(R(φ)) over the span of segment A→B seen from the origin (Gauss–Legendre in φ),
    or ∫ dφ P(R(φ)) where `lower` (a bool broadcast to the edges [..., 4]).

    Q = 1 − P(2n, b (R/R_e)^{1/n}), the fraction of light outside R along a ray;
    R(φ) is where the ray at angle φ meets the edge's line. q_or_p(x, lower): Q or P.
    """
    phi_a = safe_atan2(ay, ax)
    ex, ey = bx - ax, by - ay
    elen = safe_sqrt(ex * ex + ey * ey)
    elen = jnp.where(elen > 0, elen, 1.0)
    nx_, ny_ = ey / elen, -ex / elen  # unit normal of the edge's line
    d = jnp.abs(ax * nx_ + ay * ny_)  # the line's distance from the origin
    phi = phi_a[..., None] + dphi[..., None] * nodes
    cosang = jnp.abs(jnp.cos(phi) * nx_[..., None] + jnp.sin(phi) * ny_[..., None])
    # Rays nearly parallel to the edge meet it far away: cap R at _FAR_RE·R_e (beyond it
    # Q < 1e-24 for every n ≤ 10), so that b (R/R_e)^{1/n} stays finite in float32 (n = 0.2:
    # a power of 5) and no inf meets a zero cotangent (NaN gradients). Degenerate edges
    # (through the centre) hold no light; their rays stay out of the division.
    floor = jnp.maximum(d / (_FAR_RE * re), jnp.finfo(cosang.dtype).tiny)
    cosang = jnp.where(degenerate[..., None], 1.0, jnp.maximum(cosang, floor[..., None]))
    radius = jnp.where(degenerate[..., None], 0.0, d[..., None] / cosang)
    x = b * safe_pow(radius / re, 1.0 / n)
    # Q(a, 0) = 1, but the derivatives of the incomplete gamma function at x = 0 are
    # infinite or NaN for a ≤ 1: keep x = 0 out of them, and x near the subnormals too
    # (jitted CPU code flushes those to 0 in some ops and not others: NaN gradients; met
    # in float32 at the centre of a R_e = 1e3 pixel n = 0.2 profile). P < 1e-12 there.
    positive = x > incgamma.x_floor(x.dtype)
    xs = jnp.where(positive, x, 1.0)
    lower = lower[..., None]
    g = jnp.where(positive, q_or_p(xs, lower), jnp.where(lower, 0.0, 1.0))
    return dphi * jnp.sum(g * weights, axis=-1)


def sersic_pixel_flux_exact(x_lo, x_hi, y_lo, y_hi, *, flux, re_arcsec, n, q, pa_rad,
                            center1, center2, b=None, nodes=_FAN_NODES, q_table=None,
                            q_index=None):
    """Flux of one elliptical Sérsic inside axis-aligned pixels [x_lo, x_hi] × [y_lo, y_hi].

    Pixel bounds are arrays of any (common) shape, in arcsec; profile parameters
    are scalars (vmap over profiles). See `sersic_quad_flux_exact`.
    """
    xs = jnp.stack(jnp.broadcast_arrays(x_lo, x_hi, x_hi, x_lo), axis=-1)
    ys = jnp.stack(jnp.broadcast_arrays(y_lo, y_lo, y_hi, y_hi), axis=-1)
    return sersic_quad_flux_exact(xs, ys, flux=flux, re_arcsec=re_arcsec, n=n, q=q,
                                  pa_rad=pa_rad, center1=center1, center2=center2, b=b,
                                  nodes=nodes, q_table=q_table, q_index=q_index,
                                  counterclockwise=True)


def sersic_quad_flux_exact(xs, ys, *, flux, re_arcsec, n, q, pa_rad, center1, center2, b=None,
                           nodes=_FAN_NODES, q_table=None, q_index=None, counterclockwise=False):
    """Flux of one elliptical Sérsic inside convex quadrilaterals with corners (xs, ys).

    xs, ys: [..., 4] corners in order around each quadrilateral (either sense unless
    `counterclockwise`), arcsec; profile parameters are scalars (vmap over profiles). Exact
    up to a smooth 1-D angular quadrature: in the frame where the ellipse is a circle the
    quadrilateral is another one, and its light is the signed sum over its edges of the
    light in the triangle (centre, edge), whose radial integral is the regularised
    incomplete gamma function. No sample sits on the cusp, whatever R_e and n.
    Quadrilaterals holding the centre sum P = light inside; the others use Q = 1 − P
    and the winding number, which keeps relative precision in the wings.
    q_table: an `incgamma.QTable` of Q(2n, ·) (made here when None); q_index: this
    profile's order in it when it holds several (inside a vmap over profiles).
    """
    if b is None:
        b = sersic_b(n)
    if q_table is None:
        q_table = incgamma.q_table(2 * jnp.asarray(n, jnp.result_type(re_arcsec, float)))
    gl_x, gl_w = np.polynomial.legendre.leggauss(nodes)
    dtype = jnp.result_type(xs, re_arcsec)
    t = jnp.asarray((gl_x + 1) / 2, dtype)
    w = jnp.asarray(gl_w / 2, dtype)
    if not counterclockwise:
        # the fan's signs assume counter-clockwise corners: reverse the clockwise ones
        area2 = jnp.sum(xs * jnp.roll(ys, -1, axis=-1) - jnp.roll(xs, -1, axis=-1) * ys, axis=-1)
        flip = (area2 < 0)[..., None]
        xs = jnp.where(flip, xs[..., ::-1], xs)
        ys = jnp.where(flip, ys[..., ::-1], ys)
    u, v = to_ellipse_frame(xs, ys, center1, center2, pa_rad)
    v = v / q
    # a corner within 1e-9 of the quadrilateral's size from the centre is the centre:
    # snapping it to exactly 0 sends its edges down the degenerate branch instead of
    # through 0/0 in the gradient
    size = jnp.max(jnp.abs(xs - jnp.roll(xs, 2, axis=-1)) + jnp.abs(ys - jnp.roll(ys, 2, axis=-1)),
                   axis=-1)
    tol = 1e-9 * jax.lax.stop_gradient(size)[..., None]
    near = (jnp.abs(u) < tol) & (jnp.abs(v) < tol)
    u = jnp.where(near, 0.0, u)
    v = jnp.where(near, 0.0, v)
    ax, ay = u, v
    bx, by = jnp.roll(u, -1, axis=-1), jnp.roll(v, -1, axis=-1)
    dphi, degenerate = _edge_spans(ax, ay, bx, by)
    # The angle Φ the pixel subtends at the centre: 2π inside, π on an edge, the (sheared)
    # corner angle on a corner, and exactly 0 outside (the signed spans cancel). Its light
    # is Σ Δφ·P = Φ − Σ Δφ·Q. Each pixel takes the form that keeps relative precision: P
    # where P is small, i.e. pixels touching the centre or with their middle inside the
    # half-light ellipse (P = ½ on it); −Σ Δφ·Q (Φ = 0) in the wings. (Φ − Σ Δφ·Q near the
    # centre of a large profile cancels: in float32, R_e = 1e3 pixels with the centre on a
    # corner lost the value and gave NaN gradients.) One incomplete gamma per node either way.
    span = jnp.sum(dphi, axis=-1)
    touching = jnp.abs(span) > 1e-4
    inner = touching | (jnp.mean(u, -1) ** 2 + jnp.mean(v, -1) ** 2 < re_arcsec**2)
    light = jnp.sum(_edge_light(ax, ay, bx, by, dphi, degenerate, re_arcsec, n, b, t, w,
                                lambda x, lower: incgamma.q_upper(q_table, x, q_index, lower),
                                jnp.broadcast_to(inner[..., None], dphi.shape)), axis=-1)
    frac = jnp.where(inner, light, -light) / (2 * jnp.pi)
    # rounding can leave −1e-24 where the true light is +1e-24: light is never negative
    return flux * jnp.maximum(frac, 0.0)


# ---------------------------------------------------------------- spiral arms and texture


def spiral_modulation(x1, x2, *, center1, center2, q, pa_rad, count, amplitude, winding,
                      phase_rad, scale_arcsec, orientation_rad):
    """1 + A cos(N_a ϑ + α ln(2r/R_h) + φ_d) (Metcalf et al. 2019; the paper's Eq. for I(β, ϑ)).

    r and ϑ are measured in the disk's circularised (deprojected) frame, ϑ from
    the pattern's orientation, so that the modulation averages to exactly 1 on
    every ellipse and the disk keeps its flux. Requires 0 ≤ A ≤ 1 (no negative
    light). The logarithmic phase is floored at r = 1e-6 R_h.
    """
    u, v = to_ellipse_frame(x1, x2, center1, center2, pa_rad)
    v = v / q
    r = safe_sqrt(u * u + v * v)
    theta = safe_atan2(v, u) - orientation_rad
    rr = jnp.maximum(2 * r / scale_arcsec, 2e-6)
    phase = count * theta + winding * jnp.log(rr) + phase_rad
    return 1.0 + amplitude * jnp.cos(phase)


def _fade(t):
    return t * t * t * (t * (t * 6 - 15) + 10)


def _hash2(ix, iy, seed):
    """A 32-bit integer hash of lattice points (xor-multiply mixing): cheap and gather-free."""
    h = (ix.astype(jnp.uint32) * jnp.uint32(0x8DA6B343)) ^ (iy.astype(jnp.uint32) * jnp.uint32(0xD8163841))
    h = h ^ seed
    h = (h ^ (h >> 15)) * jnp.uint32(0x2C1B3C6D)
    h = (h ^ (h >> 12)) * jnp.uint32(0x297A2D39)
    return h ^ (h >> 15)


def perlin2d(x, y, seed):
    """Gradient ("Perlin") noise at (x, y) in lattice units, range ≈ [−1, 1].

    The gradient at each lattice point is one of the four diagonals (±1, ±1),
    chosen by hashing the point with `seed` (uint32); quintic fade, so the
    field is C² smooth. Deterministic for a given seed; no lookup tables.
    """
    xf = jnp.floor(x)
    yf = jnp.floor(y)
    fx = x - xf
    fy = y - yf
    xi = xf.astype(jnp.int32)
    yi = yf.astype(jnp.int32)
    seed = jnp.asarray(seed, jnp.uint32)

    def corner(ix, iy, dx, dy):
        h = _hash2(ix, iy, seed)
        gx = 1.0 - 2.0 * (h & 1).astype(x.dtype)
        gy = 1.0 - 2.0 * ((h >> 1) & 1).astype(x.dtype)
        return gx * dx + gy * dy

    n00 = corner(xi, yi, fx, fy)
    n10 = corner(xi + 1, yi, fx - 1, fy)
    n01 = corner(xi, yi + 1, fx, fy - 1)
    n11 = corner(xi + 1, yi + 1, fx - 1, fy - 1)
    u = _fade(fx)
    v = _fade(fy)
    nx0 = n00 + u * (n10 - n00)
    nx1 = n01 + u * (n11 - n01)
    return nx0 + v * (nx1 - nx0)


def perlin_fbm(x, y, seed, octaves: int, persistence: float = 0.5):
    """Sum of `octaves` Perlin octaves (frequency ×2, amplitude ×persistence), normalised to range ≈ [−1, 1]."""
    total = 0.0
    norm = 0.0
    amp = 1.0
    freq = 1.0
    for _ in range(octaves):
        # each octave its own seed, so octaves are independent fields
        total = total + amp * perlin2d(x * freq, y * freq, seed + jnp.uint32(0x9E3779B9 * (_ + 1) & 0xFFFFFFFF))
        norm += amp
        amp *= persistence
        freq *= 2.0
    return total / norm


def texture_modulation(x1, x2, *, center1, center2, amplitude, scale_arcsec, octaves, seed):
    """max(0, 1 + T·noise(β/scale)): a Perlin perturbation evaluated in the source plane."""
    p = perlin_fbm((x1 - center1) / scale_arcsec, (x2 - center2) / scale_arcsec, seed, octaves)
    return jnp.maximum(1.0 + amplitude * p, 0.0)
