"""Scene files: parsing, validation messages, defaults, TOML round trip, stages."""

import json
import math
import shutil
import sys
import tomllib
import types
from pathlib import Path

import numpy as np
import pytest

from clumpylen_jax import scene as sc
from clumpylen_jax.errors import ConfigError

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def minimal():
    """A small valid lensed scene as a dict (fresh each call)."""
    return {
        "scene": {"name": "t", "seed": 3, "z_source": 2.0},
        "source": {
            "center_arcsec": [0.1, -0.2],
            "bulge": {"mass_msun": 1e8, "re_arcsec": 0.1},
            "disk": {"mass_msun": 1e9, "re_arcsec": 0.3, "arms": {"count": 2}},
            "clumps": {"mass_fraction": 0.3},
        },
        "lens": {"z_lens": 0.5, "components": [{"kind": "sis", "theta_e_arcsec": 1.0}]},
        "bands": [
            {"instrument": "JWST/NIRCam", "filter": "F115W", "exptime_s": 100.0, "sky_counts_per_s": 0.2},
            {"instrument": "JWST/NIRCam", "filter": "F200W", "exptime_s": 100.0, "sky_counts_per_s": 0.2},
            {"instrument": "HST/WFC3-IR", "filter": "F160W", "exptime_s": 100.0},
        ],
        "output": {"rgb": [["F160W", "F200W", "F115W"]]},
    }


def error_for(d, base_dir=None) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        sc.scene_from_dict(d, base_dir=base_dir)
    return info.value


# --- built-in scenes ---------------------------------------------------------


def test_builtin_scenes_listed_with_descriptions():
    items = dict(sc.list_builtin_scenes())
    assert {"cosmic-archipelago", "a2744-system3", "single-sersic"} <= set(items)
    assert all(desc and "\n" not in desc for desc in items.values())


@pytest.mark.parametrize("name", ["cosmic-archipelago", "a2744-system3", "single-sersic"])
def test_builtin_round_trip_through_toml(name):
    s = sc.load_scene(name)
    text = sc.to_toml(s)
    again = sc.scene_from_dict(tomllib.loads(text), base_dir=s.base_dir)
    assert again == s
    json.dumps(sc.resolved_dict(s))  # JSON-serialisable too


def test_cosmic_archipelago_matches_the_paper():
    s = sc.load_scene("cosmic-archipelago")
    assert s.z_source == 6.145 and s.lens.z_lens == 0.396
    assert s.source.center_arcsec == (-13.716581, 3.6176634)
    assert s.lens.center_radec_deg == (64.038142, -24.067472) and s.lens.model == "macs0416-like"
    b, d = s.source.bulge, s.source.disk
    assert (b.mass_msun, b.re_arcsec, b.n, b.age_myr) == (1e7, 0.1, 4.0, 1000.0)
    assert (d.mass_msun, d.re_arcsec, d.n, d.age_myr) == (9e7, 0.18, 1.0, 500.0)
    assert math.isclose(b.pa_rad, math.pi / 8) and math.isclose(d.arms.orientation_rad, 0.75 * math.pi)
    assert (d.arms.count, d.arms.winding, d.arms.phase_rad, d.arms.scale_arcsec) == (4, 10.0, 1.0, 0.1)
    assert s.source.clumps.mass_fraction == 0.8 and s.source.clumps.cmf == sc.CMF()
    assert s.source.clumps.sfh == sc.SFH("constant", 10.0)
    table = {bd.filter: (bd.exptime_s, bd.sky_counts_per_s) for bd in s.bands}
    assert table == {
        "F105W": (5511.747, 0.694285), "F125W": (5511.747, 0.547766), "F160W": (5511.747, 0.5331),
        "F115W": (3349.872, 0.207835), "F150W": (2920.4, 0.20776), "F200W": (2920.4, 0.160606),
        "F277W": (2920.4, 0.0948052), "F356W": (2920.4, 0.0935602), "F444W": (3779.34, 0.2402224),
    }
    assert s.render.field_arcsec == sc.Field((-38.0, -33.0), (16.5, 21.5))
    assert s.output.rgb == (("F200W", "F150W", "F115W"), ("F444W", "F356W", "F277W"))
    assert s.output.hr_rgb_um == (5.0, 3.0, 2.0)


