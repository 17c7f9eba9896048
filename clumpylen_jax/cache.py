"""Where clumpylen keeps things between runs, and JAX's persistent compilation cache.

One folder: ``$CLUMPYLEN_CACHE`` if set, else ``~/.cache/clumpylen_jax``. Inside it:

- ``jax/``: XLA executables (JAX's own persistent compilation cache). JAX keys each
  entry on a hash of the program (its StableHLO: shapes, dtypes, every operation and
  constant), the compile options, the jax/jaxlib versions and the device; a changed
  scene structure, code, JAX version or machine gives a new key, never a stale hit.
  Entries are not removed by clumpylen (delete the folder to reclaim the space).
- ``programs/``: compiled executables of the pipeline's programs (`programcache`): a
  second run skips Python tracing, lowering and the persistent cache's key hashing as
  well as XLA compilation;
- ``models/``: built scene models (`modelcache`): traced pixels, linearised clumps,
  rebinning operators (~160 MB for the paper scene);
- ``psf/``: diffraction PSFs (`psf.default_cache_dir`);
- ``rays/``: traced lens-plane corners (`raycache`);
- ``light/``: the host's light per unit flux on the run's grids and traced pixels
  (`lightcache`; ~150 MB for the paper scene, the last few kept).

``programs/hints/`` lists the programs a scene's last run used, so that the next run
reads them ahead (`programcache.ReadAhead`).

``programs/``, ``models/`` and ``light/`` are keyed on the source of every module of the package,
its version and the jax/jaxlib versions (besides their own inputs): a new release or
any edit of the code starts them over.

`cache_enabled` is the one switch: ``CLUMPYLEN_NO_CACHE=1`` (or ``clumpylen simulate
--no-cache``) turns every one of them off for the process.
"""

from __future__ import annotations

import os
from pathlib import Path

_OFF = ("1", "true", "yes", "on")


def cache_root() -> Path:
    """$CLUMPYLEN_CACHE if set, else ~/.cache/clumpylen_jax."""
    root = os.environ.get("CLUMPYLEN_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "clumpylen_jax"


def cache_enabled() -> bool:
    """False when CLUMPYLEN_NO_CACHE is set to 1/true/yes/on."""
    return os.environ.get("CLUMPYLEN_NO_CACHE", "").strip().lower() not in _OFF


def enable_compilation_cache(enabled: bool | None = None, folder=None) -> Path | None:
    """Point JAX's persistent compilation cache at `folder` (default cache_root()/jax;
    enabled None: follow `cache_enabled`); returns the folder, or None when off.

    Every program is kept, however short its compilation (JAX's default keeps only those
    over 1 s; the pipeline's dozens of small ones add up to seconds). Must run before
    the programs it should serve are compiled.
    """
    import jax
    from jax.experimental.compilation_cache import compilation_cache

    if enabled is None:
        enabled = cache_enabled()
    folder = (Path(folder) if folder is not None else cache_root() / "jax") if enabled else None
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_enable_compilation_cache", bool(enabled))
    jax.config.update("jax_compilation_cache_dir", None if folder is None else str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    # JAX settles on a cache (or none) at its first compilation: start that over
    compilation_cache.reset_cache()
    return folder


def read_ahead(scene, start: bool = True):
    """A `programcache.ReadAhead` of the programs a run of `scene` (a resolved Scene, its
    overrides applied) used last time, hinted by the scene's resolved settings (loading
    them from `start`); None with the cache off. Make it as early as a run knows its scene."""
    if not cache_enabled():
        return None
    import json

    from . import scene as scene_mod
    from .programcache import ReadAhead
    hint = json.dumps(scene_mod.resolved_dict(scene), sort_keys=True, default=str)
    return ReadAhead(cache_root() / "programs", hint, start)
