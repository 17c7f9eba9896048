"""What is kept between runs (compiled programs, traced rays) and the compile / run split."""

import hashlib
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from clumpylen_jax import cache, raycache
from clumpylen_jax.cli import main
from clumpylen_jax.lensing.analytic import SIS
from clumpylen_jax.lensing.tracing import trace_corners
from clumpylen_jax.pixels import Grid
from clumpylen_jax.timing import StageClock, _union_length

_CACHE_SETTINGS = ("jax_enable_compilation_cache", "jax_compilation_cache_dir",
                   "jax_persistent_cache_min_compile_time_secs",
                   "jax_persistent_cache_min_entry_size_bytes")


@pytest.fixture
def restore_jax_cache():
    """enable_compilation_cache changes JAX's process-wide settings: put them back."""
    from jax.experimental.compilation_cache import compilation_cache
    saved = {k: jax.config.values[k] for k in _CACHE_SETTINGS}
    yield
    for k, v in saved.items():
        jax.config.update(k, v)
    compilation_cache.reset_cache()


def test_union_length_counts_nested_spans_once():
    assert _union_length([(0, 4), (1, 2), (3, 6), (8, 9)]) == pytest.approx(7.0)
    assert _union_length([]) == 0.0


def test_stage_clock_splits_compile_from_run():
    clock = StageClock()
    scale = float(np.random.default_rng().uniform(1, 2))   # a new program for this test
    f = jax.jit(lambda x: jnp.sin(x) * scale + jnp.cumsum(x))
    with clock.stage("first call"):
        jax.block_until_ready(f(jnp.ones(64)))
    with clock.stage("python only"):
        time.sleep(0.05)
    split = clock.split()
    first, py = split["first call"], split["python only"]
    assert first["compile"] > 0 and first["compile"] <= first["total"]
    assert first["run"] == pytest.approx(first["total"] - first["compile"], abs=2e-3)
    assert py["compile"] == 0.0 and py["run"] >= 0.04


def test_switch_off_turns_every_cache_off(monkeypatch, tmp_path, restore_jax_cache):
    from clumpylen_jax.psf import default_cache_dir
    monkeypatch.setenv("CLUMPYLEN_CACHE", str(tmp_path))
    monkeypatch.setenv("CLUMPYLEN_NO_CACHE", "1")
    assert not cache.cache_enabled()
    assert cache.enable_compilation_cache() is None
    assert default_cache_dir() is False
    assert not jax.config.values["jax_enable_compilation_cache"]
    monkeypatch.delenv("CLUMPYLEN_NO_CACHE")
    assert cache.enable_compilation_cache() == tmp_path / "jax"
    assert default_cache_dir() == tmp_path / "psf"


def _sis_corners(theta_e, folder, grid):
    lens = SIS(jnp.asarray(theta_e), jnp.asarray([0.0, 0.0]))
    return raycache.traced_corners(lens, grid, trace_corners, folder)


def test_ray_cache_reads_back_bit_for_bit_and_keys_on_the_lens(monkeypatch, tmp_path):
    monkeypatch.setattr(raycache, "MIN_CORNERS", 0)
    grid = Grid.covering((-1.0, 1.0), (-1.0, 1.0), 0.05)
    b1, b2 = _sis_corners(1.0, tmp_path, grid)
    files = list(tmp_path.glob("corners_*.npy"))
    assert len(files) == 1
    # the file is what is read: overwrite it and the read-back changes with it
    c1, c2 = _sis_corners(1.0, tmp_path, grid)
    assert c1.tobytes() == b1.tobytes() and c2.tobytes() == b2.tobytes()
    ref1, ref2 = trace_corners(SIS(jnp.asarray(1.0), jnp.asarray([0.0, 0.0])), grid)
    assert ref1.tobytes() == b1.tobytes() and ref2.tobytes() == b2.tobytes()
    np.save(files[0], np.stack([b1 + 1.0, b2]))
    assert np.array_equal(_sis_corners(1.0, tmp_path, grid)[0], b1 + 1.0)
    # another Einstein radius, another grid: other files; no folder: nothing written
    _sis_corners(1.1, tmp_path, grid)
    _sis_corners(1.0, tmp_path, Grid.covering((-1.0, 1.0), (-1.0, 1.0), 0.04))
    assert len(list(tmp_path.glob("corners_*.npy"))) == 3
    _sis_corners(1.2, None, grid)
    assert len(list(tmp_path.glob("*"))) == 3