def test_a2744_system3_matches_the_paper():
    s = sc.load_scene("a2744-system3")
    assert s.z_source == 3.98 and s.lens.z_lens == 0.308 and s.lens.model == "a2744-like"
    assert s.source.center_arcsec == (28.395195, 40.2729467)
    assert (s.source.bulge.mass_msun, s.source.disk.mass_msun, s.source.disk.re_arcsec) == (5e7, 1.5e8, 0.3)
    assert s.source.clumps.mass_fraction == 0.5 and s.source.disk.arms.scale_arcsec == 0.3
    assert len(s.bands) == 12 and s.render.field_arcsec is None
    assert s.band("F435W").exptime_s == 1284.0 and s.band("F814W").sky_counts_per_s == 0.0669051
    assert s.band("F125W").exptime_s == 602.93 and s.band("F444W").sky_counts_per_s == 0.228858
    assert len(s.output.rgb) == 4


# --- defaults ----------------------------------------------------------------


def test_defaults_filled():
    s = sc.scene_from_dict(minimal())
    assert s.cosmology == sc.Cosmology(70.0, 0.3)
    assert s.source.bulge.n == 4.0 and s.source.disk.n == 1.0 and s.source.disk.q == 1.0
    assert s.source.disk.arms.scale_arcsec == pytest.approx(0.3 / 1.678)
    assert s.render.source_pixel_arcsec == 0.00025 and s.render.lens_pixel_arcsec == 0.0025
    assert s.render.accuracy.preset == "default" and s.render.dtype == "float64"
    assert s.output.noise and s.output.unlensed
    assert all(b.psf == "diffraction" and b.psf_effective is False for b in s.bands)
    assert s.bands[2].sky_counts_per_s == 0.0
    assert s.lens.components[0].params == {"theta_e_arcsec": 1.0, "center_arcsec": (0.0, 0.0)}


def test_band_defaults_from_instruments_when_available(monkeypatch):
    fake = types.ModuleType("clumpylen_jax.instruments")
    fake.band_defaults = lambda inst, filt: {"pixel_arcsec": 0.031, "zeropoint_ab": 28.0}
    monkeypatch.setitem(sys.modules, "clumpylen_jax.instruments", fake)
    d = minimal()
    d["bands"][0]["zeropoint_ab"] = 27.5
    s = sc.scene_from_dict(d)
    assert (s.bands[0].pixel_arcsec, s.bands[0].zeropoint_ab) == (0.031, 27.5)
    assert (s.bands[1].pixel_arcsec, s.bands[1].zeropoint_ab) == (0.031, 28.0)


def test_band_defaults_error_names_the_band(monkeypatch):
    def band_defaults(inst, filt):
        raise ConfigError("filter", filt, "a filter of " + inst)

    fake = types.ModuleType("clumpylen_jax.instruments")
    fake.band_defaults = band_defaults
    monkeypatch.setitem(sys.modules, "clumpylen_jax.instruments", fake)
    d = minimal()
    assert error_for(d).setting == "bands[0].filter"
    for b in d["bands"]:
        b.update(pixel_arcsec=0.03, zeropoint_ab=28.0)  # explicit values: no lookup needed
    assert sc.scene_from_dict(d).bands[2].pixel_arcsec == 0.03


def test_accuracy_table_and_dtype():
    d = minimal()
    d["render"] = {"accuracy": {"preset": "high", "subsampling": 6, "dtype": "float32"}}
    s = sc.scene_from_dict(d)
    high = sc.ACCURACY_PRESETS["high"]
    assert s.render.accuracy == sc.Accuracy("high", 6, high["psf_oversampling"], high["source_mode"],
                                            source_flux_fraction=high["source_flux_fraction"])
    assert high["source_flux_fraction"] == 0.999
    assert s.render.dtype == "float32"
    d["render"]["dtype"] = "float64"
    assert error_for(d).setting == "render.accuracy.dtype"


def test_linearise_tolerance_key_reaches_the_model_and_is_checked():
    from clumpylen_jax import pipeline
    d = minimal()
    d["render"] = {"accuracy": {"source_mode": "hybrid", "linearise_tolerance": 0.2}}
    s = sc.scene_from_dict(d)
    assert s.render.accuracy.linearise_tolerance == 0.2
    assert s.render.accuracy.source_mode == "hybrid"
    acc = pipeline._accuracy(s)
    assert (acc.linearise_tolerance, acc.source_mode) == (0.2, "hybrid")
    assert sc.ACCURACY_PRESETS["default"]["source_mode"] == "hybrid"
    d["render"]["accuracy"]["linearise_tolerance"] = -1.0
    e = error_for(d)
    assert e.setting == "render.accuracy.linearise_tolerance" and "-1" in str(e)


