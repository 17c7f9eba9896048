"""Compiled programs kept between runs (`programcache`): read back, keyed, invalidated."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from clumpylen_jax import programcache


class _Model(eqx.Module):
    """A tiny model: arrays are inputs, `power` is baked into the program."""

    scale: jax.Array
    power: int = eqx.field(static=True)

    def render(self, x, key):
        noise = jax.random.normal(key, x.shape, x.dtype)
        return (self.scale * x) ** self.power + 1e-3 * noise


def _render(m, x, key):
    return m.render(x, key)


def _args(scale=1.5, power=2):
    return _Model(jnp.asarray(scale), power), jnp.linspace(0.0, 1.0, 7), jax.random.key(3)


def _refuse_tracing(monkeypatch):
    def no_export(*a, **k):
        raise AssertionError("traced again: the stored program was not used")
    monkeypatch.setattr(jax.export, "export", no_export)


def test_stored_program_is_read_back_and_gives_the_same_bits(monkeypatch, tmp_path):
    direct = np.asarray(jax.jit(_render)(*_args()))
    first = np.asarray(programcache.call("tiny", _render, *_args(), folder=tmp_path))
    assert len(list(tmp_path.glob("tiny-*.jaxexec"))) == 1
    uncached = np.asarray(programcache.call("tiny", _render, *_args(), folder=None))
    with monkeypatch.context() as m:
        _refuse_tracing(m)
        again = np.asarray(programcache.call("tiny", _render, *_args(), folder=tmp_path))
        # other array values: the same program, their own result
        other = np.asarray(programcache.call("tiny", _render, *_args(scale=2.0),
                                             folder=tmp_path))
    assert first.tobytes() == again.tobytes() == uncached.tobytes() == direct.tobytes()
    assert other.tobytes() == np.asarray(jax.jit(_render)(*_args(scale=2.0))).tobytes()
    assert len(list(tmp_path.glob("*"))) == 1


def test_compiled_is_ready_before_its_first_call_from_placeholder_values(monkeypatch, tmp_path):
    """`compiled` stores (compiles) the program from placeholder arrays of the right shapes,
    before any call; its calls then trace nothing and give `call`'s bits."""
    m, x, key = _args()
    fun = programcache.compiled("tiny", _render, _Model(jnp.asarray(0.0), 2), jnp.zeros(7),
                                jax.random.key(0), folder=tmp_path)
    assert len(list(tmp_path.glob("tiny-*.jaxexec"))) == 1
    with monkeypatch.context() as mp:
        _refuse_tracing(mp)
        got = np.asarray(fun(m, x, key))
    assert got.tobytes() == np.asarray(programcache.call("tiny", _render, m, x, key)).tobytes()


def test_key_changes_with_static_fields_shapes_and_versions(monkeypatch, tmp_path):
    programcache.call("tiny", _render, *_args(), folder=tmp_path)
    cubed = programcache.call("tiny", _render, *_args(power=3), folder=tmp_path)
    assert np.allclose(cubed[1:], (1.5 * np.linspace(0, 1, 7)[1:]) ** 3, rtol=1e-3, atol=1e-2)
    m, _, key = _args()
    programcache.call("tiny", _render, m, jnp.ones(5), key, folder=tmp_path)   # other shape
    assert len(list(tmp_path.glob("tiny-*.jaxexec"))) == 3
    # another package version (or jax version, in the same string): a new key, old file unread
    monkeypatch.setattr(programcache, "__version__", "0.0.0-other")
    programcache.call("tiny", _render, *_args(), folder=tmp_path)
    assert len(list(tmp_path.glob("tiny-*.jaxexec"))) == 4


def test_unreadable_file_is_traced_again_and_replaced(tmp_path):
    want = np.asarray(programcache.call("tiny", _render, *_args(), folder=tmp_path))
    (path,) = tmp_path.glob("tiny-*.jaxexec")
    path.write_bytes(b"not a program")
    got = np.asarray(programcache.call("tiny", _render, *_args(), folder=tmp_path))
    assert got.tobytes() == want.tobytes()
    assert path.read_bytes() != b"not a program"


