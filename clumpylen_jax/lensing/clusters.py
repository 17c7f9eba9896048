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

from .. import defaults as D
from ..errors import ConfigError
from . import analytic
from ._distances import dls_ds
from .analytic import DPIE, LensSum

_BUILTINS = D.BUILTIN_LENSES


def builtin_names():
    """Names accepted by `builtin_lens`."""
    return sorted(_BUILTINS)


def lens_component(spec: dict, where: str = "lens component", dls_ds_ratio: float = 1.0):
    """One analytic lens from a mapping such as {"kind": "sis", "theta_e_arcsec": 1.0, "center_arcsec": [0, 0]}.

    Kinds, keys and defaults: `clumpylen_jax.defaults.LENS_KINDS` (sis: theta_e_arcsec;
    sie: theta_e_arcsec, q, pa_rad; nfw: kappa_s, rs_arcsec; dpie: b0_arcsec or
    sigma0_kms, rcore_arcsec, rcut_arcsec, q, pa_rad; shear: gamma1, gamma2; sheet:
    kappa; every kind: center_arcsec). A dpie given by sigma0_kms is built by
    `DPIE.from_sigma` with `dls_ds_ratio` (D_ls/D_s) as its scale.
    """
    if not isinstance(spec, dict) or "kind" not in spec:
        raise ConfigError(where, spec, 'a table with "kind" and the parameters of that kind')
    kind = spec["kind"]
    if kind not in D.LENS_KINDS:
        raise ConfigError(f"{where}.kind", kind, "one of " + ", ".join(sorted(D.LENS_KINDS)))
    cls_name, schema = D.LENS_KINDS[kind]
    extra = set(spec) - set(schema) - {"kind"}
    if extra:
        raise ConfigError(f"{where}", sorted(extra)[0], f"keys of a {kind}: {', '.join(schema)}")
    missing = [k for k, (required, _, _) in schema.items() if required and k not in spec]
    if missing:
        raise ConfigError(f"{where}.{missing[0]}", None, f"a value (required for kind {kind!r})")
    params = {k: spec.get(k, default) for k, (_, _, default) in schema.items()}
    params = {k: v for k, v in params.items() if v is not None}
    if "center_arcsec" in params and len(params["center_arcsec"]) != 2:
        raise ConfigError(f"{where}.center_arcsec", params["center_arcsec"], "[θ1, θ2] in arcsec")
    if kind == "dpie":
        if not (0 <= float(params["rcore_arcsec"]) < float(params["rcut_arcsec"])):
            raise ConfigError(f"{where}.rcore_arcsec", params["rcore_arcsec"], "0 <= rcore_arcsec < rcut_arcsec")
        if ("b0_arcsec" in params) == ("sigma0_kms" in params):
            raise ConfigError(where, spec, "exactly one of b0_arcsec (arcsec) or sigma0_kms (km/s)")
    if kind in ("sie", "dpie") and not 0 < float(params["q"]) <= 1:
        raise ConfigError(f"{where}.q", params["q"], "0 < q <= 1")
    kw = {k: jnp.asarray(v, dtype=float) for k, v in params.items()}
    if "sigma0_kms" in kw:
        return DPIE.from_sigma(dls_ds=dls_ds_ratio, **kw)
    return getattr(analytic, cls_name)(**kw)


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