def test_source_flux_fraction_key_keeps_a_lensed_hosts_halo(tmp_path):
    """A mass sheet magnifies every ray by 1/(1 - κ)²: the lensed total is that times the
    host's flux, less the light beyond the traced disc (1 % of an n = 4 host at 0.99).
    The host's R_e is 4 lens pixels and its centre on a pixel corner: sampled at pixel
    centres it came out 3 % too bright (the cusp trap), hence the exact footprint
    integrals around the images of a host's centre."""
    from clumpylen_jax import pipeline
    d = minimal()
    d["render"] = {"accuracy": {"source_flux_fraction": 0.2}}
    e = error_for(d)
    assert e.setting == "render.accuracy.source_flux_fraction" and "[0.5, 1)" in str(e)
    d["render"]["accuracy"]["source_flux_fraction"] = 1.0
    assert error_for(d).setting == "render.accuracy.source_flux_fraction"
    scene = {
        "scene": {"name": "sheet", "z_source": 2.0},
        "source": {"center_arcsec": [0.0, 0.0],
                   "bulge": {"magnitudes": {"F200W": 20.0}, "re_arcsec": 0.01, "n": 4.0}},
        "lens": {"z_lens": 0.5, "center_radec_deg": [10.0, 0.0],
                 "components": [{"kind": "sheet", "kappa": 0.5}]},
        "render": {"lens_pixel_arcsec": 0.005, "field_arcsec": {"x": [-1.4, 1.4], "y": [-1.4, 1.4]},
                   "accuracy": {"preset": "fast", "subsampling": 1}},
        "bands": [{"instrument": "JWST/NIRCam", "filter": "F200W", "exptime_s": 100.0,
                   "psf": "none"}],
        "output": {"noise": False},
    }
    totals = {}
    for fraction in (0.99, 0.9999):
        scene["render"]["accuracy"]["source_flux_fraction"] = fraction
        prep = pipeline.prepare(sc.scene_from_dict(scene))
        assert prep.accuracy.source_flux_fraction == fraction
        flux = float(prep.source.bulge.flux[0])
        image = np.asarray(prep.model.noiseless(prep.source)[0])
        light = image.sum() - prep.model.layouts[0].sky_counts_per_s * image.size
        totals[fraction] = light / (4.0 * flux)
    assert 0.985 < totals[0.99] < 0.995
    assert abs(totals[0.9999] - 1) < 3e-4


# --- validation messages -----------------------------------------------------


def test_unknown_key_suggests_nearest():
    d = minimal()
    d["source"]["bulge"]["re_arcec"] = d["source"]["bulge"].pop("re_arcsec")
    e = error_for(d)
    assert str(e) == "unknown key 'source.bulge.re_arcec'; did you mean 're_arcsec'?"
    d = minimal()
    d["bands"][1]["exptime"] = 3.0
    assert "bands[1].exptime" in str(error_for(d)) and "exptime_s" in str(error_for(d))
    d = minimal()
    d["rendr"] = {}
    assert "did you mean 'render'" in str(error_for(d))


def test_missing_required_z_source():
    d = minimal()
    del d["scene"]["z_source"]
    e = error_for(d)
    assert e.setting == "scene.z_source" and "required" in str(e)


