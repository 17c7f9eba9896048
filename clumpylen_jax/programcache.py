"""Compiled programs kept on disk between runs, keyed by content.

JAX's persistent compilation cache (`cache.py`) skips XLA's compilation, but every
process still traces the Python model to a jaxpr, lowers it to StableHLO, serialises
and hashes that module (its cache key) before it can look there. Keeping the lowered
program (`jax.export`) skips the tracing, but not reading the module back, lowering the
call around it and hashing it (~2 s of CPU over the paper scene's four programs on a
loaded host). `call` keeps the compiled executable itself
(`jax.experimental.serialize_executable`) under ``<cache>/programs/``, so that a later
process loads it and calls it at once. Loading stays proportional to the code's size
(XLA links the executable's machine code): the band render's 13 MB takes ~3 s on a
loaded 2-core host.

What a file is keyed on (a SHA-256; any change gives a new name, so a stale program is
never read): the program's name; the structure of its arguments (pytree definition,
every array's shape and dtype; array *values* are inputs, not part of the program);
every non-array argument (equinox static fields such as grids, stamp sides, accuracy
knobs; numpy arrays by their bytes) -- these are baked into the program; the source of
every module of the clumpylen_jax package and its version; the jax and jaxlib
versions, the backend, device kind and platform version, the host CPU's features (an
executable is machine code for them), and the x64 switch. A program whose key cannot
be written down completely (an argument whose repr is an object address) is not
cached: it is compiled as usual. Files are written atomically and never removed by
clumpylen (delete the folder to reclaim the space); they are read with pickle, so the
cache folder must be as trusted as the code itself (as for `modelcache`).

Every program is the same computation whether the cache is on, off or cold: the traced
function is exported (`jax.export`) and `Exported.call` compiled, and that executable
is called or, from the cache, the one stored after that compilation: the images are bit
for bit the same in each case. A stored program is compiled with JAX's persistent cache
off where JAX's cache held it (`_compile_own`), and a stored one that fails its first call
is compiled again. `function` gives the same program as a function, loaded or compiled
once for many calls of one shape; `compiled` loads or compiles it at once (in a background
thread, before the values it will be called with exist).

Reading ahead (`ReadAhead`): a run that asks for the same programs as the last run with
the same hint (e.g. the same resolved scene) finds them loaded already. The files that
run used are listed under ``<cache>/programs/hints/``; the next run starts loading them
in a background thread (XLA releases the GIL while it links one) as soon as it knows its
hint, before it has imported, prepared or traced anything. A program is still looked
up by its own key: a stale list costs only the loading of files the run does not use.
"""

from __future__ import annotations

import functools
import hashlib
import pickle
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import equinox as eqx
import jax
import jax.monitoring as monitoring
import numpy as np
from jax.experimental import serialize_executable

from . import __version__
from .io import atomic_write

_LAYOUT = "3"       # bump when the file layout or the key changes

# XLA's CPU loop emitters instead of its fusion emitters: the paper scene's band render
# compiled in 5.9 s instead of 10.1 s and ran in 2.2 s instead of 1.9 s (issue 20). Only
# for programs that run once per process and whose compilation costs more than their run:
# the unlensed grids' host light ran 6.5 → 28 s with them.
QUICK_COMPILE = {"xla_cpu_use_fusion_emitters": False}
# ... and LLVM unoptimised (quick_compile="light"): for programs whose run is a few ms, e.g.
# the disk's modulation mean (compiled in 0.77 s instead of 1.41, run 7 → 11 ms). Its
# floating-point results may differ from a default jit's in the last bit.
LIGHT_COMPILE = dict(QUICK_COMPILE, xla_backend_optimization_level=0)


