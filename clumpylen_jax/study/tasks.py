"""Task generation: a study → a list of small, independent, reproducible tasks.

Every random number of a task comes from `numpy.random.SeedSequence(study.seed,
spawn_key=...)` with a spawn key made of the task's own indices (never from the
order tasks run in), so each sample or injection can be recomputed alone:

    (0, i)                 simulate / fit sample i (clump count, masses, sizes, positions, noise)
    (1, v)                 the injection positions of completeness variant v
    (2, v, i, j, p)        the noise of the injection at position p of cell (mass i, size j)

Tasks are grouped by shape: a sample's clump count is padded to the next bucket
(`simulate.buckets`), so a study compiles one program per (variant, bucket), and
tasks are listed bucket by bucket.
"""

from __future__ import annotations

import dataclasses
import numpy as np

from .spec import Study


@dataclasses.dataclass(frozen=True)
class Task:
    """One unit of work. `id` names its result file; `shape` is its compile group."""

    id: str
    kind: str                 # "simulate" | "fit" | "inject" | "map"
    variant: int
    shape: tuple              # (variant, clump slots) — tasks of one shape share a program
    sample: int = -1          # simulate / fit
    mass_index: int = -1      # inject / map
    size_index: int = -1
    positions: tuple = ()     # inject: indices into the variant's positions


def sample_rng(study: Study, *key: int) -> np.random.Generator:
    """The generator of one task element: SeedSequence(study seed, spawn_key=key)."""
    return np.random.default_rng(np.random.SeedSequence(study.seed, spawn_key=tuple(key)))


def disc_offsets(rng: np.random.Generator, n: int, radius_arcsec: float) -> np.ndarray:
    """[n, 2] offsets uniform in a disc."""
    r = radius_arcsec * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.c_[r * np.cos(phi), r * np.sin(phi)]


@dataclasses.dataclass(frozen=True)
class Sample:
    """The random content of simulate / fit sample `index` (positions relative to the host centre)."""

    index: int
    variant: int
    mass_msun: np.ndarray       # [n]
    re_pc: np.ndarray           # [n]
    offset_arcsec: np.ndarray   # [n, 2]
    noise_seed: int
    start_factors: np.ndarray   # [n, 3]: fit start = truth × exp(scatter · these) (flux, R_e) and
                                #          centre + scatter · R_e · (third) along a random angle
    start_angles: np.ndarray    # [n]


def draw_sample(study: Study, index: int) -> Sample:
    """Sample `index` of a simulate or fit study, from its own seed only."""
    opts = study.options
    per_variant = opts["samples"]
    rng = sample_rng(study, 0, index)
    lo, hi = opts["clumps_per_sample"]
    n = int(rng.integers(lo, hi + 1))
    mass = study.mass_msun.draw(rng, n)
    re_pc = study.re_pc.draw(rng, n)
    off = disc_offsets(rng, n, study.clumps["region_arcsec"])
    noise_seed = int(rng.integers(0, 2**31 - 1))
    factors = rng.standard_normal((n, 3))
    angles = rng.uniform(0, 2 * np.pi, n)
    return Sample(index, index // per_variant, mass, re_pc, off, noise_seed, factors, angles)


def bucket(n: int, buckets) -> int:
    """The smallest bucket holding n clumps."""
    for b in buckets:
        if n <= b:
            return int(b)
    return int(n)


def positions(study: Study, variant: int) -> np.ndarray:
    """[P, 2] injection offsets (arcsec, from the host centre) of a completeness variant."""
    rng = sample_rng(study, 1, variant)
    return disc_offsets(rng, study.options["positions"], study.clumps["region_arcsec"])


def map_offsets(study: Study) -> np.ndarray:
    """[M², 2] offsets of the Fisher map's grid over the injection disc's bounding square."""
    m = study.options["map_npix"]
    r = study.clumps["region_arcsec"]
    x = np.linspace(-r, r, m)
    xx, yy = np.meshgrid(x, x, indexing="xy")
    return np.c_[xx.ravel(), yy.ravel()]


def make_tasks(study: Study) -> list[Task]:
    """Every task of the study, grouped by compile shape."""
    opts = study.options
    nv = len(study.variants)
    tasks = []
    if study.kind in ("simulate", "fit"):
        for i in range(opts["samples"] * nv):
            s = draw_sample(study, i)
            slots = bucket(len(s.mass_msun), opts["buckets"]) if study.kind == "simulate" \
                else len(s.mass_msun)
            prefix = "sim" if study.kind == "simulate" else "fit"
            tasks.append(Task(f"{prefix}-{i:07d}", study.kind, s.variant, (s.variant, slots), sample=i))
    else:
        nm, ns = len(study.mass_msun.values), len(study.re_pc.values)
        per = opts["positions_per_task"]
        n_pos = opts["positions"]
        for v in range(nv):
            for i in range(nm):
                for j in range(ns):
                    tasks.append(Task(f"map-v{v}-m{i}-s{j}", "map", v, (v, "map"),
                                      mass_index=i, size_index=j))
                    for k, p0 in enumerate(range(0, n_pos, per)):
                        idx = tuple(range(p0, min(p0 + per, n_pos)))
                        tasks.append(Task(f"inj-v{v}-m{i}-s{j}-p{k}", "inject", v, (v, 1),
                                          mass_index=i, size_index=j, positions=idx))
    return sorted(tasks, key=lambda t: (str(t.shape), t.id))
