"""plotting: every figure of a run is a PNG; what a run lacks is skipped."""

import pytest

from _fake_run import make_fake_run
from clumpylen_jax import plotting

PNG = b"\x89PNG\r\n\x1a\n"
CATALOGUE = {"clump_mass_function.png", "clump_size_mass.png", "clump_ages.png"}


@pytest.fixture(scope="module")
def lensed_run(tmp_path_factory):
    return make_fake_run(tmp_path_factory.mktemp("plots") / "lensed", lensed=True)


def test_lensed_run_makes_all_figures(lensed_run):
    paths = plotting.plot_run(lensed_run)
    names = {p.name for p in paths}
    assert names == CATALOGUE | {"lens_planes.png", "mosaic.png"}
    for p in paths:
        assert p.parent == lensed_run / "plots"
        assert p.read_bytes()[:8] == PNG and p.stat().st_size > 5000
    assert not list((lensed_run / "plots").glob(".*tmp*"))  # atomic writes left nothing behind


def test_unlensed_without_catalogue_skips(tmp_path):
    run = make_fake_run(tmp_path / "u")
    (run / "catalog.ecsv").unlink()
    out = tmp_path / "figs"
    paths = plotting.plot_run(run, out_dir=out)
    assert [p.name for p in paths] == ["mosaic.png"]
    assert (out / "mosaic.png").read_bytes()[:8] == PNG


def test_brown_gnedin_relation():
    assert plotting.brown_gnedin_re_pc(1e4) == pytest.approx(2.55)
    assert plotting.brown_gnedin_re_pc(1e6) == pytest.approx(2.55 * 100**0.24)


def test_cli_plot(lensed_run, capsys, tmp_path):
    from clumpylen_jax.cli import main

    assert main(["plot", str(lensed_run)]) == 0
    assert "mosaic.png" in capsys.readouterr().out
    assert main(["plot", str(tmp_path / "missing")]) == 2