@functools.lru_cache(maxsize=1)
def _package_digest() -> bytes:
    """SHA-256 of every .py file of the package (names and contents)."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes())
    return h.digest()


def _environment() -> str:
    import jaxlib

    dev = jax.devices()[0]
    return (f"{__version__} jax {jax.__version__} jaxlib {jaxlib.__version__} "
            f"{jax.default_backend()} {dev.device_kind} x64={jax.config.read('jax_enable_x64')}")


@functools.lru_cache(maxsize=1)
def _machine() -> str:
    """The backend's platform version and the host CPU's feature flags: a stored executable
    is machine code, valid only where both are the same (a cache folder may be shared by
    hosts of a cluster)."""
    flags = ""
    try:
        with open("/proc/cpuinfo") as fh:
            flags = next((line for line in fh if line.startswith(("flags", "Features"))), "")
    except OSError:             # not Linux: the processor's name instead
        import platform
        flags = platform.processor()
    return f"{jax.devices()[0].client.platform_version}\0{flags.strip()}"


def _is_dynamic(x) -> bool:
    """Arguments traced as inputs: JAX and numpy arrays (as `eqx.filter_jit` does)."""
    return eqx.is_array(x)


def feed_pytree(h, obj) -> bool:
    """Hash a pytree's content into `h`: its structure, arrays (numpy or JAX) by dtype,
    shape and bytes, other leaves by type and repr. False (and `h` unusable) when a leaf
    is known only by its address, so that no stable key exists."""
    leaves, tree = jax.tree_util.tree_flatten(obj)
    with np.printoptions(threshold=sys.maxsize):
        text = str(tree)
        for leaf in leaves:
            if isinstance(leaf, (np.ndarray, np.generic, jax.Array)):
                a = np.ascontiguousarray(np.asarray(leaf))
                h.update(f"{a.dtype}{a.shape}".encode())
                h.update(a.tobytes())
            else:
                text += f"\0{type(leaf).__qualname__}:{leaf!r}"
    if " at 0x" in text:
        return False
    h.update(text.encode())
    return True


def program_key(name: str, dyn_leaves, dyn_tree, static) -> str | None:
    """Hex SHA-256 naming a program (see the module docstring), or None when it cannot
    be keyed completely."""
    h = hashlib.sha256(f"{_LAYOUT}\0{name}\0{_environment()}\0{_machine()}\0".encode())
    h.update(_package_digest())
    h.update(str(dyn_tree).encode())
    for leaf in dyn_leaves:
        h.update(f"{leaf.dtype}{leaf.shape};".encode())
    return h.hexdigest() if feed_pytree(h, static) else None


def _as_key_data(leaf):
    """Typed PRNG keys travel as their raw data (export takes plain arrays)."""
    if isinstance(leaf, jax.Array) and jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key):
        return jax.random.key_data(leaf), jax.random.key_impl(leaf)
    return leaf, None


class ReadAhead:
    """Executables of `folder` loaded in a background thread before the run asks for them.

    folder: the programs folder.  hint: names the list of files (any string, e.g. a hash
    of the resolved scene); the files are those the last `remember` with that hint
    recorded, loaded in the order that run used them (from `start`, unless `start` is
    False: call `start()` then). A program asked for before its turn is loaded by the
    thread that asks. `remember` records this run's files. `stored`: a list was found
    and every file on it exists (the run will likely load, not compile, its programs).
    """

    def __init__(self, folder, hint: str, start: bool = True):
        self.folder = Path(folder)
        self._list = self.folder / "hints" / f"{hashlib.sha256(hint.encode()).hexdigest()[:40]}.txt"
        try:
            self._listed = self._list.read_text().split()
        except OSError:
            self._listed = []
        self.stored = bool(self._listed) and all((self.folder / n).is_file()
                                                 for n in self._listed)
        self._used = []
        self._ahead = {}
        if start:
            self.start()

    def start(self) -> "ReadAhead":
        """Begin loading the listed files in a background thread (once)."""
        if self._listed and not self._ahead:
            pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="clumpylen-read-ahead")
            self._ahead = {n: pool.submit(_load, self.folder / n, False) for n in self._listed}
            pool.shutdown(wait=False)
        return self

    def load(self, path: Path):
        """The executable at path (read ahead, or loaded now), or None; the wait for one
        being read ahead is reported as a compilation span, as `_load` does."""
        self._used.append(path.name)
        later = self._ahead.pop(path.name, None)
        if later is None or later.cancel():     # not read ahead, or not begun: load it here
            return _load(path)
        start = time.time()
        compiled = later.result()
        monitoring.record_event_time_span("/jax/core/compile/backend_compile_duration",
                                          start, time.time())
        return compiled

    def remember(self) -> None:
        """Record the files this run used, for the next run with the same hint."""
        used = list(dict.fromkeys(self._used))
        if used and used != self._listed:
            self._list.parent.mkdir(parents=True, exist_ok=True)
            with atomic_write(self._list, "w") as fh:
                fh.write("\n".join(used) + "\n")


def _folder_and_reader(folder):
    """(the programs folder or None, a function path → executable or None) of `folder`:
    a path (or None) or a `ReadAhead`."""
    if isinstance(folder, ReadAhead):
        return folder.folder, folder.load
    return folder, _load


def call(name: str, fun, *args, folder=None, baked=None, quick_compile=False):
    """`fun(*args)` compiled as one program, its executable read from / written to `folder`.

    name: identifies `fun` (part of the key: two functions must not share a name).
    args: pytrees (equinox Modules included); arrays are the program's inputs, every
    other leaf is static (baked in). folder: the programs folder, or a `ReadAhead` of it;
    None: compiled here, nothing read or written.
    baked: a pytree given to `fun` as its first argument whose arrays, too, are constants
    of the program (part of the key by their bytes), as those a jitted closure captures:
    XLA folds them as it does there, so that the values are those of such a jit.
    quick_compile: compiled with `QUICK_COMPILE`'s options (part of the key), for a
    program whose compilation costs more than its runs; "light": `LIGHT_COMPILE`'s, for
    one whose runs cost next to nothing.
    """
    program, leaves = _program(name, fun, args, folder, baked, quick_compile)
    return program(leaves)


def function(name: str, fun, *args, folder=None, baked=None, quick_compile=False):
    """`call`'s program as a function: it takes arguments like `args` (the same structure,
    array shapes and dtypes, and non-array leaves), and the executable is loaded or
    compiled once for all its calls (a program called on many chunks of one shape)."""
    program, _ = _program(name, fun, args, folder, baked, quick_compile)
    return lambda *a: program(_inputs(a)[0])


def compiled(name: str, fun, *args, folder=None, baked=None, quick_compile=False):
    """`function`, with its executable loaded or compiled now rather than at its first call
    (in a background thread, before the values it will be called with exist: `args` need
    only their structure, array shapes and dtypes, and non-array leaves)."""
    program, _ = _program(name, fun, args, folder, baked, quick_compile)
    program.ready()
    return lambda *a: program(_inputs(a)[0])


def _inputs(args):
    """(the program's inputs, the pytree structure, typed-key implementations) of args."""
    leaves, tree = jax.tree_util.tree_flatten(eqx.filter(args, _is_dynamic))
    pairs = [_as_key_data(x) for x in leaves]
    # NumPy arrays by `device_put`: `jnp.asarray` compiles a small program per new shape
    # and dtype (~15 ms each; the paper scene's cold run made 58 such, 1.6 s)
    return ([jax.device_put(x) if isinstance(x, np.ndarray) else jax.numpy.asarray(x)
             for x, _ in pairs], tree, [impl for _, impl in pairs])


def _compile_options(quick) -> dict:
    """XLA's options for a program: `QUICK_COMPILE`'s where asked for (quick True, on a
    CPU), `LIGHT_COMPILE`'s for quick "light", else XLA's defaults."""
    if not quick or jax.default_backend() != "cpu":
        return {}
    return dict(LIGHT_COMPILE if quick == "light" else QUICK_COMPILE)


def _program(name, fun, args, folder, baked, quick_compile=False):
    """(a `_Program` for fun at args' shapes and static leaves, args' inputs)."""
    static = eqx.filter(args, _is_dynamic, inverse=True)
    leaves, tree, impls = _inputs(args)

    def flat(*xs):
        xs = [x if impl is None else jax.random.wrap_key_data(x, impl=impl)
              for x, impl in zip(xs, impls)]
        full = eqx.combine(jax.tree_util.tree_unflatten(tree, xs), static)
        return fun(*full) if baked is None else fun(baked, *full)

    specs = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]
    options = _compile_options(quick_compile)
    key = program_key(name, leaves, tree, (static, [str(i) for i in impls], baked,
                                           sorted(options.items())))
    folder, read = _folder_and_reader(folder)
    path = None if folder is None or key is None else Path(folder) / f"{name}-{key[:40]}.jaxexec"

    def compile_():
        exp = jax.export.export(jax.jit(flat))(*specs)

        def lower():
            return jax.jit(exp.call).lower(*specs)

        if path is None:
            return lower().compile(options)
        compiled = _compile_own(lower, options)
        _store(compiled, path)
        return compiled

    return _Program(None if path is None else read(path), compile_), leaves


