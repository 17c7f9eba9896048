"""`clumpylen fit`: bad arguments fail fast with status 2 and one clear line."""

import pytest

from clumpylen_jax.cli import main


def test_fit_rejects_bad_image_arguments(capsys, tmp_path):
    assert main(["fit", "single-sersic", "--image", "F200W", "--out", str(tmp_path)]) == 2
    assert "BAND=FILE" in capsys.readouterr().err
    missing = tmp_path / "nope.fits"
    assert main(["fit", "single-sersic", "--image", f"F200W={missing}", "--out", str(tmp_path)]) == 2
    assert "existing FITS file" in capsys.readouterr().err
    real = tmp_path / "x.fits"
    real.write_bytes(b"")
    assert main(["fit", "single-sersic", "--image", f"F999W={real}", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "F999W" in err and "Traceback" not in err


_SAMPLER_SCENE = """
[scene]
name = "sampler-start"
seed = 4
z_source = 2.0

[source.bulge]
magnitudes = {{ F200W = 24.5 }}
re_arcsec = 0.15
n = 1.0
q = 0.8
pa_rad = 0.3

[source.clumps]
catalog = "{catalog}"

[render]
source_pixel_arcsec = 0.005
lens_pixel_arcsec = 0.01
field_arcsec = {{ x = [-0.35, 0.35], y = [-0.35, 0.35] }}
accuracy = "fast"

[[bands]]
instrument = "JWST/NIRCam"
filter = "F200W"
exptime_s = 3000.0
psf = "none"

[output]
noise = true
unlensed = false
hr = false
"""


@pytest.mark.slow
def test_sampler_starts_from_the_data_driven_fit_not_the_scenes_clumps(tmp_path):
    """`clumpylen fit --method emcee` on the mock path: the scene given to fit lists three
    clumps where there are none (a garbage catalogue); the sampled catalogue has the two
    clumps of the image, near their true positions, because the chain starts from the
    auto (data-driven) MAP fit and the scene's clumps are never read."""
    import json

    import numpy as np
    from astropy.table import Table

    from clumpylen_jax.cli import main

    true_pos = np.array([[-0.12, 0.08], [0.1, -0.1]])
    Table({"beta1_arcsec": true_pos[:, 0], "beta2_arcsec": true_pos[:, 1], "re_arcsec": [0.015, 0.02],
           "q": [1.0, 1.0], "pa_rad": [0.0, 0.0], "mag_F200W": [25.3, 25.6]}).write(
        tmp_path / "truth.ecsv", format="ascii.ecsv")
    Table({"beta1_arcsec": [0.2, -0.2, 0.0], "beta2_arcsec": [0.2, -0.2, 0.25],
           "re_arcsec": [0.05, 0.04, 0.03], "q": [1.0, 1.0, 1.0], "pa_rad": [0.0, 0.0, 0.0],
           "mag_F200W": [24.0, 24.5, 25.0]}).write(tmp_path / "garbage.ecsv", format="ascii.ecsv")
    for name, cat in (("sim.toml", "truth.ecsv"), ("fit.toml", "garbage.ecsv")):
        (tmp_path / name).write_text(_SAMPLER_SCENE.format(catalog=cat))
    assert main(["simulate", str(tmp_path / "sim.toml"), "--out", str(tmp_path / "run"), "-q"]) == 0
    out = tmp_path / "fit"
    assert main(["fit", str(tmp_path / "fit.toml"), "--image",
                 f"F200W={tmp_path / 'run' / 'bands' / 'F200W.fits'}", "--method", "emcee",
                 "--out", str(out), "-q"]) == 0
    t = Table.read(out / "fit.ecsv")
    assert t.meta["method"] == "emcee" and len(t) == 2, t
    got = np.c_[t["beta1_arcsec"], t["beta2_arcsec"]]
    d = np.hypot(*(got[:, None, :] - true_pos[None]).transpose(2, 0, 1))
    assert np.all(d.min(axis=0) < 0.031), d
    assert (out / "chains.npz").is_file()
    assert [s["action"] for s in json.loads((out / "fit_steps.json").read_text())][0] == "host"
