"""One registry of defaults: the scene parser (scene.py), the Python API (model.py,
population.py) and the lens builders (lensing/clusters.py, pipeline.py) read them here,
so that a scene file and a Python call cannot disagree. Plain data, no imports.

Accuracy presets are the exception: they are `model.ACCURACY_PRESETS` (values measured
by benchmarks/), which scene.py reads.
"""

# --- [render] -----------------------------------------------------------------------
SOURCE_PIXEL_ARCSEC = 0.00025   # the paper's 0.25 mas source-plane pixel
LENS_PIXEL_ARCSEC = 0.0025      # the high-resolution lens-plane pixel
DTYPE = "float64"
ACCURACY_PRESET = "default"

# --- [source.clumps] ----------------------------------------------------------------
# Clump mass function f(M) ∝ M^slope exp[−delta (M/m_cut)^gamma] on [m_min, m_max]
# (the ClumPyLen paper's choice).
CMF = {"slope": -2.0, "m_cut_msun": 5.0e6, "delta": 1.0, "gamma": 1.0,
       "m_min_msun": 1.0e4, "m_max_msun": 1.0e7}
# Mass–size relation R_e = norm (M/pivot)^slope (Brown & Gnedin 2021), lognormal scatter.
SIZE_RELATIONS = ("brown-gnedin-2021",)
SIZE = {"relation": "brown-gnedin-2021", "scatter_ln": 0.3,
        "norm_pc": 2.55, "slope": 0.24, "pivot_msun": 1.0e4}
AGES = {"slope": -0.5, "min_myr": 1.0, "max_myr": 500.0}   # dN/dt ∝ t^slope
CLUMPS = {"mass_fraction": 0.8, "host": "disk", "metallicity": 0.004, "sersic_n": 0.5,
          "q_range": (0.3, 1.0), "sfh_kind": "constant", "sfh_duration_myr": 10.0}

# --- [lens] -------------------------------------------------------------------------
# Built-in look-alike clusters: name -> parameter file in clumpylen_jax/data.
BUILTIN_LENSES = {"macs0416-like": "lens_macs0416_like.json", "a2744-like": "lens_abell2744_like.json"}

# Analytic lens components: kind -> (class in lensing.analytic, {parameter: (required,
# value kind, default)}). Value kinds: "pos" (> 0), "nonneg" (>= 0), "q" (0 < q <= 1),
# "real", "pair". Parameter names are the classes' field names. A dpie takes exactly one
# of b0_arcsec or sigma0_kms (then DPIE.from_sigma).
_CENTER = ("center_arcsec", (False, "pair", (0.0, 0.0)))
LENS_KINDS = {
    "sis": ("SIS", dict([("theta_e_arcsec", (True, "pos", None)), _CENTER])),
    "sie": ("SIE", dict([("theta_e_arcsec", (True, "pos", None)), ("q", (False, "q", 1.0)),
                         ("pa_rad", (False, "real", 0.0)), _CENTER])),
    "nfw": ("NFW", dict([("kappa_s", (True, "pos", None)), ("rs_arcsec", (True, "pos", None)), _CENTER])),
    "dpie": ("DPIE", dict([("b0_arcsec", (False, "pos", None)), ("sigma0_kms", (False, "pos", None)),
                           ("rcore_arcsec", (False, "nonneg", 0.0)), ("rcut_arcsec", (True, "pos", None)),
                           ("q", (False, "q", 1.0)), ("pa_rad", (False, "real", 0.0)), _CENTER])),
    "shear": ("ExternalShear", dict([("gamma1", (False, "real", 0.0)), ("gamma2", (False, "real", 0.0)),
                                     _CENTER])),
    "sheet": ("MassSheet", dict([("kappa", (True, "real", None)), _CENTER])),
}
