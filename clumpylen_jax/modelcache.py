"""Built models kept on disk between runs, keyed by the content of what builds them.

`model.build_model` makes the static decisions of a scene (traced pixels, linearised
clump images, host-core footprints, sparse rebinning operators, stored source tiles):
seconds of NumPy for the paper scene on every run, although they depend only on the
scene. `build` keeps the built `SceneModel` under ``<cache>/models/`` (a pickle of its
arrays and static fields) and reads it back when every input is the same.

The file name is a SHA-256 of: every argument of `build_model` (the source's and the
lens's pytree structure and every leaf's dtype, shape and bytes; each band's fields and
PSF array; field, pixel scales, accuracy knobs, dtype); the source of every module of the
package and its version; the jax, jaxlib, numpy versions, backend and x64 switch
(`programcache`). Any change gives a new name, so a stale model is never read; the model
read back holds the built one's arrays bit for bit. An input whose repr is an object
address cannot be keyed: such a model is built every time. Files are written atomically;
they are read with pickle, so the cache folder must be as trusted as the code itself (it
is the user's own, like JAX's compilation cache).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import pickle
from pathlib import Path


from .io import atomic_write
from .programcache import _environment, _package_digest, feed_pytree

_LAYOUT = "1"
# A built paper scene is ~160 MB and every seed builds another: keep only the models of the
# last few runs (most recently used first), so the folder cannot grow without bound.
KEEP_MODELS = 4


def model_key(source, bands, lens, **settings) -> str | None:
    """Hex SHA-256 of everything that sets a built model (module docstring), or None."""
    h = hashlib.sha256(f"{_LAYOUT}\0{_environment()}\0".encode())
    h.update(_package_digest())
    band_fields = [dataclasses.asdict(b) for b in bands]
    for part in (source, band_fields, lens, sorted(settings.items(), key=lambda kv: kv[0])):
        if not feed_pytree(h, part):
            return None
    return h.hexdigest()


def build(build_fn, source, bands, *, lens=None, folder=None, submit=None, **settings):
    """build_fn(source, bands, lens=lens, **settings), read from / kept in `folder`
    (None: built, nothing read or written); `submit`: see `pickled`."""
    key = None if folder is None else model_key(source, bands, lens, **settings)
    if key is None:
        return build_fn(source, bands, lens=lens, **settings)
    return pickled(Path(folder), f"model-{key[:40]}.pkl",
                   lambda: build_fn(source, bands, lens=lens, **settings), KEEP_MODELS,
                   "model-*.pkl", submit=submit)


def pickled(folder: Path, name: str, compute, keep: int, pattern: str, stored=lambda x: x,
            submit=None):
    """folder/name read back (pickle), else compute() written there atomically as stored(it),
    keeping the `keep` most recently used files of folder that match `pattern`. A truncated
    or foreign file is computed again and replaced.

    submit: a function (fn, *args) that calls fn(*args) in the background (an executor's
    `submit`; its owner waits for it before its outputs count as written), so that the
    caller goes on at once: JAX arrays still being computed are waited for there, not
    here. None: written here."""
    path = folder / name
    if path.is_file():
        try:
            value = pickle.loads(path.read_bytes())
            path.touch()        # most recently used: kept longest by evict
            return value
        except Exception:       # truncated or from other code: computed again and replaced
            pass
    value = compute()
    (_write if submit is None else functools.partial(submit, _write))(
        path, value, stored, keep, pattern)
    return value


def _write(path: Path, value, stored, keep: int, pattern: str):
    with atomic_write(path, "wb") as fh:
        pickle.dump(stored(value), fh, protocol=pickle.HIGHEST_PROTOCOL)
    evict(path.parent, keep, pattern)


def evict(folder: Path, keep: int, pattern: str):
    """Delete all but the `keep` most recently used files of `folder` matching `pattern`."""
    def mtime(p):
        try:
            return p.stat().st_mtime
        except OSError:         # removed meanwhile by another run
            return 0.0
    for old in sorted(folder.glob(pattern), key=mtime, reverse=True)[keep:]:
        old.unlink(missing_ok=True)