def test_read_ahead_loads_last_runs_programs_before_they_are_asked_for(monkeypatch, tmp_path):
    """A run that `remember`s its programs: the next with the same hint reads them ahead
    (loaded in its thread before the call, no tracing), another hint does not, and a
    stale list (a file gone) costs nothing but a compile."""
    want = np.asarray(programcache.call("tiny", _render, *_args(), folder=tmp_path))
    first = programcache.ReadAhead(tmp_path, "scene A")
    assert not first._ahead and not first.stored        # nothing remembered yet
    programcache.call("tiny", _render, *_args(), folder=first)
    first.remember()
    (listed,) = (tmp_path / "hints").glob("*.txt")
    assert listed.read_text().split() == [p.name for p in tmp_path.glob("tiny-*.jaxexec")]

    again = programcache.ReadAhead(tmp_path, "scene A")
    (name,) = again._ahead
    assert again.stored
    assert again._ahead[name].result() is not None          # loaded by the reading thread
    with monkeypatch.context() as m:
        _refuse_tracing(m)
        got = np.asarray(programcache.call("tiny", _render, *_args(), folder=again))
    assert got.tobytes() == want.tobytes() and not again._ahead
    assert not programcache.ReadAhead(tmp_path, "scene B")._ahead

    (tmp_path / name).unlink()
    stale = programcache.ReadAhead(tmp_path, "scene A")
    assert not stale.stored
    got = np.asarray(programcache.call("tiny", _render, *_args(), folder=stale))
    assert got.tobytes() == want.tobytes() and (tmp_path / name).is_file()


_IN_JAX_CACHE = """
import sys, pathlib
import jax, jax.numpy as jnp
from clumpylen_jax import programcache
from clumpylen_jax.cache import enable_compilation_cache

root, step, folder = pathlib.Path(sys.argv[1]), sys.argv[2], sys.argv[3]
enable_compilation_cache(True, root / "jax")


def f(x):     # slices, pads and reshapes: XLA makes fusions of them
    y = jnp.cumsum(jnp.sin(x[::2]) * jnp.exp(x[1::2]))
    return jnp.concatenate([y, y[::-1] ** 2])[3:70]


x = jnp.linspace(0.0, 1.0, 200)
if step == "older":         # older code: compiled through jax/ (a hit there stores JAX's copy)
    programcache._fresh_compile = lambda lowered, options=None: lowered.compile(options)
if step == "load":          # the stored executable, called directly
    (path,) = (root / folder).glob("f-*.jaxexec")
    out = programcache._load(path)(x)
else:
    out = programcache.call("f", f, x, folder=root / folder)
print(float(out.sum()))
"""


# slow: fresh processes, ~28 s on 2 cores (make test took 10 min 9 s with it)
@pytest.mark.slow
def test_program_also_in_jax_cache_is_stored_callable(tmp_path):
    """A program that JAX's persistent cache already holds is stored as XLA's own compile
    (JAX's copy serialises without its machine code: a later process fails calling it), and
    a file that older code stored that way is compiled again and replaced, not a crash.
    Each step in its own process (JAX's persistent cache on, no symbols loaded yet)."""
    import subprocess
    import sys

    def step(name, folder):
        run = subprocess.run([sys.executable, "-c", _IN_JAX_CACHE, str(tmp_path), name, folder],
                             capture_output=True, text=True, timeout=300)
        return run.returncode, run.stdout.strip(), run.stderr[-2000:]

    rc, want, err = step("older", "a")          # jax/ now holds the program
    assert rc == 0, err
    assert step("call", "programs")[:2] == (0, want)    # stored while jax/ holds it
    assert step("load", "programs")[:2] == (0, want)
    assert step("older", "b")[:2] == (0, want)          # JAX's copy stored, as older code did
    rc, _, err = step("load", "b")
    assert rc != 0 and "not found" in err, "JAX's copy ran: this test no longer shows the bug"
    assert step("call", "b")[:2] == (0, want)           # compiled again and replaced
    assert step("load", "b")[:2] == (0, want)