@pytest.mark.parametrize(
    "path, value, setting",
    [
        (("source", "bulge", "n"), "four", "source.bulge.n"),
        (("source", "bulge", "n"), 0.1, "source.bulge.n"),
        (("source", "bulge", "n"), 11.0, "source.bulge.n"),
        (("source", "bulge", "q"), 0.0, "source.bulge.q"),
        (("source", "disk", "q"), 1.2, "source.disk.q"),
        (("source", "bulge", "re_arcsec"), 0.0, "source.bulge.re_arcsec"),
        (("source", "bulge", "mass_msun"), -1.0, "source.bulge.mass_msun"),
        (("source", "clumps", "mass_fraction"), 1.5, "source.clumps.mass_fraction"),
        (("source", "disk", "arms", "count"), 0, "source.disk.arms.count"),
        (("source", "disk", "arms", "count"), 2.5, "source.disk.arms.count"),
        (("source", "disk", "arms", "count"), True, "source.disk.arms.count"),
        (("scene", "seed"), "x", "scene.seed"),
        (("lens", "z_lens"), 2.5, "lens.z_lens"),
        (("output", "noise"), "yes", "output.noise"),
        (("source", "clumps", "host"), "bar", "source.clumps.host"),
        (("source", "clumps", "q_range"), [0.5, 0.2], "source.clumps.q_range"),
        (("source", "clumps", "sfh"), {"kind": "exponential"}, "source.clumps.sfh.kind"),
        (("render", "accuracy"), "medium", "render.accuracy"),
    ],
)
def test_bad_values_name_the_setting(path, value, setting):
    d = minimal()
    t = d
    for k in path[:-1]:
        t = t.setdefault(k, {})
    t[path[-1]] = value
    e = error_for(d)
    assert e.setting == setting
    assert str(e).startswith(setting)


@pytest.mark.parametrize("key, value", [("exptime_s", 0.0), ("exptime_s", "long"), ("sky_counts_per_s", -0.1),
                                        ("psf_effective", 1), ("filter", "F999X"), ("instrument", "HST/WFC3")])
def test_band_errors_are_indexed(key, value):
    d = minimal()
    d["bands"][2][key] = value
    assert error_for(d).setting == f"bands[2].{key}"


def test_exptime_required_only_with_noise():
    d = minimal()
    del d["bands"][0]["exptime_s"]
    assert error_for(d).setting == "bands[0].exptime_s"
    d["output"]["noise"] = False
    assert sc.scene_from_dict(d).bands[0].exptime_s is None


def test_duplicate_filter_rejected():
    d = minimal()
    d["bands"][1]["filter"] = "F115W"
    assert error_for(d).setting == "bands[1].filter"


def test_rgb_must_name_bands():
    d = minimal()
    d["output"]["rgb"] = [["F444W", "F200W", "F115W"]]
    e = error_for(d)
    assert e.setting == "output.rgb[0]" and "F444W" in str(e)


def test_component_needs_mass_or_all_magnitudes():
    d = minimal()
    del d["source"]["bulge"]["mass_msun"]
    d["source"]["bulge"]["magnitudes"] = {"F115W": 25.0, "F200W": 24.5}
    e = error_for(d)
    assert e.setting == "source.bulge.mass_msun" and "F160W" in str(e)
    d["source"]["bulge"]["magnitudes"]["f160w"] = 24.0  # case-insensitive filter names
    assert sc.scene_from_dict(d).source.bulge.magnitudes == {"F115W": 25.0, "F200W": 24.5, "F160W": 24.0}
    d["source"]["bulge"]["magnitudes"]["F1150W"] = 1.0
    assert "source.bulge.magnitudes.F1150W" in str(error_for(d))


def test_clumps_need_a_massive_host():
    d = minimal()
    del d["source"]["disk"]
    assert error_for(d).setting == "source.clumps.host"
    d["source"]["clumps"]["host"] = "bulge"
    assert sc.scene_from_dict(d).source.clumps.host == "bulge"


def test_lens_exactly_one_kind():
    d = minimal()
    d["lens"]["model"] = "macs0416-like"
    assert error_for(d).setting == "lens"
    d = minimal()
    d["lens"]["components"] = [{"kind": "sis"}]
    assert error_for(d).setting == "lens.components[0].theta_e_arcsec"
    d["lens"]["components"] = [{"kind": "sis", "theta_e_arcsec": 1.0}, {"kind": "nfw", "kappa_s": 0.1}]
    assert error_for(d).setting == "lens.components[1].rs_arcsec"
    d["lens"]["components"] = [{"kind": "sie", "theta_e_arcsec": 1.0, "q": 0.5, "gama": 0.1}]
    assert error_for(d).setting == "lens.components[0].gama"
    d["lens"]["components"] = [{"kind": "dpie", "rcut_arcsec": 5.0}]
    assert error_for(d).setting == "lens.components[0]"
    d["lens"]["components"] = [{"kind": "dpie", "sigma0_kms": 300.0, "rcore_arcsec": 0.1, "rcut_arcsec": 20.0},
                               {"kind": "shear", "gamma1": 0.05}, {"kind": "sheet", "kappa": 0.02}]
    s = sc.scene_from_dict(d)
    assert s.lens.components[0].params == {"sigma0_kms": 300.0, "rcore_arcsec": 0.1, "rcut_arcsec": 20.0,
                                           "q": 1.0, "pa_rad": 0.0, "center_arcsec": (0.0, 0.0)}
    assert sc.scene_from_dict(tomllib.loads(sc.to_toml(s))) == s
    d["lens"]["components"] = [{"kind": "point"}]
    assert error_for(d).setting == "lens.components[0].kind"
    d = minimal()
    d["lens"] = {"z_lens": 0.3, "model": "macs0416-lik"}
    assert "macs0416-like" in str(error_for(d))


