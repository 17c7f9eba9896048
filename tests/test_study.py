"""Studies (`clumpylen study`): validation, resume, determinism, Dask with a killed worker,
and the injection–recovery completeness against the Fisher forecast."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from clumpylen_jax.cli import main
from clumpylen_jax.errors import ConfigError
from clumpylen_jax.study import load_study, run_study
from clumpylen_jax.study.store import Store
from clumpylen_jax.study.tasks import draw_sample, make_tasks

# fixtures/study_tiny.toml: an unlensed exponential host in one NIRCam band on a 33 × 33 pixel
# field (compiles fast); the study files below name it "tiny.toml"
SCENE = (Path(__file__).resolve().parents[1] / "fixtures" / "study_tiny.toml").read_text(encoding="utf-8")

SIMULATE = """
[study]
kind = "simulate"
seed = 11
scenes = ["tiny.toml"]
[clumps]
mass_msun = { min = 1e6, max = 1e7 }
re_pc = { min = 20.0, max = 60.0, scale = "linear" }
region_arcsec = 0.25
[simulate]
samples = {samples}
clumps_per_sample = [0, 3]
buckets = [3]
"""


def _write(tmp_path: Path, study_text: str, name="study.toml") -> Path:
    (tmp_path / "tiny.toml").write_text(SCENE)
    p = tmp_path / name
    p.write_text(study_text)
    return p


def _arrays_equal(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(
        a[k].dtype == b[k].dtype and a[k].shape == b[k].shape and a[k].tobytes() == b[k].tobytes()
        for k in a)


# ------------------------------------------------------------------ validation (no compute)


@pytest.mark.parametrize("text, setting, hint", [
    ('[study]\nkind = "simulate"\nscenes = ["tiny.toml"]\n[clumps]\nmass_mson = [1e6]\n',
     "clumps.mass_mson", "mass_msun"),
    ('[study]\nkind = "simulate"\nscens = ["tiny.toml"]\n', "study.scens", "scenes"),
    ('[study]\nkind = "completness"\nscenes = ["tiny.toml"]\n', "study.kind", None),
    ('[study]\nkind = "completeness"\nscenes = ["tiny.toml"]\n[clumps]\nmass_msun = {min = 1e5, max = 1e7}\n',
     "clumps.mass_msun.num", None),
    ('[study]\nkind = "simulate"\nscenes = ["nope.toml"]\n', "study.scenes[0]", None),
    ('[study]\nkind = "simulate"\nscenes = ["tiny.toml"]\n[completeness]\npositions = 4\n',
     "completeness", None),
    ('[study]\nkind = "simulate"\nscenes = ["tiny.toml"]\n[vary]\nz_source = [-1.0]\n',
     "vary.z_source[0]", None),
    ('[study]\nkind = "simulate"\nscenes = ["tiny.toml"]\n[vary]\nlens = [{z_lens = 0.3, '
     'components = [{kind = "SIS", theta_e = 1.0}]}]\n', "lens", None),
    ('[study]\nkind = "simulate"\nscenes = ["tiny.toml"]\n[simulate]\nclumps_per_sample = [0, 9]\n'
     'buckets = [4]\n', "simulate.buckets", None),
])
def test_invalid_study_names_the_key(tmp_path, text, setting, hint):
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        load_study(p)
    assert setting in str(exc.value)
    if hint:
        assert f"did you mean '{hint}'" in str(exc.value)


def test_cli_invalid_study_exits_2_before_work(tmp_path, capsys):
    p = _write(tmp_path, '[study]\nkind = "simulate"\nscenes = ["tiny.toml"]\n[clumps]\nre_pcc = [3]\n')
    assert main(["study", str(p), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "clumps.re_pcc" in err and "re_pc" in err
    assert not (tmp_path / "o").exists()            # nothing started


def test_samples_are_reproducible_alone(tmp_path):
    study = load_study(_write(tmp_path, SIMULATE.replace("{samples}", "40")))
    a = [draw_sample(study, i) for i in range(40)]
    b = draw_sample(study, 17)
    assert np.array_equal(a[17].mass_msun, b.mass_msun) and a[17].noise_seed == b.noise_seed
    assert len({s.noise_seed for s in a}) == 40
    assert {len(s.mass_msun) for s in a} == {0, 1, 2, 3}
    assert all(t.shape == (0, 3) for t in make_tasks(study))       # one bucket: one program


# ------------------------------------------------------------------ resume, interrupt, determinism


def test_simulate_resume_interrupt_and_determinism(tmp_path, monkeypatch):
    import xarray as xr

    from clumpylen_jax.study import runner, work

    study = load_study(_write(tmp_path, SIMULATE.replace("{samples}", "4")))
    full = run_study(study, tmp_path / "a", scheduler="synchronous", progress=False)
    assert full["ran"] == 4
    ds = xr.open_zarr(tmp_path / "a" / "dataset.zarr")             # the one-line load
    assert ds["image"].shape[:2] == (4, 1) and ds["clump_valid"].shape == (4, 3)
    assert np.all(np.isfinite(ds["image"].values)) and np.all(ds["variance"].values > 0)
    n = ds["n_clumps"].values
    assert np.array_equal(ds["clump_valid"].values.sum(1), n)
    # more clumps, more light: each sample's noiseless image holds host + its clumps
    host = ds["noiseless"].values[n == 0]
    if host.size:
        assert np.all(ds["noiseless"].values[n > 0].sum((1, 2, 3)) > host[0].sum())

    # Ctrl-C after the second task: the store keeps two complete files, nothing half-written
    real = work.run_task
    calls = {"n": 0}

    def interrupted(study, task):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(study, task)

    monkeypatch.setattr(work, "run_task", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_study(study, tmp_path / "b", scheduler="synchronous", progress=False)
    files = sorted(os.listdir(tmp_path / "b" / "tasks"))
    assert len(files) == 2 and all(f.endswith(".npz") for f in files)
    monkeypatch.setattr(work, "run_task", real)
    again = run_study(study, tmp_path / "b", scheduler="synchronous", progress=False)
    assert again["ran"] == 2                                        # only the missing ones
    assert run_study(study, tmp_path / "b", scheduler="synchronous", progress=False)["ran"] == 0
    sa, sb = Store(tmp_path / "a"), Store(tmp_path / "b")
    for t in make_tasks(study):
        assert _arrays_equal(sa.read(t.id), sb.read(t.id)), t.id   # bit for bit
    # another study into the same directory is refused
    other = load_study(_write(tmp_path, SIMULATE.replace("{samples}", "5"), "other.toml"))
    with pytest.raises(ConfigError, match="--out"):
        run_study(other, tmp_path / "a", scheduler="synchronous", progress=False)
    monkeypatch.delenv("CLUMPYLEN_NO_CACHE", raising=False)
    assert runner.cache_dir().endswith(os.path.join("clumpylen_jax", "jax")) or \
        os.environ.get("CLUMPYLEN_CACHE")
    monkeypatch.setenv("CLUMPYLEN_NO_CACHE", "1")   # the one switch turns the workers' cache off too
    assert runner.cache_dir() is None


# ------------------------------------------------------------------ a real Dask cluster


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_dask_cluster_with_a_killed_worker(tmp_path):
    """Scheduler + two workers on loopback, one killed mid-study: every task once, identical."""
    study_path = _write(tmp_path, SIMULATE.replace("{samples}", "12"))
    study = load_study(study_path)
    ref = run_study(study, tmp_path / "ref", scheduler="synchronous", progress=False)
    bin_dir = Path(sys.executable).parent
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "CLUMPYLEN_CACHE": str(tmp_path / "cache")}
    procs = [subprocess.Popen([str(bin_dir / "dask"), "scheduler", "--host", "127.0.0.1",
                               "--port", str(port), "--no-dashboard"], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        time.sleep(3)
        workers = [subprocess.Popen([str(bin_dir / "dask"), "worker", addr, "--nthreads", "1",
                                     "--no-nanny", "--host", "127.0.0.1", "--no-dashboard"],
                                    env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                   for _ in range(2)]
        procs += workers
        out = tmp_path / "dask"
        run = subprocess.Popen([str(bin_dir / "clumpylen"), "study", str(study_path), "--out", str(out),
                                "--scheduler", addr, "--quiet"], env=env)
        procs.append(run)
        deadline = time.time() + 400
        while time.time() < deadline and len(list((out / "tasks").glob("*.npz"))) < 3:
            time.sleep(0.2)
        assert len(list((out / "tasks").glob("*.npz"))) >= 3, "the study did not start"
        workers[0].send_signal(signal.SIGKILL)                      # a worker dies mid-study
        assert len(list((out / "tasks").glob("*.npz"))) < 12
        assert run.wait(timeout=400) == 0
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
    tasks = make_tasks(study)
    names = sorted(f.name for f in (out / "tasks").iterdir())
    assert names == sorted(f"{t.id}.npz" for t in tasks)            # every task exactly once
    sa, sb = Store(tmp_path / "ref"), Store(out)
    for t in tasks:
        assert _arrays_equal(sa.read(t.id), sb.read(t.id)), t.id
    assert ref["tasks"] == len(tasks)


# ------------------------------------------------------------------ completeness vs Fisher


@pytest.mark.slow
def test_completeness_falls_where_fisher_snr_crosses_5(tmp_path):
    from astropy.table import Table

    study = load_study(_write(tmp_path, """