def test_an_argument_without_a_stable_repr_is_not_stored(tmp_path):
    class Opaque:            # repr is an address: no key can name it across processes
        pass

    o = Opaque()
    out = programcache.call("opaque", lambda x, _o: 2 * x, jnp.ones(3), o, folder=tmp_path)
    assert np.array_equal(out, 2 * np.ones(3))
    assert not list(tmp_path.glob("*"))


def _profile(c, x):
    """libm-heavy work on constants (cos, pow, log, atan2), as the host brightness does."""
    return jnp.cos(c[0]) * x ** c[1] + jnp.log(c[2]) * jnp.arctan2(x, c[0])


def test_baked_arrays_give_a_closure_jits_bits_and_are_keyed(monkeypatch, tmp_path):
    """`baked` arrays are constants of the program, as a jit's closure has them (the
    population's host brightness): the same bits as that jit, stored or not, and a
    program of their own per value."""
    c = jnp.asarray([0.3, 1.7, 2.9])
    x = jnp.linspace(0.1, 5.0, 1001)
    want = np.asarray(jax.jit(lambda x: _profile(c, x))(x))
    for folder in (None, tmp_path, tmp_path):      # uncached, stored, read back
        got = np.asarray(programcache.call("profile", _profile, x, folder=folder, baked=c))
        assert got.tobytes() == want.tobytes()
    programcache.call("profile", _profile, x, folder=tmp_path, baked=c + 1)
    assert len(list(tmp_path.glob("profile-*.jaxexec"))) == 2


def test_function_loads_its_program_once_for_all_calls(monkeypatch, tmp_path):
    c = jnp.asarray([0.3, 1.7, 2.9])
    x = jnp.linspace(0.1, 5.0, 64)
    programcache.function("profile", _profile, x, folder=tmp_path, baked=c)(x)   # stored
    loads = []
    load = programcache._load
    monkeypatch.setattr(programcache, "_load", lambda path: loads.append(path) or load(path))
    _refuse_tracing(monkeypatch)
    f = programcache.function("profile", _profile, x, folder=tmp_path, baked=c)
    for k in range(3):
        got = np.asarray(f(x + k))
        assert got.tobytes() == np.asarray(jax.jit(lambda x: _profile(c, x))(x + k)).tobytes()
    assert len(loads) == 1


def _lensed_tiny():
    from clumpylen_jax.lensing.analytic import SIS
    from clumpylen_jax.model import Accuracy, Band
    from clumpylen_jax.source import Clumps, Source

    def f64(x):
        return jnp.asarray(x, jnp.float64)

    src = Source(clumps=Clumps(f64([[0.3, 0.0]]), f64([[100.0]]), f64([0.01]), f64([0.5]),
                               f64([1.0]), f64([0.0])))
    return src, [Band("X", 0.05, 1.0)], SIS(f64(1.0), f64([0.0, 0.0])), dict(
        field_arcsec=((-1.5, 1.5), (-1.0, 1.0)), lens_pixel_arcsec=0.01,
        accuracy=Accuracy(source_mode="grid"), source_pixel_arcsec=0.002)


