"""Running a study on Dask: an embedded LocalCluster by default, or an existing cluster.

    run_study(study, out_dir, scheduler=None)

- scheduler None: a `dask.distributed.LocalCluster` on this machine, one single-threaded
  worker process per core (`n_workers` to change it); "ADDRESS" (tcp://host:8786): an
  existing cluster (e.g. one started by dask-jobqueue on SLURM or PBS); "synchronous":
  no Dask at all, every task in this process (tests, debugging).
- Only tasks without a result file are sent (resume); each result is written
  atomically by this process the moment its future completes, so a worker needs no
  shared file system. A worker that dies loses only the tasks it held: the scheduler
  reruns them elsewhere. Ctrl-C cancels what is queued; the files written stay valid.
- Every worker points JAX's persistent compilation cache at one directory
  (`$CLUMPYLEN_CACHE/jax`, default `~/.cache/clumpylen_jax/jax`), so a program compiled
  by one worker is loaded, not recompiled, by the others and by later runs.
- Workers use whatever JAX device they are given (CPU or GPU): nothing here picks one.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from .spec import Study
from .store import Store, gather
from .tasks import make_tasks


def cache_dir() -> str | None:
    """The shared JAX compilation cache (`cache.py`: $CLUMPYLEN_CACHE/jax or
    ~/.cache/clumpylen_jax/jax); None when CLUMPYLEN_NO_CACHE turns caching off."""
    from ..cache import cache_enabled, cache_root

    return str(cache_root() / "jax") if cache_enabled() else None


def enable_compilation_cache(path: str | None) -> None:
    """Point this process's JAX at the study's compilation cache (None: no cache).
    Before anything compiles: JAX settles on a cache at its first compilation."""
    from ..cache import enable_compilation_cache as enable

    enable(path is not None, folder=path)


def _plugin(path: str):
    from distributed.diagnostics.plugin import WorkerPlugin

    class JaxCache(WorkerPlugin):
        """Sets the shared compilation cache and float64 (as the CLI does) on every worker."""

        name = "clumpylen-jax-cache"

        def setup(self, worker):
            from .. import enable_float64

            enable_compilation_cache(path)
            enable_float64()  # a worker is our process: compute as `clumpylen` does

    return JaxCache()


class _Bar:
    """A one-line progress bar on stderr (a terminal only)."""

    def __init__(self, total: int, done: int, enabled: bool):
        self.total, self.done, self.t0 = total, done, time.perf_counter()
        self.start = done
        self.on = enabled and sys.stderr.isatty()
        self.show()

    def show(self):
        if not self.on:
            return
        frac = self.done / max(self.total, 1)
        rate = (self.done - self.start) / max(time.perf_counter() - self.t0, 1e-9) * 3600
        sys.stderr.write(f"\r[{'#' * int(30 * frac):<30}] {self.done}/{self.total} tasks "
                         f"({rate:.0f}/h)")
        sys.stderr.flush()

    def step(self):
        self.done += 1
        self.show()

    def close(self):
        if self.on:
            sys.stderr.write("\n")


def _run_local(study, todo, store, bar):
    from .work import run_task

    enable_compilation_cache(cache_dir())
    for t in todo:
        store.write(t.id, run_task(study, t))
        bar.step()


def _client(scheduler, n_workers):
    from distributed import Client, LocalCluster

    if scheduler:
        return Client(scheduler), None
    cluster = LocalCluster(n_workers=n_workers or os.cpu_count() or 1, threads_per_worker=1,
                           processes=True, dashboard_address=None)
    return Client(cluster), cluster


def _run_dask(study, todo, store, bar, scheduler, n_workers):
    from distributed import as_completed

    from .work import run_task

    client, cluster = _client(scheduler, n_workers)
    futures = {}
    try:
        client.register_plugin(_plugin(cache_dir()))
        [study_f] = client.scatter([study], broadcast=True)
        token = os.urandom(4).hex()
        for t in todo:
            f = client.submit(run_task, study_f, t, key=f"clumpylen-{t.id}-{token}", pure=False)
            futures[f] = t
        failed = []
        for f in as_completed(list(futures)):
            t = futures[f]
            if f.status == "error":
                failed.append(f"{t.id}: {f.exception()!r}")
                continue
            store.write(t.id, f.result())
            bar.step()
        if failed:
            raise RuntimeError(f"{len(failed)} task(s) failed (rerun to retry them): " + "; ".join(failed[:3]))
    finally:
        client.cancel(list(futures))
        client.close()
        if cluster is not None:
            cluster.close()


def run_study(study: Study, out_dir, *, scheduler: str | None = None, n_workers: int | None = None,
              progress: bool = True) -> dict:
    """Run (or resume) a study into out_dir; returns the gathered products {name: path}."""
    store = Store(out_dir)
    store.init(study)
    tasks = make_tasks(study)
    todo = [t for t in tasks if not store.done(t.id)]
    bar = _Bar(len(tasks), len(tasks) - len(todo), progress)
    try:
        if todo and scheduler == "synchronous":
            _run_local(study, todo, store, bar)
        elif todo:
            _run_dask(study, todo, store, bar, scheduler, n_workers)
    finally:
        bar.close()
    files = gather(study, store, tasks)
    return {"tasks": len(tasks), "ran": len(todo), "files": {k: str(Path(v)) for k, v in files.items()}}