class _Program:
    """An executable: the stored one, else compiled (`compile_`) at its first call. A
    stored one whose first call fails (stored by older code, see `_compile_own`) is
    compiled again and replaced."""

    def __init__(self, stored, compile_):
        self._exe, self._compile, self._unchecked = stored, compile_, stored is not None

    def ready(self):
        """Load or compile the executable now (a stored one is still checked at its first
        call)."""
        if self._exe is None:
            self._exe = self._compile()

    def __call__(self, leaves):
        if self._unchecked:
            self._unchecked = False
            try:    # waited for: a missing function is reported at execution, not dispatch
                return jax.block_until_ready(self._exe(*leaves))
            except jax.errors.JaxRuntimeError:
                self._exe = None
        if self._exe is None:
            self._exe = self._compile()
        return self._exe(*leaves)


def _compile_own(lower, options=None):
    """`lower().compile()`, compiled by XLA in this process.

    An executable that JAX read back from its own persistent cache serialises without its
    machine code: stored here and loaded by a later process, its first call fails
    ("Function ..._fusion not found"). That happens when programs/ lacks a program that
    jax/ holds (a clumpylen edit or upgrade that leaves the program unchanged, programs/
    deleted): then it is compiled again with JAX's cache off."""
    hits, me = [], threading.get_ident()

    def on_event(event, **_):           # called in the thread that records the event
        if event == "/jax/compilation_cache/cache_hits" and threading.get_ident() == me:
            hits.append(event)

    monitoring.register_event_listener(on_event)
    try:
        compiled = lower().compile(options)
    finally:
        monitoring.unregister_event_listener(on_event)
    # lowered anew: a Lowered keeps the executable it compiled first
    return _fresh_compile(lower(), options) if hits else compiled