def test_built_model_is_read_back_bit_for_bit_and_keyed_on_inputs_and_version(monkeypatch,
                                                                             tmp_path):
    from clumpylen_jax import modelcache
    from clumpylen_jax.model import build_model

    src, bands, lens, kw = _lensed_tiny()
    built = modelcache.build(build_model, src, bands, lens=lens, folder=tmp_path, **kw)

    def refuse(*a, **k):
        raise AssertionError("built again: the stored model was not used")

    again = modelcache.build(refuse, src, bands, lens=lens, folder=tmp_path, **kw)
    a, ta = jax.tree_util.tree_flatten(built)
    b, tb = jax.tree_util.tree_flatten(again)
    assert ta == tb
    assert all(np.asarray(x).tobytes() == np.asarray(y).tobytes() for x, y in zip(a, b))
    # another lens, or another package version: built anew, a file of its own
    from clumpylen_jax.lensing.analytic import SIS
    other = SIS(jnp.asarray(1.01), jnp.asarray([0.0, 0.0]))
    modelcache.build(build_model, src, bands, lens=other, folder=tmp_path, **kw)
    monkeypatch.setattr(programcache, "__version__", "0.0.0-other")
    modelcache.build(build_model, src, bands, lens=lens, folder=tmp_path, **kw)
    assert len(list(tmp_path.glob("model-*.pkl"))) == 3


def test_model_folder_keeps_only_the_most_recently_used(monkeypatch, tmp_path):
    from clumpylen_jax import modelcache
    from clumpylen_jax.model import build_model

    monkeypatch.setattr(modelcache, "KEEP_MODELS", 2)
    src, bands, lens, kw = _lensed_tiny()
    from clumpylen_jax.lensing.analytic import SIS
    lenses = [SIS(jnp.asarray(1.0 + 0.01 * i), jnp.asarray([0.0, 0.0])) for i in range(3)]
    modelcache.build(build_model, src, bands, lens=lenses[0], folder=tmp_path, **kw)
    modelcache.build(build_model, src, bands, lens=lenses[1], folder=tmp_path, **kw)
    first = modelcache.model_key(src, bands, lenses[0], **kw)[:40]
    import os
    import time
    os.utime(tmp_path / f"model-{first}.pkl", (time.time() + 5, time.time() + 5))  # used last
    modelcache.build(build_model, src, bands, lens=lenses[2], folder=tmp_path, **kw)
    kept = sorted(p.name for p in tmp_path.glob("model-*.pkl"))
    third = modelcache.model_key(src, bands, lenses[2], **kw)[:40]
    assert kept == sorted([f"model-{first}.pkl", f"model-{third}.pkl"])


def test_quick_compile_is_keyed_apart_reaches_xla_and_reads_back_its_own_bits(monkeypatch,
                                                                             tmp_path):
    """`quick_compile`: XLA gets `QUICK_COMPILE`'s options (on a CPU), the program is stored
    under a key of its own beside the default one, and read back it gives its own bits; its
    values are the default program's to rounding."""
    seen = []
    real = jax.stages.Lowered.compile

    def spy(self, compiler_options=None, **kw):
        seen.append(dict(compiler_options or {}))
        return real(self, compiler_options, **kw)

    with monkeypatch.context() as m:
        m.setattr(jax.stages.Lowered, "compile", spy)
        quick = np.asarray(programcache.call("tiny", _render, *_args(), folder=tmp_path,
                                             quick_compile=True))
        default = np.asarray(programcache.call("tiny", _render, *_args(), folder=tmp_path))
    want = programcache.QUICK_COMPILE if jax.default_backend() == "cpu" else {}
    # each may be compiled twice (`_compile_own`, after a hit in JAX's cache)
    first_default = seen.index({}) if want else 1
    assert first_default >= 1 and all(o == want for o in seen[:first_default])
    assert len(seen) > first_default and all(o == {} for o in seen[first_default:])
    assert len(list(tmp_path.glob("tiny-*.jaxexec"))) == 2
    with monkeypatch.context() as m:
        _refuse_tracing(m)
        again = np.asarray(programcache.call("tiny", _render, *_args(), folder=tmp_path,
                                             quick_compile=True))
    assert again.tobytes() == quick.tobytes()
    np.testing.assert_allclose(quick, default, rtol=1e-14, atol=0)
