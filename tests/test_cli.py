"""The clumpylen command: exit codes, one-line errors, scenes/show/validate, overrides."""

import sys
import tomllib
import types

import pytest

from clumpylen_jax import scene as sc
from clumpylen_jax.cli import main

GOOD = """
[scene]
name = "tiny"
z_source = 2.0

[source.bulge]
re_arcsec = 0.1
magnitudes = { F200W = 24.0, F115W = 24.5 }

[[bands]]
instrument = "JWST/NIRCam"
filter = "F115W"
exptime_s = 100.0

[[bands]]
instrument = "JWST/NIRCam"
filter = "F200W"
exptime_s = 100.0
"""


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def write(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def assert_user_error(code, err, *fragments):
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("clumpylen: error:"), err
    assert "Traceback" not in err
    for f in fragments:
        assert f in lines[0], (f, lines[0])


def test_scenes_lists_builtins(capsys):
    code, out, _ = run(capsys, "scenes")
    assert code == 0
    names = [line.split()[0] for line in out.strip().splitlines()]
    assert {"cosmic-archipelago", "a2744-system3", "single-sersic"} <= set(names)


@pytest.mark.parametrize("name", ["cosmic-archipelago", "a2744-system3", "single-sersic"])
def test_show_parses_back_to_the_same_scene(capsys, name):
    ref = sc.load_scene(name)
    for extra in ([], ["--resolved"]):
        code, out, _ = run(capsys, "show", name, *extra)
        assert code == 0
        assert sc.scene_from_dict(tomllib.loads(out), base_dir=ref.base_dir) == ref


def test_show_file(capsys, tmp_path):
    p = write(tmp_path, GOOD)
    code, out, _ = run(capsys, "show", p)
    assert code == 0 and out == GOOD


def test_validate_prints_resolved_scene_and_stages(capsys, tmp_path):
    code, out, _ = run(capsys, "validate", write(tmp_path, GOOD))
    assert code == 0
    assert "stages: render:F115W, psf:F115W, render:F200W, psf:F200W, noise, hr" in out
    resolved = tomllib.loads(out)  # the comment lines are TOML comments
    assert resolved["render"]["lens_pixel_arcsec"] == 0.0025 and resolved["bands"][0]["psf"] == "diffraction"


def test_typo_suggestion(capsys, tmp_path):
    code, _, err = run(capsys, "validate", write(tmp_path, GOOD.replace("re_arcsec", "re_arcec")))
    assert_user_error(code, err, "unknown key 'source.bulge.re_arcec'", "did you mean 're_arcsec'?")


def test_missing_required_key(capsys, tmp_path):
    code, _, err = run(capsys, "validate", write(tmp_path, GOOD.replace("z_source = 2.0", "")))
    assert_user_error(code, err, "scene.z_source", "required")


def test_bad_type(capsys, tmp_path):
    code, _, err = run(capsys, "validate", write(tmp_path, GOOD.replace("exptime_s = 100.0", 'exptime_s = "long"', 1)))
    assert_user_error(code, err, "bands[0].exptime_s = 'long'", "expected a number")


def test_nonexistent_files(capsys, tmp_path):
    code, _, err = run(capsys, "validate", str(tmp_path / "missing.toml"))
    assert_user_error(code, err, "missing.toml")
    code, _, err = run(capsys, "validate", "no-such-scene")
    assert_user_error(code, err, "scene = 'no-such-scene'", "built-in scene")
    text = GOOD.replace('filter = "F115W"', 'filter = "F115W"\npsf = "psfs/F115W.fits"')
    code, _, err = run(capsys, "validate", write(tmp_path, text))
    assert_user_error(code, err, "bands[0].psf = 'psfs/F115W.fits'", "an existing file")


def test_toml_syntax_error_has_line_and_column(capsys, tmp_path):
    code, _, err = run(capsys, "validate", write(tmp_path, "[scene]\nz_source = \n"))
    assert_user_error(code, err, "invalid TOML", "line 2")


def test_usage_errors_exit_2(capsys):
    assert run(capsys, "simulate", "single-sersic")[0] == 2  # --out is required
    assert run(capsys, "frobnicate")[0] == 2
    assert run(capsys, "--help")[0] == 0


@pytest.fixture
def fake_modules(monkeypatch):
    """Stand-ins for pipeline/plotting/analysis that record how they were called."""
    calls = {}

    def simulate(scene, out_dir, *, bands=None, seed=None, noise=None, progress=True,
                 programs=None):
        calls["simulate"] = dict(scene=scene, out_dir=out_dir, bands=bands, seed=seed, noise=noise,
                                 progress=progress)
        return {"bands": {"F200W": {"total_counts_per_s": 12.5, "total_counts": 37500.0}},
                "timings_s": {"render": 0.5}}

    for mod, name, fn in [("pipeline", "simulate", simulate),
                          ("plotting", "plot_run", lambda d: calls.setdefault("plot", d)),
                          ("analysis", "analyze_run", lambda d, **kw: calls.setdefault("analyze", (d, kw)))]:
        m = types.ModuleType(f"clumpylen_jax.{mod}")
        setattr(m, name, fn)
        monkeypatch.setitem(sys.modules, f"clumpylen_jax.{mod}", m)
    return calls


def test_simulate_passes_overrides(capsys, tmp_path, fake_modules):
    p = write(tmp_path, GOOD)
    out = tmp_path / "run"
    code, stdout, _ = run(capsys, "simulate", p, "--out", str(out), "--seed", "5", "--bands", "f200w",
                          "--no-noise", "--plots")
    assert code == 0, stdout
    c = fake_modules["simulate"]
    assert c["scene"].name == "tiny" and c["out_dir"] == str(out)
    assert (c["bands"], c["seed"], c["noise"], c["progress"]) == (["F200W"], 5, False, True)
    assert fake_modules["plot"] == str(out)
    assert "F200W: source 12.5 counts/s (37500 counts in the exposure)" in stdout
    code, stdout, _ = run(capsys, "simulate", p, "--out", str(out), "--quiet")
    c = fake_modules["simulate"]
    assert code == 0 and stdout == "" and (c["bands"], c["seed"], c["noise"], c["progress"]) == (None, None, None, False)


def test_simulate_rejects_unknown_band_before_running(capsys, tmp_path, fake_modules):
    code, _, err = run(capsys, "simulate", write(tmp_path, GOOD), "--out", str(tmp_path / "r"), "--bands", "F150W")
    assert_user_error(code, err, "--bands", "F115W, F200W")
    assert "simulate" not in fake_modules


def test_plot_and_analyze(capsys, tmp_path, fake_modules):
    from clumpylen_jax.rundir import write_manifest
    write_manifest(tmp_path)   # a (tiny) complete run: plot and analyze check the manifest
    assert run(capsys, "plot", str(tmp_path))[0] == 0 and fake_modules["plot"] == str(tmp_path)
    assert run(capsys, "analyze", str(tmp_path), "--snr-threshold", "3")[0] == 0
    assert fake_modules["analyze"] == (str(tmp_path), {"snr_threshold": 3.0})
    code, _, err = run(capsys, "plot", str(tmp_path / "nope"))
    assert_user_error(code, err, "run directory not found")


def test_long_run_memory_is_reset_after_the_command():
    """The simulate command's memory settings (malloc thresholds, frozen collector) do not
    outlive it: a process that goes on (a test session) collects its objects as before."""
    import gc

    from clumpylen_jax.cli import _long_run_memory

    with _long_run_memory():
        assert gc.get_freeze_count() > 0
    assert gc.get_freeze_count() == 0
