"""Built-in analytic look-alike clusters, and lenses from plain component lists.

The look-alikes ("macs0416-like", "a2744-like") are sums of dPIE halos and an
external shear fitted to the public HFF GRALE (Williams et al., v4) deflection
maps by `scripts/fit_lookalike_clusters.py`, constrained to reproduce the
multiple-image configurations of the ClumPyLen paper's examples. They are
look-alikes for simulations that need no files, not the published models. The
package ships only their parameters (clumpylen_jax/data/lens_*_like.json, with
provenance), given for D_ls/D_s = 1 in the θ frame of the paper's lens centre.
"""

from __future__ import annotations

import json
from importlib import resources

import jax.numpy as jnp

from ..errors import ConfigError
from ._distances import dls_ds
from .analytic import DPIE, NFW, SIE, SIS, ExternalShear, LensSum, MassSheet

_BUILTINS = {"macs0416-like": "lens_macs0416_like.json", "a2744-like": "lens_abell2744_like.json"}

# kind → (class, required keys in constructor order, optional keys with defaults)
_KINDS = {
    "sis": (SIS, ("theta_e_arcsec", "center_arcsec"), {}),
    "sie": (SIE, ("theta_e_arcsec", "q", "pa_rad", "center_arcsec"), {}),
    "nfw": (NFW, ("kappa_s", "rs_arcsec", "center_arcsec"), {}),
    "dpie": (DPIE, ("b0_arcsec", "rcore_arcsec", "rcut_arcsec", "q", "pa_rad", "center_arcsec"), {}),
    "shear": (ExternalShear, ("gamma1", "gamma2"), {"center_arcsec": (0.0, 0.0)}),
    "sheet": (MassSheet, ("kappa",), {"center_arcsec": (0.0, 0.0)}),
}


def builtin_names():
    """Names accepted by `builtin_lens`."""
    return sorted(_BUILTINS)


def lens_component(spec: dict, where: str = "lens component"):
    """One analytic lens from a mapping such as {"kind": "sis", "theta_e_arcsec": 1.0, "center_arcsec": [0, 0]}.

    Kinds and keys: sis (theta_e_arcsec, center_arcsec), sie (theta_e_arcsec, q,
    pa_rad, center_arcsec), nfw (kappa_s, rs_arcsec, center_arcsec), dpie
    (b0_arcsec, rcore_arcsec, rcut_arcsec, q, pa_rad, center_arcsec), shear
    (gamma1, gamma2[, center_arcsec]), sheet (kappa[, center_arcsec]).
    """
    if not isinstance(spec, dict) or "kind" not in spec:
        raise ConfigError(where, spec, 'a table with "kind" and the parameters of that kind')
    kind = spec["kind"]
    if kind not in _KINDS:
        raise ConfigError(f"{where}.kind", kind, "one of " + ", ".join(sorted(_KINDS)))
    cls, required, optional = _KINDS[kind]
    extra = set(spec) - set(required) - set(optional) - {"kind"}
    if extra:
        raise ConfigError(f"{where}", sorted(extra)[0], f"keys of a {kind}: {', '.join(required + tuple(optional))}")
    missing = [k for k in required if k not in spec]
    if missing:
        raise ConfigError(f"{where}.{missing[0]}", None, f"a value (required for kind {kind!r})")
    args = []
    for k in required:
        v = spec[k]
        if k == "center_arcsec":
            if len(v) != 2:
                raise ConfigError(f"{where}.{k}", v, "[θ1, θ2] in arcsec")
        args.append(jnp.asarray(v, dtype=float))
    kw = {k: jnp.asarray(spec.get(k, d), dtype=float) for k, d in optional.items()}
    if kind == "dpie" and not (0 <= float(spec["rcore_arcsec"]) < float(spec["rcut_arcsec"])):
        raise ConfigError(f"{where}.rcore_arcsec", spec["rcore_arcsec"], "0 <= rcore_arcsec < rcut_arcsec")
    if kind in ("sie", "dpie") and not 0 < float(spec["q"]) <= 1:
        raise ConfigError(f"{where}.q", spec["q"], "0 < q <= 1")
    return cls(*args, **kw)


def lens_from_components(components, scale=1.0):
    """A LensSum of analytic components (see `lens_component`), times `scale`."""
    if not components:
        raise ConfigError("lens components", components, "a non-empty list of lens components")
    return LensSum([lens_component(c, f"lens.components[{i}]") for i, c in enumerate(components)], scale=scale)


def load_builtin_spec(name: str) -> dict:
    """The JSON document of a built-in look-alike (parameters and provenance)."""
    if name not in _BUILTINS:
        raise ConfigError("lens model", name, "one of " + ", ".join(builtin_names()))
    text = resources.files("clumpylen_jax").joinpath("data", _BUILTINS[name]).read_text()
    return json.loads(text)


def builtin_lens(name: str, z_source: float, cosmology=None) -> LensSum:
    """A built-in look-alike cluster as a lens for a source at z_source.

    name: "macs0416-like" (z_l = 0.396, centre RA, Dec = 64.038142, −24.067472) or
    "a2744-like" (z_l = 0.308, centre 3.586257, −30.400172). The deflection is
    scaled by D_ls/D_s(z_l, z_s) (astropy, flat ΛCDM H0 = 70, Ωm = 0.3 unless
    `cosmology` says otherwise). θ is relative to that centre (DESIGN.md).
    """
    spec = load_builtin_spec(name)
    return lens_from_components(spec["components"], scale=dls_ds(spec["z_lens"], float(z_source), cosmology))


def builtin_lens_info(name: str) -> dict:
    """z_lens and center_radec_deg of a built-in look-alike (for scenes and FITS headers)."""
    spec = load_builtin_spec(name)
    return {"z_lens": spec["z_lens"], "center_radec_deg": tuple(spec["center_radec_deg"])}