def test_relative_files_resolve_against_scene_dir(tmp_path):
    (tmp_path / "maps").mkdir()
    for name, fixture in (("ax.fits", "lens_hff_x-arcsec-deflect.fits"), ("ay.fits", "lens_hff_y-arcsec-deflect.fits"),
                          ("psf.fits", "psf_nircam_f200w_detsamp.fits")):  # real files, as a user's would be
        shutil.copy(FIXTURES / fixture, tmp_path / "maps" / name)
    d = minimal()
    d["lens"] = {"z_lens": 0.3, "center_radec_deg": [10.0, -5.0],
                 "deflection": {"x": "maps/ax.fits", "y": "maps/ay.fits", "normalization": {"z_source": 9.0}}}
    d["bands"][0]["psf"] = "maps/psf.fits"
    s = sc.scene_from_dict(d, base_dir=tmp_path)
    assert s.lens.deflection.x == str(tmp_path / "maps" / "ax.fits")
    assert s.lens.deflection.normalization_z_source == 9.0
    assert s.bands[0].psf == str(tmp_path / "maps" / "psf.fits")
    again = sc.scene_from_dict(tomllib.loads(sc.to_toml(s)))  # absolute paths: any base_dir
    assert again == s
    d["lens"]["deflection"]["y"] = "maps/missing.fits"
    e = error_for(d, base_dir=tmp_path)
    assert e.setting == "lens.deflection.y" and "existing file" in str(e)
    d["lens"]["deflection"]["y"] = "maps/ay.fits"
    d["lens"]["deflection"]["normalization"] = "unity"
    assert error_for(d, base_dir=tmp_path).setting == "lens.deflection.normalization"


def test_load_scene_file_and_errors(tmp_path):
    p = tmp_path / "my.toml"
    p.write_text(sc.to_toml(minimal()))
    s = sc.load_scene(str(p))
    assert s.name == "t" and s.base_dir == str(tmp_path)
    with pytest.raises(FileNotFoundError):
        sc.load_scene(str(tmp_path / "nope.toml"))
    with pytest.raises(ConfigError, match="did you mean 'cosmic-archipelago'"):
        sc.load_scene("cosmic-archipelag")
    p.write_text("[scene\n")
    with pytest.raises(tomllib.TOMLDecodeError, match="line 1"):
        sc.load_scene(str(p))


def test_clump_catalog_columns_checked(tmp_path):
    from astropy.table import Table

    # q and pa_rad: simulate's reader needs them, and validation now uses that reader
    good = Table({"beta1_arcsec": [0.0], "beta2_arcsec": [0.1], "re_pc": [3.0], "q": [0.8],
                  "pa_rad": [0.0], "mag_F115W": [27.0], "mag_F200W": [27.1], "mag_F160W": [27.2], "extra": [1]})
    good.write(tmp_path / "cl.ecsv", format="ascii.ecsv")
    d = minimal()
    d["source"]["clumps"]["catalog"] = "cl.ecsv"
    s = sc.scene_from_dict(d, base_dir=tmp_path)
    assert s.source.clumps.catalog == str(tmp_path / "cl.ecsv")
    assert "catalog" in sc.stages(s) and "population" not in sc.stages(s)
    good.remove_column("mag_F160W")
    good.write(tmp_path / "cl.ecsv", format="ascii.ecsv", overwrite=True)
    e = error_for(d, base_dir=tmp_path)
    assert e.setting.startswith("source.clumps.catalog") and "mag_F160W" in str(e)


# --- stages and overrides ----------------------------------------------------


