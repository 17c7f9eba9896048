"""Free parameters: which entries of the source are fitted, and the flat vector they map to.

A fit moves a flat unconstrained vector u (what optimisers and samplers see).
`Parametrization.state(u)` turns it into a `FitState` — the `Source` pytree plus
a per-band background level and, optionally, clump masses and ages — by
transforming each entry to its physical value (`transforms.py`: log for
positive quantities, scaled logistic for bounded ones, identity for positions
and angles) and writing it into a fixed template with `eqx.tree_at`. Entries
that are not free keep the template's values.

Free entries are named by a path into the FitState, relative to the source for
source fields:

    "clumps.flux", "clumps.center_arcsec", "clumps.re_arcsec", "clumps.q",
    "clumps.pa_rad", "clumps.n", "bulge.flux", "disk.sersic.re_arcsec", ...,
    "background" (per band, counts/s/pixel), "mass_msun", "age_myr" (clumps,
    with a `photometric.ClumpPhotometry` in the state).

and selected with ``free = {path: selection}`` where a selection is True (every
element), a sequence of ints (rows along the first axis: clumps for clump
fields, bands for host fluxes), a boolean mask of the leaf's shape, or a
`Free(select, transform)` to override the default transform.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from ..source import Source
from .transforms import Transform, default_transform

_TOP_LEVEL = ("background", "mass_msun", "age_myr")


class FitState(eqx.Module):
    """What a fit varies: the source, a background level per band, optional clump masses/ages.

    source: the `Source` (its clump fluxes are ignored when `photometry` is set).
    background_counts_per_s: [B] additive level per band on top of the model's sky.
    mass_msun, age_myr: [N] clump masses (M☉ formed) and ages (Myr), used only with
        `photometry` (a `photometric.ClumpPhotometry`), which turns them into flux[N, B].
    """

    source: Source
    background_counts_per_s: jnp.ndarray
    mass_msun: Optional[jnp.ndarray] = None
    age_myr: Optional[jnp.ndarray] = None
    photometry: Any = eqx.field(static=True, default=None)

    def render_source(self) -> Source:
        """The source the scene model renders (clump fluxes from mass and age when asked)."""
        if self.photometry is None or self.mass_msun is None:
            return self.source
        flux = self.photometry.counts_per_s(self.mass_msun, self.age_myr)
        return eqx.tree_at(lambda s: s.clumps.flux, self.source, flux.astype(self.source.clumps.flux.dtype))


def masked_clumps(state: FitState, active) -> FitState:
    """The state with clump k's fluxes multiplied by active[k] (0 or 1): a fixed capacity of
    clump slots of which only the active ones shine (`capacity.py`)."""
    flux = state.source.clumps.flux
    return eqx.tree_at(lambda s: s.source.clumps.flux, state,
                       flux * jnp.asarray(active, flux.dtype)[:, None])


def clump_rows(state: FitState, slots) -> FitState:
    """The state with only the clump rows `slots` (int [L], a traced array: any rows, a
    fixed count), for a model whose clump renderer draws any number of clumps
    (`Renderer.any_count`). Fluxes from masses and ages (`photometry`) are not supported."""
    if state.photometry is not None:
        raise ConfigError("clump_rows", "photometry", "a state with clump fluxes as parameters")
    rows = jax.tree_util.tree_map(lambda a: a[slots], state.source.clumps)
    return eqx.tree_at(lambda s: s.source.clumps, state, rows)


def take_rows(tree, idx):
    """The rows idx (int, concrete) of every array of tree, taken in numpy outside a trace
    (no op-by-op gather compiled per field)."""
    rows = np.asarray(idx, int)
    return jax.tree_util.tree_map(lambda a: jnp.asarray(np.asarray(a)[rows]) if eqx.is_array(a)
                                  else a, tree)


HOST_PART, CLUMP_PART = "host", "clumps"
_CLUMP_LEAVES = ("clumps.", "mass_msun", "age_myr")


def held(state: FitState, part: str) -> FitState:
    """The state with `part`'s parameters behind stop_gradient: "host" (bulge, disk) or
    "clumps" (clumps, and masses and ages, which make their fluxes). Forward-mode
    derivatives then carry symbolic-zero tangents through that part's rendering, i.e. skip
    it, where every tangent would be zero anyway (`part_blocks`)."""
    sg = jax.lax.stop_gradient
    if part == HOST_PART:
        return eqx.tree_at(lambda s: (s.source.bulge, s.source.disk), state,
                           (sg(state.source.bulge), sg(state.source.disk)), is_leaf=lambda x: x is None)
    return eqx.tree_at(lambda s: (s.source.clumps, s.mass_msun, s.age_myr), state,
                       (sg(state.source.clumps), sg(state.mass_msun), sg(state.age_myr)),
                       is_leaf=lambda x: x is None)


def only_gradient(state: FitState, path: str) -> FitState:
    """The state with every leaf behind stop_gradient except the one at `path` (e.g.
    "clumps.flux"): a forward-mode derivative along that leaf then carries symbolic-zero
    tangents through everything else, e.g. the profile of a component whose flux moves
    (`lm.columns_by_kind`)."""
    get = _getter(path)
    stopped = jax.tree_util.tree_map(jax.lax.stop_gradient, state)
    return eqx.tree_at(get, stopped, get(state))


# leaves that enter the images linearly and band by band: entry (…, b) moves band b's image
# only, by its own unit image (host and clump fluxes, the background level)
PER_BAND_LINEAR = ("bulge.flux", "disk.sersic.flux", "clumps.flux", "background")


def entry_kinds(param: "Parametrization", entries) -> tuple:
    """Per entry of u in `entries`: (leaf path, band, row) where the leaf is in
    PER_BAND_LINEAR (row: the clump's for clumps.flux [N, B], else 0), else (None, −1, 0);
    an entry outside u (padding) is (None, −1, 0). Static, for `lm.columns_by_kind`."""
    where, start = {}, 0
    for leaf in param.leaves:
        for k, i in enumerate(leaf.index):
            at = np.unravel_index(i, leaf.shape) if leaf.shape else (0,)
            row = int(at[0]) if len(at) > 1 else 0
            where[start + k] = ((leaf.path, int(at[-1]), row) if leaf.path in PER_BAND_LINEAR
                                else (None, -1, 0))
        start += leaf.size
    return tuple(where.get(int(e), (None, -1, 0)) for e in np.asarray(entries).ravel())


def part_blocks(param: "Parametrization"):
    """((entries of u that move the host or the background), (entries that move the clumps,
    their masses or ages)): numpy int arrays partitioning u. Each leaf's transform is
    elementwise, so a block's entries move only their own part of the state."""
    host, clumps, start = [], [], 0
    for leaf in param.leaves:
        (clumps if leaf.path.startswith(_CLUMP_LEAVES) else host).extend(
            range(start, start + leaf.size))
        start += leaf.size
    return np.asarray(host, int), np.asarray(clumps, int)


def make_state(source: Source, n_bands: int, *, background_counts_per_s=None, mass_msun=None,
               age_myr=None, photometry=None, dtype=jnp.float64) -> FitState:
    """A FitState with every floating leaf cast to `dtype` (weak types would change jit keys)."""
    bg = jnp.zeros(n_bands, dtype) if background_counts_per_s is None else \
        jnp.asarray(background_counts_per_s, dtype).reshape(n_bands)
    if (mass_msun is None) != (age_myr is None) or (mass_msun is not None and photometry is None):
        raise ConfigError("mass_msun/age_myr", "partial", "both masses and ages, and a photometry map")
    return FitState(source.astype(dtype), bg,
                    None if mass_msun is None else jnp.asarray(mass_msun, dtype),
                    None if age_myr is None else jnp.asarray(age_myr, dtype), photometry)


@dataclasses.dataclass(frozen=True)
class Free:
    """A free entry: `select` (True, rows, or a boolean mask) and an optional transform override."""

    select: Any = True
    transform: Optional[Transform] = None


@dataclasses.dataclass(frozen=True)
class FreeLeaf:
    """One free leaf, resolved: its path, leaf shape, flat indices of free elements, transform."""

    path: str
    shape: tuple
    index: tuple
    transform: Transform

    @property
    def size(self):
        return len(self.index)


def _getter(path: str):
    parts = path.split(".")
    if parts[0] not in _TOP_LEVEL:
        parts = ["source"] + parts
    names = {"background": "background_counts_per_s"}
    parts = [names.get(p, p) for p in parts]
    return lambda st: functools.reduce(getattr, parts, st)


def _resolve(state: FitState, path: str, spec) -> FreeLeaf:
    spec = spec if isinstance(spec, Free) else Free(spec)
    try:
        leaf = _getter(path)(state)
    except AttributeError:
        leaf = None
    if leaf is None:
        raise ConfigError("free", path, "a path to an existing array of the fit state "
                          "(e.g. clumps.flux, bulge.re_arcsec, background)")
    shape = tuple(np.shape(leaf))
    sel = spec.select
    if sel is True or sel is None:
        mask = np.ones(shape, bool)
    elif isinstance(sel, np.ndarray) and sel.dtype == bool or (
            np.asarray(sel).dtype == bool and np.shape(sel) == shape):
        mask = np.asarray(sel, bool)
        if mask.shape != shape:
            raise ConfigError(f"free[{path}]", mask.shape, f"a boolean mask of shape {shape}")
    else:
        rows = np.atleast_1d(np.asarray(sel, int))
        if len(shape) == 0 or np.any(rows < 0) or np.any(rows >= shape[0]):
            raise ConfigError(f"free[{path}]", sel, f"row indices below {shape[0] if shape else 0}")
        mask = np.zeros(shape, bool)
        mask[rows] = True
    index = tuple(int(i) for i in np.flatnonzero(mask.ravel()))
    transform = spec.transform or default_transform(path)
    return FreeLeaf(path, shape, index, transform)


class Parametrization(eqx.Module):
    """The map between a flat unconstrained vector u and a FitState.

    Build with `parametrize(state, free)`. Methods are pure and jit/vmap/grad-safe.
    Ordering of u: leaves in the order of `free`, elements of a leaf in C order.

    The maps between u, x and the state are jitted: called outside a trace (seeding, starts,
    answers), one program per Parametrization and shape instead of an op-by-op compile of
    every transform, slice and scatter (~170 small compiles in a `clumpylen fit`); inside
    a trace they inline.
    """

    template: FitState
    leaves: tuple = eqx.field(static=True)

    @property
    def size(self) -> int:
        return sum(l.size for l in self.leaves)

    @property
    def labels(self) -> tuple:
        """One label per entry of u, e.g. "clumps.flux[0,1]" (clump 0, band 1)."""
        out = []
        for l in self.leaves:
            for i in l.index:
                idx = np.unravel_index(i, l.shape) if l.shape else ()
                out.append(f"{l.path}[{','.join(str(int(k)) for k in idx)}]")
        return tuple(out)

    def _split(self, vec):
        parts, start = [], 0
        for l in self.leaves:
            parts.append(vec[start:start + l.size])
            start += l.size
        return parts

    @eqx.filter_jit
    def physical_vector(self, u):
        """Physical values x(u), same layout as u."""
        return jnp.concatenate([l.transform.forward(p) for l, p in zip(self.leaves, self._split(u))]
                               ) if self.leaves else jnp.zeros(0)

    @eqx.filter_jit
    def physical_and_slope(self, u):
        """(x(u), dx/du): the slope is the Jacobian's diagonal, all of it (every transform acts
        elementwise), from one forward-mode pass."""
        return jax.jvp(self.physical_vector, (u,), (jnp.ones_like(u),))

    @eqx.filter_jit
    def unconstrained_vector(self, x):
        """u(x): the inverse of `physical_vector`."""
        x = jnp.asarray(x)
        return jnp.concatenate([l.transform.inverse(p) for l, p in zip(self.leaves, self._split(x))]
                               ) if self.leaves else jnp.zeros(0)

    def log_abs_det_jacobian(self, u):
        """ln |dx/du| summed: add to a log density flat in x to sample in u."""
        return sum(jnp.sum(l.transform.log_abs_det_jacobian(p))
                   for l, p in zip(self.leaves, self._split(u)))

    @eqx.filter_jit
    def state_from_physical(self, x) -> FitState:
        """The template with its free entries replaced by the physical values x."""
        state = self.template
        for l, p in zip(self.leaves, self._split(x)):
            get = _getter(l.path)
            old = jnp.asarray(get(state))
            new = old.ravel().at[np.asarray(l.index, int)].set(p.astype(old.dtype)).reshape(l.shape)
            state = eqx.tree_at(get, state, new)
        return state

    @eqx.filter_jit
    def state(self, u) -> FitState:
        """The FitState at unconstrained u."""
        return self.state_from_physical(self.physical_vector(u))

    @eqx.filter_jit
    def physical_of_state(self, state: Optional[FitState] = None):
        """The free entries of `state` (default: the template) as a physical vector."""
        state = self.template if state is None else state
        parts = [jnp.asarray(_getter(l.path)(state)).ravel()[np.asarray(l.index, int)]
                 for l in self.leaves]
        return jnp.concatenate(parts) if parts else jnp.zeros(0)

    @eqx.filter_jit
    def initial(self, state: Optional[FitState] = None):
        """u of `state` (default: the template): the usual optimiser start."""
        return self.unconstrained_vector(self.physical_of_state(state))

    def u_limits(self) -> tuple:
        """(lo, hi) numpy [size]: the range of each entry of u (`Transform.u_range`)."""
        lo = [np.full(l.size, l.transform.u_range()[0]) for l in self.leaves]
        hi = [np.full(l.size, l.transform.u_range()[1]) for l in self.leaves]
        return (np.concatenate(lo), np.concatenate(hi)) if lo else (np.zeros(0), np.zeros(0))

    def scatter(self, values, fill=np.nan):
        """A FitState-shaped pytree holding `values` (layout of u) at free entries, `fill` elsewhere.

        Used to attach errors to parameters (fixed entries get NaN: not estimated).
        """
        def fill_leaf(x):
            return jnp.full(jnp.shape(x), fill, x.dtype) if eqx.is_inexact_array(x) else x

        blank = jax.tree_util.tree_map(fill_leaf, self.template)
        return Parametrization(blank, self.leaves).state_from_physical(jnp.asarray(values))


def parametrize(state: FitState, free) -> Parametrization:
    """Resolve `free` (a mapping path → selection, or a sequence of paths) against `state`."""
    if isinstance(free, str):
        free = [free]
    items = free.items() if isinstance(free, dict) else [(p, True) for p in free]
    leaves = tuple(_resolve(state, path, spec) for path, spec in items)
    paths = [l.path for l in leaves]
    if len(set(paths)) != len(paths):
        raise ConfigError("free", paths, "each path once")
    if state.photometry is not None and any(p == "clumps.flux" for p in paths):
        raise ConfigError("free", "clumps.flux", "mass_msun/age_myr when fluxes come from photometry")
    leaves = tuple(l for l in leaves if l.size > 0)
    return Parametrization(state, leaves)


def default_free(source: Source, *, clump_fields=("flux", "center_arcsec", "re_arcsec"),
                 host_fields=(), background=False) -> dict:
    """A `free` mapping: the given clump fields of every clump, host fields of present hosts."""
    free = {}
    if source.clumps is not None and source.clumps.count > 0:
        free.update({f"clumps.{f}": True for f in clump_fields})
    for name, comp in (("bulge", source.bulge),
                       ("disk.sersic", None if source.disk is None else source.disk.sersic)):
        if comp is not None:
            free.update({f"{name}.{f}": True for f in host_fields})
    if background:
        free["background"] = True
    return free