[study]
kind = "completeness"
seed = 3
scenes = ["tiny.toml"]
[clumps]
mass_msun = { min = 1e5, max = 3e7, num = 6 }
re_pc = [30.0]
region_arcsec = 0.25
[completeness]
positions = 16
positions_per_task = 16
map_npix = 6
nsigma = 5.0
npixels = 1
"""))
    res = run_study(study, tmp_path / "c", scheduler="synchronous", progress=False)
    t = Table.read(res["files"]["table"])
    t.sort("mass_msun")
    snr, comp = np.asarray(t["fisher_snr_median"]), np.asarray(t["completeness"])
    assert np.all(np.diff(snr) > 0)                                 # S/N grows with mass
    assert snr.min() < 2 and snr.max() > 12                         # the grid spans the fall
    assert comp[snr > 12].min() >= 0.8 and comp[snr < 2].max() <= 0.2
    # the 50 % point (interpolated in log S/N) is where the Fisher forecast says S/N ≈ 5
    k = int(np.argmax(comp >= 0.5))
    w = (0.5 - comp[k - 1]) / (comp[k] - comp[k - 1])
    snr50 = np.exp((1 - w) * np.log(snr[k - 1]) + w * np.log(snr[k]))
    # measured: 2.71 (647784b), 2.46 since the noise keys changed (one position of 16 at S/N
    # 3.1 detected more: 9 → 10); the marginal Fisher S/N (R_e and centre free) is below a
    # detection's, which knows the clump's shape: the 50 % point sits under 5, within 2.5×
    assert 2.0 < snr50 < 10, snr50
    assert all(Path(f).exists() for f in res["files"].values())


@pytest.mark.slow
def test_vmapped_fisher_matches_the_inference_package(tmp_path):
    """The study's vmapped Fisher S/N equals inference.detect.clump_detectability, clump by clump."""
    from clumpylen_jax.inference.detect import clump_detectability
    from clumpylen_jax.study import work

    study = load_study(_write(tmp_path, SIMULATE.replace("{samples}", "2")))
    var = work.variant(study, 0)
    pos = var.center_arcsec + np.array([[0.1, -0.05], [-0.2, 0.12]])
    flux = np.array([[0.3], [0.8]])
    re = np.array([0.004, 0.008])
    new = work._clumps(pos, flux, re, study.clumps)
    snr = np.asarray(work.fisher_snr(var.model(1), var.base, new))[:, 0]
    for k in range(2):
        one = work._clumps(pos[k:k + 1], flux[k:k + 1], re[k:k + 1], study.clumps)
        t = clump_detectability(var.model(1), work._append(var.base, one))
        assert snr[k] == pytest.approx(t["snr_flux_F200W"][0], rel=1e-6)


@pytest.mark.slow
def test_fit_study_recovers_clumps_from_a_start_off_the_truth(tmp_path):
    from astropy.table import Table

    study = load_study(_write(tmp_path, """
[study]
kind = "fit"
seed = 5
scenes = ["tiny.toml"]
[clumps]
mass_msun = { min = 5e6, max = 2e7 }
re_pc = { min = 40.0, max = 80.0 }
region_arcsec = 0.25
[fit]
samples = 3
clumps_per_sample = 2
"""))
    res = run_study(study, tmp_path / "f", scheduler="synchronous", progress=False)
    t = Table.read(res["files"]["table"])
    assert len(t) == 6
    start_err = np.abs(t["start_flux_F200W"] / t["true_flux_F200W"] - 1)
    fit_err = np.abs(t["fit_flux_F200W"] / t["true_flux_F200W"] - 1)
    assert np.all(start_err > 0) and np.median(fit_err) < np.median(start_err)
    pull = (t["fit_flux_F200W"] - t["true_flux_F200W"]) / t["err_flux_F200W"]
    assert np.all(np.abs(pull) < 5)