def test_stages_only_what_the_scene_needs():
    s = sc.load_scene("single-sersic")
    st = sc.stages(s)
    assert "lensing" not in st and "population" not in st and "photometry" not in st
    assert not any(x.startswith("psf:") for x in st) and "unlensed" not in st
    full = sc.stages(sc.scene_from_dict(minimal()))
    for name in ("population", "photometry", "lensing", "psf:F115W", "noise", "unlensed", "rgb:F160W-F200W-F115W"):
        assert name in full


def test_with_overrides():
    s = sc.scene_from_dict(minimal())
    t = sc.with_overrides(s, seed=99, bands="f115w,F200W", noise=False)
    assert t.seed == 99 and t.band_names == ("F115W", "F200W") and not t.output.noise
    assert t.output.rgb == ()  # the composite needed F160W
    with pytest.raises(ConfigError, match="did you mean F150W|no F150W"):
        sc.with_overrides(s, bands=["F150W"])


def test_to_toml_escapes_and_round_trips():
    d = {"scene": {"name": 'odd "name"\\ with\ttab', "x": 1.5e-9, "big": 2.0e12, "n": -3, "ok": True},
         "t": [{"a": [1, 2], "b": {"c": "d"}}, {"a": []}]}
    assert tomllib.loads(sc.to_toml(d)) == d


def test_scene_defaults_are_the_python_api_defaults():
    """One registry (clumpylen_jax.defaults): a scene file that omits a setting and a
    Python call that omits it get the same value."""
    import inspect

    from clumpylen_jax import model, population

    s = sc.scene_from_dict(minimal())
    build = inspect.signature(model.build_model).parameters
    assert s.render.source_pixel_arcsec == build["source_pixel_arcsec"].default
    assert s.render.lens_pixel_arcsec == build["lens_pixel_arcsec"].default
    acc, api = sc.Accuracy(), model.Accuracy()
    assert (acc.subsampling, acc.psf_oversampling, acc.source_mode, acc.linearise_tolerance,
            acc.source_flux_fraction) == (api.lens_subsampling, api.psf_oversampling, api.source_mode,
                                          api.linearise_tolerance, api.source_flux_fraction)
    assert s.render.accuracy == acc
    cmf, cfg = sc.CMF(), population.ClumpConfig()
    assert (cmf.slope, cmf.m_cut_msun, cmf.delta, cmf.gamma, cmf.m_min_msun, cmf.m_max_msun) == (
        cfg.cmf_slope, cfg.cmf_m_cut_msun, cfg.cmf_delta, cfg.cmf_gamma, cfg.cmf_m_min_msun,
        cfg.cmf_m_max_msun)
    sample = inspect.signature(population.sample_cmf_masses).parameters
    assert sample["slope"].default == cmf.slope and sample["m_max_msun"].default == cmf.m_max_msun


def test_lens_components_build_through_the_one_registry():
    """pipeline.build_lens builds scene components with lensing.clusters.lens_component
    (defaults.LENS_KINDS): a σ0-given dPIE is DPIE.from_sigma with the scene's D_ls/D_s,
    b0 = 6π (σ0/c)² D_ls/D_s in arcsec (Elíasdóttir et al. 2007)."""
    import jax
    import jax.numpy as jnp

    from clumpylen_jax import cosmology, pipeline
    from clumpylen_jax.constants import ARCSEC_PER_RAD, C_KMS
    from clumpylen_jax.lensing import DPIE, LensSum

    d = minimal()
    d["lens"]["components"] = [{"kind": "dpie", "sigma0_kms": 300.0, "rcore_arcsec": 0.1, "rcut_arcsec": 20.0,
                                "q": 0.7}, {"kind": "shear", "gamma1": 0.05}]
    s = sc.scene_from_dict(d)
    lens = pipeline.build_lens(s)
    assert isinstance(lens, LensSum) and isinstance(lens.lenses[0], DPIE)
    ratio = cosmology.dls_ds(s.lens.z_lens, s.z_source, pipeline._cosmology(s))
    b0 = 6 * math.pi * (300.0 / C_KMS) ** 2 * ARCSEC_PER_RAD * ratio
    ref = DPIE(b0, 0.1, 20.0, 0.7, 0.0, jnp.zeros(2))
    t1, t2 = jnp.array([0.3, -1.2, 4.0]), jnp.array([0.9, 0.2, -2.5])
    ours, expect = jax.jit(lambda a, b: (lens.lenses[0].deflection(a, b), ref.deflection(a, b)))(t1, t2)
    np.testing.assert_allclose(ours, expect, rtol=1e-12)
