"""The host's light per unit flux kept on disk between runs, keyed by the content of what
sets it.

A run draws the host (bulge, textured disk with arms) per unit flux three times: at the
3.5 M traced lens-plane pixels, on the unlensed bands' sub-grids and on the 2047²
high-resolution source grid (the paper scene: ~2/3 of a warm run's program execution,
libm's pow, atan2 and cos at every sample). That light depends only on the host's
geometry and the grids, not on the clumps, the host's fluxes or the noise: `kept` reads it
back when every input is the same, and the programs then take it as data
(`SceneModel.with_host_light`). The images are the same bit for bit whether the light
was read back, computed in this run or computed with the cache off: it is always computed
by its own program (`programcache`) and handed to the next one as an input.

The file name is a SHA-256 of: the light's name; every argument of its program (pytree
structure, arrays by dtype, shape and bytes, other leaves by repr: the host's geometry,
the traced pixels or the grids, the accuracy knobs); the source of every module of the
package and its version; the jax, jaxlib versions, backend, x64 switch and the host CPU
(`programcache`: the values are XLA's arithmetic on that machine). Any change gives a new
name, so stale light is never read. Files are written atomically and read with pickle
(the cache folder must be as trusted as the code, as for `modelcache`); only the most
recently used `KEEP_FILES` are kept.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import jax
import numpy as np

from .modelcache import pickled
from .programcache import _environment, _machine, _package_digest, feed_pytree

_LAYOUT = "1"
# the paper scene keeps ~190 MB in three files per host geometry
KEEP_FILES = 9


def light_key(name: str, args) -> str | None:
    """Hex SHA-256 of a light's name, its program's arguments and the code (see above), or
    None when an argument cannot be keyed (its repr is an object address)."""
    h = hashlib.sha256(f"{_LAYOUT}\0{name}\0{_environment()}\0{_machine()}\0".encode())
    h.update(_package_digest())
    return h.hexdigest() if feed_pytree(h, args) else None


def kept(name: str, compute, args, folder=None, submit=None):
    """compute() (a pytree of arrays, the light of `args`), read from / written to `folder`
    (None: computed, nothing read or written). Read back, its arrays are NumPy's.
    submit: writes the file in the background (`modelcache.pickled`), so that the caller
    need not wait for the program to finish."""
    key = None if folder is None else light_key(name, args)
    if key is None:
        return compute()
    return pickled(Path(folder), f"{name}-{key[:40]}.pkl", compute, KEEP_FILES, "*.pkl",
                   lambda light: jax.tree_util.tree_map(np.asarray, light), submit=submit)
