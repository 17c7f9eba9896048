"""AB magnitudes and fluxes of stellar populations through filters (JAX, differentiable).

The chain for a component of mass M (M☉ formed, see `sps`) and age t:

    L_λ,rest(t) = Σ_k w_k(t; SFH) L_λ,k          (sps.sfh_weights, L☉/Å per M☉)
    f_λ,obs(λ(1+z)) = M L_λ,rest(λ) L☉ / (4π D_L² (1+z)) × T_IGM(λ_obs) × 10^(−0.4 A_λ)
    <f_ν> = ∫ f_λ T λ dλ / (c ∫ T/λ dλ)           (photon-counting band average)
    m_AB = 23.9 − 2.5 log10(<f_ν> / μJy)

Everything after the SFH weights is linear in the spectrum and independent of
(M, t), so for a configuration (library, metallicity, filters, z, IGM, dust) the
band fluxes of every SSP age node are computed once with numpy (cached) and an
evaluation is a weighted sum: cheap for hundreds of clumps, smooth in mass and
age. Redshift, dust and the IGM are configuration here (not differentiated).

Flux unit: μJy (1 μJy = 1e-29 erg/s/cm²/Hz; AB 23.9). It keeps float32 values
of order unity for typical clumps.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from . import cosmology as _cosmo
from .errors import ConfigError
from .filters import Filter, load_filters
from .igm import igm_transmission
from .sps import L_SUN_ERG_S, SSPLibrary, default_library, sfh_weights

C_AA_PER_S = 2.99792458e18
UJY_CGS = 1e-29  # erg/s/cm²/Hz
AB_ZERO_UJY = 23.9  # m_AB of 1 μJy
CALZETTI_RV = 4.05


# ---------------------------------------------------------------- dust

def calzetti_k(wavelength_rest_aa) -> np.ndarray:
    """Calzetti et al. (2000) starburst attenuation curve k(λ) = A_λ / E(B−V), R_V = 4.05.

    Defined on 0.12–2.2 μm; extended linearly in 1/λ below 0.12 μm (slope of
    the curve at 0.12 μm) and continued as the red-side formula, floored at 0,
    above 2.2 μm.
    """
    lam = np.asarray(wavelength_rest_aa, dtype=float) / 1e4  # μm

    def blue(x):
        return 2.659 * (-2.156 + 1.509 / x - 0.198 / x**2 + 0.011 / x**3) + CALZETTI_RV

    def red(x):
        return 2.659 * (-1.857 + 1.040 / x) + CALZETTI_RV

    x0, h = 0.12, 1e-4
    # slope dk/d(1/λ) at 0.12 μm, for the UV extension
    slope = (blue(x0 - h) - blue(x0 + h)) / (1 / (x0 - h) - 1 / (x0 + h))
    uv = blue(x0) + slope * (1 / np.maximum(lam, 1e-6) - 1 / x0)
    k = np.where(lam < x0, uv, np.where(lam < 0.63, blue(np.maximum(lam, x0)), red(lam)))
    return np.clip(k, 0.0, None)


def dust_transmission(wavelength_rest_aa, dust_av: float) -> np.ndarray:
    """10^(−0.4 A_λ) for a Calzetti screen with A_V = dust_av."""
    if dust_av == 0:
        return np.ones_like(np.asarray(wavelength_rest_aa, dtype=float))
    return 10 ** (-0.4 * dust_av * calzetti_k(wavelength_rest_aa) / CALZETTI_RV)


# ---------------------------------------------------------------- validation

def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _check_config(z, dust_av, sfh, sfh_duration_myr, library):
    if not (isinstance(z, (int, float, np.floating, np.integer)) and np.isfinite(z) and z > 0):
        raise ConfigError("z", z, "a redshift > 0 (a Python float)")
    if not (np.isfinite(dust_av) and dust_av >= 0):
        raise ConfigError("dust_av", dust_av, "A_V >= 0 (mag)")
    if sfh not in ("burst", "constant"):
        raise ConfigError("sfh", sfh, "'burst' or 'constant'")
    if sfh == "constant":
        d = float(sfh_duration_myr)
        if not (np.isfinite(d) and d > 0):
            raise ConfigError("sfh_duration_myr", sfh_duration_myr, "a duration > 0 (Myr)")
    if not isinstance(library, SSPLibrary):
        raise ConfigError("library", library, "an SSPLibrary (or None for the built-in BC03 table)")


def _check_inputs(mass_msun, age_myr, library):
    """Range checks on concrete inputs (inside jit they are tracers and are not checked)."""
    if _is_concrete(age_myr):
        a = np.asarray(age_myr, dtype=float)
        lo, hi = library.age_range_myr
        if not (np.all(np.isfinite(a)) and np.all(a > lo) and np.all(a <= hi * (1 + 1e-9))):
            bad = a[~(np.isfinite(a) & (a > lo) & (a <= hi * (1 + 1e-9)))] if a.ndim else a
            raise ConfigError("age_myr", np.ravel(bad)[:3].tolist(),
                              f"ages in ({lo:g}, {hi:g}] Myr (the range of SSP library {library.name!r})")
    if _is_concrete(mass_msun):
        m = np.asarray(mass_msun, dtype=float)
        if not (np.all(np.isfinite(m)) and np.all(m > 0)):
            raise ConfigError("mass_msun", np.ravel(m[~(np.isfinite(m) & (m > 0))])[:3].tolist()
                              if m.ndim else float(m), "masses > 0 (M☉)")


# ---------------------------------------------------------------- band tables

def _observed_flux_scale(z: float, d_l_cm: float) -> float:
    """f_λ,obs per L_λ,rest in L☉/Å, in erg/s/cm²/Å: L☉ / (4π D_L² (1+z))."""
    return L_SUN_ERG_S / (4.0 * np.pi * d_l_cm**2 * (1.0 + z))


@functools.lru_cache(maxsize=128)
def _band_table(library: SSPLibrary, metallicity: float, nebular: bool, filt: Filter, z: float,
                igm: bool, dust_av: float, d_l_cm: float) -> np.ndarray:
    """(n_age,) band-averaged <f_ν> in μJy per M☉ formed, for each SSP age node."""
    rest_w = library.wavelength_aa
    lo_obs, hi_obs = filt.support_aa()
    lo_lib, hi_lib = rest_w[0] * (1 + z), rest_w[-1] * (1 + z)
    if lo_obs < lo_lib or hi_obs > hi_lib:
        raise ConfigError(
            "filter", filt.name,
            f"a band inside the SSP library's range at z = {z:g}: the band spans {lo_obs:.0f}–{hi_obs:.0f} Å "
            f"observed, the library {lo_lib:.0f}–{hi_lib:.0f} Å")
    # Integrate on the union of the filter's samples and the redshifted library
    # samples inside the band, so neither a coarse filter curve nor a coarse
    # spectrum is undersampled.
    lam_f = filt.wavelength_aa
    lib_obs = rest_w * (1 + z)
    inband = lib_obs[(lib_obs > lam_f[0]) & (lib_obs < lam_f[-1])]
    lam = np.union1d(lam_f, inband)
    thr = np.interp(lam, lam_f, filt.throughput)
    lam_rest = lam / (1 + z)
    spec = library.spectra(metallicity, nebular)  # (n_age, n_wave)
    spec_on = np.stack([np.interp(lam_rest, rest_w, row, left=0.0, right=0.0) for row in spec])
    factor = _observed_flux_scale(z, d_l_cm) * dust_transmission(lam_rest, dust_av)
    if igm:
        factor = factor * igm_transmission(lam, z)
    f_lambda = spec_on * factor  # erg/s/cm²/Å per M☉
    num = np.trapezoid(f_lambda * thr * lam, lam, axis=-1)
    den = C_AA_PER_S * np.trapezoid(thr / lam, lam)
    return num / den / UJY_CGS


@functools.lru_cache(maxsize=128)
def _mono_table(library: SSPLibrary, metallicity: float, nebular: bool, wavelength_obs_aa: tuple,
                z: float, igm: bool, dust_av: float, d_l_cm: float) -> np.ndarray:
    """(n_age, n_lambda) f_ν in μJy per M☉ formed at observed wavelengths."""
    lam = np.asarray(wavelength_obs_aa)
    lam_rest = lam / (1 + z)
    rest_w = library.wavelength_aa
    if np.any(lam_rest < rest_w[0]) or np.any(lam_rest > rest_w[-1]):
        raise ConfigError("wavelength_obs_um", (lam / 1e4).tolist(),
                          f"wavelengths inside the SSP library's range at z = {z:g}: "
                          f"{rest_w[0] * (1 + z) / 1e4:.3f}–{rest_w[-1] * (1 + z) / 1e4:.3f} μm")
    spec = library.spectra(metallicity, nebular)
    spec_on = np.stack([np.interp(lam_rest, rest_w, row) for row in spec])
    factor = _observed_flux_scale(z, d_l_cm) * dust_transmission(lam_rest, dust_av)
    if igm:
        factor = factor * igm_transmission(lam, z)
    f_nu = spec_on * factor * lam**2 / C_AA_PER_S
    return f_nu / UJY_CGS


def _prepare(z, metallicity, sfh, sfh_duration_myr, dust_av, library, cosmology):
    library = default_library() if library is None else library
    _check_config(z, dust_av, sfh, sfh_duration_myr, library)
    metallicity = float(library.metallicities[library.metallicity_index(metallicity)])
    d_l = _cosmo.luminosity_distance_cm(float(z), cosmology)
    return library, metallicity, d_l


@functools.lru_cache(maxsize=32, typed=True)   # typed: 100.0 and np.float64(100.0) promote apart
def _sfh_weights_program(library: SSPLibrary, sfh: str, sfh_duration_myr: float):
    """sfh_weights on the library's ages as one jitted function (the ages are constants: op
    by op it costs ~0.5 s a call), one per population kind, so that the calls of a run with
    the same kind (magnitudes, then high-resolution fluxes) trace and load it once."""
    return jax.jit(lambda a: sfh_weights(a, library.ages_myr, sfh, sfh_duration_myr))


def _combine(mass_msun, age_myr, table, library, metallicity, sfh, sfh_duration_myr, mass_definition):
    """mass × (SFH weights · table), in the floating dtype of the inputs."""
    mass = jnp.asarray(mass_msun)
    age = jnp.asarray(age_myr)
    dtype = jnp.result_type(mass, age)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    mass, age = jnp.broadcast_arrays(mass.astype(dtype), age.astype(dtype))
    w = _sfh_weights_program(library, sfh, sfh_duration_myr)(age)
    per_formed = w @ jnp.asarray(table, dtype=dtype)  # (..., n_out)
    if mass_definition == "surviving":
        surv = w @ jnp.asarray(library.surviving_fraction(metallicity), dtype=dtype)
        per_formed = per_formed / surv[..., None]
    elif mass_definition != "formed":
        raise ConfigError("mass_definition", mass_definition, "'formed' or 'surviving'")
    return mass[..., None] * per_formed


def band_fluxes_ujy(mass_msun, age_myr, *, filters, z, metallicity=0.004, sfh="constant",
                    sfh_duration_myr=100.0, igm=True, dust_av=0.0, nebular=True, library=None,
                    cosmology=None, mass_definition="formed"):
    """Band-averaged f_ν (μJy) of populations, shape broadcast(mass, age) + (n_filters,).

    See `ab_magnitudes` for the arguments.
    """
    filts = load_filters(filters)
    library, metallicity, d_l = _prepare(z, metallicity, sfh, sfh_duration_myr, dust_av,
                                         library, cosmology)
    _check_inputs(mass_msun, age_myr, library)
    neb = bool(nebular) and library.has_nebular
    table = np.stack([_band_table(library, metallicity, neb, f, float(z), bool(igm), float(dust_av), d_l)
                      for f in filts], axis=-1)  # (n_age, n_filters)
    return _combine(mass_msun, age_myr, table, library, metallicity, sfh, sfh_duration_myr, mass_definition)


def ab_magnitudes(mass_msun, age_myr, *, filters, z, metallicity=0.004, sfh="constant",
                  sfh_duration_myr=100.0, igm=True, dust_av=0.0, nebular=True, library=None,
                  cosmology=None, mass_definition="formed"):
    """AB magnitudes of stellar populations, shape broadcast(mass, age) + (n_filters,).

    mass_msun: stellar mass (M☉); by default the mass *formed* (the SSP tables'
        normalisation, the paper's F = F_SSP M / M_SSP); mass_definition="surviving"
        interprets it as the surviving stellar mass at the population's age.
    age_myr: age (Myr) of the oldest stars, in (0, oldest library age].
    filters: a name ("F200W"), a Filter, or a sequence of them.
    z: source redshift (Python float; configuration, not differentiated).
    metallicity: a metallicity of the library (built-in: 0.0004, 0.004, 0.008, 0.02).
    sfh: "constant" (SFR constant for sfh_duration_myr, starting age_myr ago)
        or "burst" (instantaneous).
    igm: apply the Inoue et al. (2014) mean IGM transmission.
    dust_av: Calzetti (2000) screen, A_V in mag.
    nebular: add the library's nebular continuum + lines (if it has them).
    library: an `sps.SSPLibrary`; None = the built-in BC03 (2016, MILES) table.
    cosmology: astropy cosmology; None = flat ΛCDM H0 = 70, Ωm = 0.3.

    Differentiable (jax.grad) in mass_msun and age_myr; works under jit (range
    checks then apply only to concrete inputs).
    """
    flux = band_fluxes_ujy(mass_msun, age_myr, filters=filters, z=z, metallicity=metallicity, sfh=sfh,
                           sfh_duration_myr=sfh_duration_myr, igm=igm, dust_av=dust_av, nebular=nebular,
                           library=library, cosmology=cosmology, mass_definition=mass_definition)
    return AB_ZERO_UJY - 2.5 * jnp.log10(flux)


def monochromatic_fnu(mass_msun, age_myr, *, wavelength_obs_um, z, metallicity=0.004, sfh="constant",
                      sfh_duration_myr=100.0, igm=True, dust_av=0.0, nebular=True, library=None,
                      cosmology=None, mass_definition="formed"):
    """f_ν in μJy at observed wavelengths (μm): shape broadcast(mass, age) + (n_wavelengths,).

    For the paper's high-resolution colour images (e.g. 5, 3, 2 μm). Same
    arguments as `ab_magnitudes`; the spectrum is the library's bin-averaged
    L_λ interpolated linearly to λ_obs / (1 + z).
    """
    lam_um = np.atleast_1d(np.asarray(wavelength_obs_um, dtype=float))
    if lam_um.ndim != 1 or not np.all(np.isfinite(lam_um)) or np.any(lam_um <= 0):
        raise ConfigError("wavelength_obs_um", wavelength_obs_um, "positive wavelengths in μm")
    library, metallicity, d_l = _prepare(z, metallicity, sfh, sfh_duration_myr, dust_av,
                                         library, cosmology)
    _check_inputs(mass_msun, age_myr, library)
    neb = bool(nebular) and library.has_nebular
    table = _mono_table(library, metallicity, neb, tuple(float(x) for x in lam_um * 1e4), float(z),
                        bool(igm), float(dust_av), d_l)
    return _combine(mass_msun, age_myr, table, library, metallicity, sfh, sfh_duration_myr, mass_definition)


def mag_to_counts_per_s(mag_ab, zeropoint_ab):
    """Count rate (e⁻/s) of a source of AB magnitude mag_ab: 10^(−0.4 (m − ZP)).

    Array-library agnostic: numpy (or Python numbers) in, numpy out (the pipeline's
    build-time photometry, no JAX dispatch); JAX arrays in, JAX out (differentiable).
    """
    if not isinstance(mag_ab, jax.Array) and not isinstance(zeropoint_ab, jax.Array):
        return 10.0 ** (-0.4 * (np.asarray(mag_ab, float) - np.asarray(zeropoint_ab, float)))
    return 10.0 ** (-0.4 * (jnp.asarray(mag_ab) - zeropoint_ab))


def mags_to_counts_per_s_or_zero(mag_ab, zeropoint_ab) -> np.ndarray:
    """Count rates (numpy) of AB magnitudes; 0 where a magnitude is not finite (no light)."""
    mag_ab = np.asarray(mag_ab, float)
    ok = np.isfinite(mag_ab)
    counts = mag_to_counts_per_s(np.where(ok, mag_ab, 0.0), np.asarray(zeropoint_ab, float))
    return np.where(ok, counts, 0.0)


def counts_per_s_to_mag(counts_per_s, zeropoint_ab):
    """AB magnitude of a count rate (e⁻/s): ZP − 2.5 log10(counts/s)."""
    return zeropoint_ab - 2.5 * jnp.log10(jnp.asarray(counts_per_s))


def fnu_ujy_to_mag(fnu_ujy):
    """AB magnitude of a flux density in μJy."""
    return AB_ZERO_UJY - 2.5 * jnp.log10(jnp.asarray(fnu_ujy))
