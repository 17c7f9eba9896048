"""`clumpylen fit`: bad arguments fail fast with status 2 and one clear line."""

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