def _fits_digest(folder):
    from astropy.io import fits
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*.fits")):
        with fits.open(p) as hdul:
            for hdu in hdul:
                if hdu.data is not None:
                    h.update(hdu.data.tobytes())
    return h.hexdigest()


def test_cli_cache_on_off_same_images_and_prints_the_split(capsys, monkeypatch, tmp_path,
                                                           restore_jax_cache):
    monkeypatch.setenv("CLUMPYLEN_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("CLUMPYLEN_NO_CACHE", raising=False)
    assert main(["simulate", "single-sersic", "--out", str(tmp_path / "on")]) == 0
    out = capsys.readouterr().out
    assert "time split (stages summed over the main and background threads): compile" in out \
        and "files bands/: F200W.fits" in out
    assert any((tmp_path / "cache" / "jax").iterdir())       # programs were kept
    assert main(["simulate", "single-sersic", "--out", str(tmp_path / "off"), "--no-cache"]) == 0
    assert "compilation cache off" in capsys.readouterr().out
    assert _fits_digest(tmp_path / "on") == _fits_digest(tmp_path / "off")
    # a second run reads the host's light back (lightcache) and gives the same bits
    assert any((tmp_path / "cache" / "light").glob("*.pkl"))
    assert main(["simulate", "single-sersic", "--out", str(tmp_path / "again")]) == 0
    assert _fits_digest(tmp_path / "again") == _fits_digest(tmp_path / "on")


def test_cli_fit_keeps_its_programs_and_no_cache_keeps_none(monkeypatch, tmp_path,
                                                            restore_jax_cache):
    """`clumpylen fit` of an observation uses the persistent compilation cache as `simulate`
    does: the first fit writes programs, a second loads them and gives the same numbers bit
    for bit, and --no-cache writes nothing and also gives the same numbers."""
    import json

    from astropy.table import Table

    from clumpylen_jax.observations import write_cutout
    y, x = np.mgrid[:24, :24] - 11.5
    sci = 50.0 * np.exp(-np.hypot(x, y) / 3.0) + np.random.default_rng(4).normal(size=(24, 24))
    image = write_cutout(tmp_path / "c.fits", sci, np.ones_like(sci), extra={"PIXSCALE": 0.03})
    scene = tmp_path / "s.toml"
    scene.write_text(f'[scene]\nname = "t"\n\n[[observations]]\nfilter = "F150W"\n'
                     f'image = "{image}"\n\n[fit]\nclumps = "none"\n')
    monkeypatch.delenv("CLUMPYLEN_NO_CACHE", raising=False)
    runs = {}
    for name, cache_dir, extra in (("first", "cache", []), ("second", "cache", []),
                                   ("off", "cache_off", ["--no-cache"])):
        monkeypatch.setenv("CLUMPYLEN_CACHE", str(tmp_path / cache_dir))
        assert main(["fit", str(scene), "--out", str(tmp_path / name), "-q", *extra]) == 0
        runs[name] = (Table.read(tmp_path / name / "fit.ecsv").meta,    # the host, with errors
                      json.loads((tmp_path / name / "summary.json").read_text())["chi2_per_dof"])
        if name == "first":
            assert any((tmp_path / "cache" / "jax").iterdir())     # programs were kept
    assert not (tmp_path / "cache_off" / "jax").exists()
    assert runs["first"] == runs["second"] == runs["off"], runs