def _fresh_compile(lowered, options=None):
    """`lowered.compile()` with JAX's persistent cache off for this one compilation (for
    the whole process while it lasts: other threads' compilations then miss it)."""
    from jax.experimental.compilation_cache import compilation_cache

    jax.config.update("jax_enable_compilation_cache", False)
    compilation_cache.reset_cache()     # JAX settles on a cache once: make it look again
    try:
        return lowered.compile(options)
    finally:
        jax.config.update("jax_enable_compilation_cache", True)
        compilation_cache.reset_cache()


def _store(compiled, path):
    try:
        blob = pickle.dumps(serialize_executable.serialize(compiled),
                            protocol=pickle.HIGHEST_PROTOCOL)
    except Exception:           # a backend or program that cannot be serialised: not kept
        return
    with atomic_write(path, "wb") as fh:
        fh.write(blob)


def _load(path, report: bool = True):
    """The executable stored at path, or None (absent or unreadable: compiled again).

    With `report`, its loading is reported to `jax.monitoring` as a compilation span (as
    JAX reports a load from its own cache), so that stage timings count it as compile
    time (`ReadAhead` reports the wait for it instead)."""
    if path is None or not path.is_file():
        return None
    start = time.time()
    try:
        compiled = serialize_executable.deserialize_and_load(*pickle.loads(path.read_bytes()))
    except Exception:       # a truncated or foreign file: compiled again and replaced
        return None
    if report:
        monitoring.record_event_time_span("/jax/core/compile/backend_compile_duration",
                                          start, time.time())
    return compiled
