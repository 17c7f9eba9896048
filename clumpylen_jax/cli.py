"""The `clumpylen` command.

    clumpylen scenes                         built-in scenes, one line each
    clumpylen show NAME [--resolved]         a scene as TOML, to start from
    clumpylen validate SCENE                 check a scene; print it resolved and its stages
    clumpylen simulate SCENE --out DIR [--seed N] [--bands F115W,F200W] [--no-noise] [--quiet] [--plots] [--no-cache]
    clumpylen plot DIR                       figures of a finished run
    clumpylen analyze DIR                    S/N and limiting magnitudes of a finished run
    clumpylen fit SCENE --out DIR            fit [[observations]] (or --image BAND=FILE) with host + clumps
    clumpylen study STUDY --out DIR [--scheduler ADDRESS] [--workers N]   a study on Dask

User errors (an invalid scene, a missing file, a TOML syntax error) exit with
status 2 and one line on stderr, without a traceback. Heavy modules (JAX, the
pipeline) are imported only by the commands that need them.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import os
import sys
import tomllib

from .errors import ConfigError

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2


class _UserError(Exception):
    """A problem the user can fix; printed as one line, exit status 2."""


def _load(scene_arg: str):
    from . import scene as sc

    try:
        return sc.load_scene(scene_arg)
    except tomllib.TOMLDecodeError as exc:
        # tomllib's message already says "(at line L, column C)".
        raise _UserError(f"{scene_arg}: invalid TOML: {exc}") from exc


def _cmd_scenes(args) -> int:
    from . import scene as sc

    items = sc.list_builtin_scenes()
    width = max((len(n) for n, _ in items), default=0)
    for name, desc in items:
        print(f"{name:<{width}}  {desc}".rstrip())
    return EXIT_OK


def _cmd_show(args) -> int:
    from . import scene as sc

    if args.resolved or os.path.isfile(args.scene) or args.scene not in dict(sc.list_builtin_scenes()):
        # A file (or --resolved): validate first, so what is shown is a working scene.
        s = _load(args.scene)
        if args.resolved:
            sys.stdout.write(sc.to_toml(s))
        else:
            with open(s.path, encoding="utf-8") as fh:
                sys.stdout.write(fh.read())
        return EXIT_OK
    # A built-in: its own text, with the comments that explain it.
    sys.stdout.write(sc.builtin_scene_text(args.scene))
    return EXIT_OK


def _cmd_validate(args) -> int:
    from . import scene as sc

    from .preflight import preflight

    s = _load(args.scene)
    notes = preflight(s)   # the files and sizes `simulate` would refuse
    print(f"# scene '{s.name}' is valid" + (f" ({s.path})" if s.path else ""))
    for note in notes:
        print(f"# warning: {note}")
    if s.description:
        print(f"# {s.description}")
    print("# stages: " + ", ".join(sc.stages(s)))
    print("# resolved (all defaults filled):")
    sys.stdout.write(sc.to_toml(s))
    return EXIT_OK


def _parse_bands(text: str | None):
    if text is None:
        return None
    names = [x.strip().upper() for x in text.split(",") if x.strip()]
    if not names:
        raise ConfigError("--bands", text, "comma-separated filter names, e.g. F115W,F200W")
    return names


@contextlib.contextmanager
def _long_run_memory():
    """Memory settings for one long command, reset after it to glibc's defaults and an
    unfrozen collector (a caller such as a test session goes on in the same process). Only
    where memory comes from and when it is scanned change, never a value.

    - glibc's malloc keeps freed memory for reuse: a run allocates and frees hundreds of MB
      of NumPy temporaries (the 2028² high-resolution frames: 33 MB a channel, 99 MB for
      three); with glibc's defaults blocks above 32 MB are mapped and unmapped again and the
      heap's free top is given back, so each new block is fresh pages the kernel faults in
      and zeroes. Blocks up to 256 MiB come from the heap and up to 1 GiB of free heap is
      kept meanwhile. Most of a warm run's 1.4 M page faults are XLA's first touches of its
      buffers, which this does not change (1.40 → 1.30 M faults).
    - what is imported by then (JAX, astropy, NumPy, the package: about a million objects)
      is kept out of the cyclic collector (`gc.freeze`), whose full passes over it cost
      ~1 s of a warm run's CPU; objects made during the command are collected as before.
    """
    mallopt = _mallopt()
    mallopt(_M_MMAP_THRESHOLD, 256 << 20)
    mallopt(_M_TRIM_THRESHOLD, 1 << 30)
    mallopt(_M_TOP_PAD, 64 << 20)
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()
        for option in (_M_MMAP_THRESHOLD, _M_TRIM_THRESHOLD, _M_TOP_PAD):
            mallopt(option, _GLIBC_DEFAULT)


_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -2, -3, -8  # <malloc.h>
_GLIBC_DEFAULT = 128 * 1024     # each of the three (mallopt(3))


def _mallopt():
    """glibc's mallopt, or a function doing nothing (another C library)."""
    import ctypes

    try:
        return ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return lambda option, value: 0


@contextlib.contextmanager
def _one_malloc_arena():
    """glibc's malloc serves every thread from one arena while the command runs (reset to
    its default after it). By default each thread that allocates gets an arena of its own
    (up to 8 per core): XLA's worker threads, the loading and writing threads. A block one
    thread frees is then not reused by another, and freed arena memory goes back to the
    kernel, so new buffers are fresh pages faulted in and zeroed: ~2 s of a warm paper-scene
    run's system time (6.6 → 4.4 s; page faults 1.24 → 1.09 M). Enter it before the
    threads start allocating (JAX's backend is started by the first program). Not for a
    run that compiles: XLA's compiler threads then wait on the one arena's lock."""
    mallopt = _mallopt()
    mallopt(_M_ARENA_MAX, 1)
    try:
        yield
    finally:
        mallopt(_M_ARENA_MAX, 0)        # 0: glibc's default limit


def _cmd_simulate(args) -> int:
    from . import scene as sc

    s = _load(args.scene)
    bands = _parse_bands(args.bands)
    noise = False if args.no_noise else None
    # Check the overrides, the output directory, the files and the memory the scene
    # needs before any computation.
    resolved = sc.with_overrides(s, seed=args.seed, bands=bands, noise=noise)
    from .cache import read_ahead
    # the last run's programs load in the background while the pipeline is imported
    # and prepared (a second run's largest single wait otherwise)
    programs = read_ahead(resolved, start=False)
    # one malloc arena only where the programs are stored: XLA's compilation allocates
    # from many threads at once, and through one arena a first run took 146 s, not 93 s
    warm = programs is not None and programs.stored
    with _one_malloc_arena() if warm else contextlib.nullcontext():
        return _simulate_run(args, s, resolved, bands, noise,
                             programs.start() if programs is not None else None)


def _simulate_run(args, s, resolved, bands, noise, programs) -> int:
    """`simulate` once the scene is read and the programs' reading ahead is set up."""
    from .preflight import preflight
    from .rundir import check_target

    out = os.fspath(check_target(args.out, "--out"))
    for note in preflight(resolved):
        print(f"clumpylen: warning: {note}", file=sys.stderr)
    try:
        from .cache import enable_compilation_cache
        from .pipeline import simulate
    except ImportError as exc:
        print(f"clumpylen: error: the simulation pipeline is not available ({exc})", file=sys.stderr)
        return EXIT_FAILURE
    cache_dir = enable_compilation_cache()
    with _long_run_memory():
        summary = simulate(s, out, bands=bands, seed=args.seed, noise=noise,
                           progress=not args.quiet, programs=programs)
    if args.plots:
        from .plotting import plot_run

        plot_run(out)
    if not args.quiet:
        _print_summary(summary, out)
        _print_files_and_split(summary, out, cache_dir)
    return EXIT_OK


def _parse_images(items, required=True) -> dict:
    """--image BAND=FILE arguments → {BAND: path}, checked before any computation."""
    images = {}
    for item in items or []:
        band, sep, path = item.partition("=")
        if not sep or not band.strip() or not path.strip():
            raise ConfigError("--image", item, "BAND=FILE, e.g. F200W=bands/F200W.fits")
        if not os.path.isfile(path):
            raise ConfigError(f"--image {band}", path, "an existing FITS file")
        key = band.strip().upper()
        if key in images:
            raise ConfigError("--image", key, "each band once (it was given twice)")
        images[key] = path
    if not images and required:
        raise ConfigError("--image", None, "at least one BAND=FILE")
    return images


def _read_fit_image(band: str, path: str):
    """(image, variance or None) of a --image file: the SCI HDU, else the first 2-D image."""
    from astropy.io import fits
    import numpy as np

    try:
        hdul = fits.open(path, memmap=False)
    except Exception as exc:
        raise ConfigError(f"--image {band}", path, f"a readable FITS file ({exc})") from None
    with hdul:
        from .observations.read import find_image_hdu
        idx = find_image_hdu(hdul, path, f"--image {band}")
        var = np.asarray(hdul["VARIANCE"].data, float) if "VARIANCE" in [h.name for h in hdul] else None
        return np.asarray(hdul[idx].data, float), var


def _cmd_fit_observations(args) -> int:
    """`clumpylen fit SCENE --out DIR` for a scene with [[observations]] (SCENE.md v2)."""
    import dataclasses

    from .observations.config import load_observation_scene
    from .observations.run import fit_observation_scene

    scene = load_observation_scene(args.scene)
    images = _parse_images(args.image, required=False)
    names = [o.filter for o in scene.observations]
    for band in images:
        if band not in names:
            raise ConfigError("--image", band, "a filter of the scene's [[observations]]: "
                              + ", ".join(names))
    if images:
        scene = dataclasses.replace(scene, observations=tuple(
            dataclasses.replace(o, image=os.path.abspath(images.get(o.filter, o.image)))
            for o in scene.observations))
    if args.method is not None:   # the command line wins over [fit] method
        scene = dataclasses.replace(scene, fit=dataclasses.replace(scene.fit, method=args.method))
    out = os.path.abspath(args.out)
    if os.path.exists(out) and not os.path.isdir(out):
        raise ConfigError("--out", args.out, "a directory (this path is a file)")
    say = None if args.quiet else (lambda m: print(m, file=sys.stderr))
    from .cache import enable_compilation_cache
    enable_compilation_cache()   # a second fit of these cutouts loads its programs (cache.py)
    fit, table, host, files = fit_observation_scene(scene, out, progress=say)
    if not args.quiet:
        print(f"wrote {out} ({', '.join(os.path.basename(str(f)) for f in files)}); "
              f"{fit.n_clumps} clumps, {'converged' if fit.success else 'NOT converged'}")
    return EXIT_OK


def _cmd_fit(args) -> int:
    from . import scene as sc
    from .observations.config import is_observation_scene

    if os.path.isfile(args.scene) and is_observation_scene(args.scene):
        return _cmd_fit_observations(args)
    s = _load(args.scene)
    images = _parse_images(args.image)
    for band in images:
        if band not in s.band_names:
            raise ConfigError("--image", band, "a filter of the scene: " + ", ".join(s.band_names))
    s = sc.with_overrides(s, seed=args.seed, bands=list(images), noise=None)
    import numpy as np

    from .pipeline import prepare

    data, variances = {}, {}
    for band, path in images.items():
        data[band], var = _read_fit_image(band, path)
        if var is not None:
            variances[band] = var
    if variances and len(variances) != len(data):
        raise ConfigError("--image", sorted(set(data) - set(variances)),
                          "FITS files that all have a VARIANCE extension, or none")
    for band, img in data.items():
        usable = np.isfinite(img) & (np.isfinite(variances[band]) & (variances[band] > 0)
                                     if band in variances else True)
        if not np.any(usable):
            raise ConfigError(f"--image {band}", images[band],
                              "an image with usable pixels (all are NaN or have zero variance)")
    from .cache import enable_compilation_cache
    enable_compilation_cache()   # after the inputs are checked, before anything compiles
    prep = prepare(s)
    shapes = {lay.name: lay.grid.shape for lay in prep.model.layouts}
    for band, img in data.items():
        if img.shape != shapes[band]:
            raise ConfigError(f"--image {band}", f"shape {img.shape}",
                              f"the scene's detector grid for {band}, shape {shapes[band]}")
    order = [lay.name for lay in prep.model.layouts]
    out = os.path.abspath(args.out)
    if args.method in (None, "map"):
        # no catalogue: clumps found, seeded and counted from the images (inference/auto.py)
        from .inference.auto_run import run_auto_fit
        run_auto_fit(prep, [data[b] for b in order],
                     [variances[b] for b in order] if variances else None, out_dir=out)
        if not args.quiet:
            print(f"wrote {out} (fit.ecsv, fit_steps.json, residuals)")
        return EXIT_OK
    # a sampler starts from the same data-driven MAP fit, never from the scene's clumps
    from .inference.auto_run import run_sampled_fit
    run_sampled_fit(prep, [data[b] for b in order], [variances[b] for b in order] if variances else None,
                    method=args.method, out_dir=out)
    if not args.quiet:
        print(f"wrote {out} (fit.ecsv, residuals, chains.npz)")
    return EXIT_OK


def _print_summary(summary, out: str) -> None:
    print(f"wrote {out}")
    if not isinstance(summary, dict):
        return
    for band, info in (summary.get("bands") or {}).items():
        rate, counts = info.get("total_counts_per_s"), info.get("total_counts")
        if isinstance(rate, (int, float)):
            print(f"  {band}: source {rate:.6g} counts/s ({counts:.6g} counts in the exposure)")
    timings = summary.get("timings_s") or summary.get("timings") or {}
    if isinstance(timings, dict) and timings:
        total = timings.get("total")
        if not isinstance(total, (int, float)):  # no overall timing: add the stages
            total = sum(v for v in timings.values() if isinstance(v, (int, float)))
        print(f"  time: {total:.1f} s")


def _cmd_study(args) -> int:
    from .study import load_study, run_study

    study = load_study(args.study)             # validated entirely before any work is sent
    if args.workers is not None and args.workers < 1:
        raise ConfigError("--workers", args.workers, "an integer >= 1")
    out = os.path.abspath(args.out)
    if os.path.exists(out) and not os.path.isdir(out):
        raise ConfigError("--out", args.out, "a directory (this path is a file)")
    if not args.quiet:
        print(f"{study.describe()} -> {out}", file=sys.stderr)
    result = run_study(study, out, scheduler=args.scheduler, n_workers=args.workers,
                       progress=not args.quiet)
    if not args.quiet:
        print(f"wrote {out}: {result['tasks']} tasks ({result['ran']} run now, "
              f"{result['tasks'] - result['ran']} already done)")
        for name, path in result["files"].items():
            print(f"  {name}: {path}")
    return EXIT_OK


def _print_files_and_split(summary, out: str, cache_dir) -> None:
    """The files of a run, folder by folder, and its time split into compile and run."""
    from pathlib import Path

    root = Path(out)
    by_dir: dict = {}
    for f in sorted(p for p in root.rglob("*") if p.is_file()):
        rel = f.relative_to(root)
        by_dir.setdefault(str(rel.parent), []).append(rel.name)
    for folder, names in sorted(by_dir.items(), key=lambda kv: (kv[0] != ".", kv[0])):
        label = "" if folder == "." else f"{folder}/: "
        print(f"  files {label}{' '.join(names)}")
    split = summary.get("timings_split_s") if isinstance(summary, dict) else None
    if not split:
        return
    comp = sum(v["compile"] for v in split.values())
    run = sum(v["run"] for v in split.values())
    big = sorted(split.items(), key=lambda kv: -kv[1]["total"])[:5]
    print("  slowest stages: " + ", ".join(
        f"{k} {v['total']:.1f} s ({v['compile']:.1f} compile)" for k, v in big))
    where = f"compilation cache {cache_dir}" if cache_dir else "compilation cache off"
    # programs after the band render load and run in a background thread beside the main
    # one: the stages' seconds, summed over both threads, exceed the wall time
    print(f"  time split (stages summed over the main and background threads): compile "
          f"{comp:.1f} s + run {run:.1f} s ({where})")


def _existing_dir(path: str) -> str:
    """A complete run directory (its manifest checked), else a user error."""
    from .rundir import check_run

    if not os.path.isdir(path):
        raise FileNotFoundError(f"run directory not found: {path}")
    check_run(path, "DIR")
    return path


def _cmd_plot(args) -> int:
    d = _existing_dir(args.dir)
    from .plotting import plot_run

    result = plot_run(d)
    if result:
        for item in result if isinstance(result, (list, tuple)) else [result]:
            print(item)
    return EXIT_OK


def _cmd_analyze(args) -> int:
    d = _existing_dir(args.dir)
    from .analysis import analyze_run

    kwargs = {}
    if args.snr_threshold is not None:
        kwargs["snr_threshold"] = args.snr_threshold
    result = analyze_run(d, **kwargs)
    if isinstance(result, dict):
        import json

        from .io import _jsonable

        print(json.dumps(_jsonable(result), indent=2))
    elif result is not None:
        print(result)
    return EXIT_OK


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("clumpylen_jax")
    except Exception:  # not installed (running from a checkout)
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of `clumpylen` (exposed for docs and tests)."""
    p = argparse.ArgumentParser(
        prog="clumpylen",
        description="Simulate strongly lensed clumpy galaxies as HST and JWST would see them.",
    )
    p.add_argument("--version", action="version", version=f"clumpylen_jax {_version()}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)
    _add_scene_commands(sub)
    _add_run_commands(sub)
    _add_run_dir_commands(sub)
    return p


def _add_scene_commands(sub) -> None:
    """The subcommands scenes, show, validate: read a scene, run nothing."""
    q = sub.add_parser("scenes", help="list the built-in scenes")
    q.set_defaults(func=_cmd_scenes)

    q = sub.add_parser("show", help="print a scene as TOML (a starting point for your own)")
    q.add_argument("scene", metavar="SCENE", help="built-in scene name or path to a .toml file")
    q.add_argument("--resolved", action="store_true", help="print it with every default filled in")
    q.set_defaults(func=_cmd_show)

    q = sub.add_parser("validate", help="check a scene; print it resolved and the stages it runs")
    q.add_argument("scene", metavar="SCENE", help="built-in scene name or path to a .toml file")
    q.set_defaults(func=_cmd_validate)


def _add_run_commands(sub) -> None:
    """The subcommands simulate, fit, study: the commands that compute."""
    q = sub.add_parser("simulate", help="simulate a scene and write images, catalogue and summary")
    q.add_argument("scene", metavar="SCENE", help="built-in scene name or path to a .toml file")
    q.add_argument("--out", "-o", required=True, metavar="DIR", help="output directory")
    q.add_argument("--seed", type=int, help="override the scene's seed")
    q.add_argument("--bands", metavar="F1,F2", help="simulate only these bands (comma-separated filters)")
    q.add_argument("--no-noise", action="store_true", help="noise-free images only")
    q.add_argument("--quiet", "-q", action="store_true", help="no progress output")
    q.add_argument("--plots", action="store_true", help="also make the diagnostic figures")
    q.add_argument("--no-cache", action="store_true",
                   help="keep nothing between runs: no compiled programs, PSFs or traced rays "
                        "read or written (same as CLUMPYLEN_NO_CACHE=1)")
    q.set_defaults(func=_cmd_simulate)

    q = sub.add_parser("fit", help="fit the scene's clumps to observed or simulated images")
    q.add_argument("scene", metavar="SCENE", help="a scene with [[observations]] (SCENE.md v2), "
                   "or a built-in name / .toml whose catalogue and host are the starting point")
    q.add_argument("--image", action="append", metavar="BAND=FILE",
                   help="an image to fit (SCI HDU or the first 2-D image; a VARIANCE extension is "
                   "used if present); with [[observations]], replaces that band's image")
    q.add_argument("--out", "-o", required=True, metavar="DIR", help="output directory")
    q.add_argument("--method", choices=("map", "emcee", "nuts"),
                   help="map (the default; with [[observations]], the scene's [fit] method), "
                   "or the posterior sampled from the optimum by emcee or nuts")
    q.add_argument("--seed", type=int, help="override the scene's seed (clump catalogue)")
    q.add_argument("--quiet", "-q", action="store_true", help="no output")
    q.add_argument("--no-cache", action="store_true",
                   help="neither read nor write compiled programs (same as CLUMPYLEN_NO_CACHE=1)")
    q.set_defaults(func=_cmd_fit)

    q = sub.add_parser("study", help="run a study (many samples, injections or fits) on Dask; "
                       "rerun to resume")
    q.add_argument("study", metavar="STUDY", help="study file (.toml)")
    q.add_argument("--out", "-o", required=True, metavar="DIR", help="output directory")
    q.add_argument("--scheduler", metavar="ADDRESS", help="an existing Dask scheduler "
                   "(tcp://host:8786); default: a LocalCluster here; 'synchronous': no Dask")
    q.add_argument("--workers", type=int, help="LocalCluster workers (default: one per core)")
    q.add_argument("--quiet", "-q", action="store_true", help="no progress output")
    q.set_defaults(func=_cmd_study)


def _add_run_dir_commands(sub) -> None:
    """The subcommands plot, analyze: read a finished run's directory."""
    q = sub.add_parser("plot", help="make the figures of a finished run")
    q.add_argument("dir", metavar="DIR", help="output directory of `clumpylen simulate`")
    q.set_defaults(func=_cmd_plot)

    q = sub.add_parser("analyze", help="S/N and limiting magnitudes of a finished run")
    q.add_argument("dir", metavar="DIR", help="output directory of `clumpylen simulate`")
    q.add_argument("--snr-threshold", type=float, help="detection threshold in S/N (default: the analysis module's)")
    q.set_defaults(func=_cmd_analyze)


def main(argv: list[str] | None = None) -> int:
    """Run `clumpylen` with `argv` (default sys.argv[1:]); returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help (0) or a usage error (2), already printed
        return int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_USAGE
    if args.command not in ("scenes", "show"):  # those two stay free of JAX
        from . import enable_float64

        enable_float64()  # the command computes in float64 unless a scene asks for float32
    saved_switch = os.environ.get("CLUMPYLEN_NO_CACHE")  # --no-cache sets it for this command only
    if getattr(args, "no_cache", False):   # the one switch (`cache.py`): programs, PSFs, rays
        os.environ["CLUMPYLEN_NO_CACHE"] = "1"
    try:
        return args.func(args)
    except (ConfigError, _UserError) as exc:
        print(f"clumpylen: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except FileNotFoundError as exc:
        msg = exc.strerror and exc.filename and f"{exc.strerror}: {exc.filename}" or str(exc)
        print(f"clumpylen: error: {msg}", file=sys.stderr)
        return EXIT_USAGE
    except tomllib.TOMLDecodeError as exc:
        print(f"clumpylen: error: invalid TOML: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:
        # Output piped into `head` and closed early: not an error. Point stdout
        # at devnull so the interpreter's final flush does not complain.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK
    except KeyboardInterrupt:
        print("clumpylen: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:
        # a read-only or full disk, a path under a file...: the path and the reason
        from .rundir import describe_oserror

        print(f"clumpylen: error: {describe_oserror(exc)}", file=sys.stderr)
        return EXIT_USAGE
    finally:
        if saved_switch is None:
            os.environ.pop("CLUMPYLEN_NO_CACHE", None)
        else:
            os.environ["CLUMPYLEN_NO_CACHE"] = saved_switch


def console() -> None:
    """The `clumpylen` script: `main` on the command line's arguments, then exit.

    After `simulate`, the process ends without the interpreter's teardown (`os._exit`,
    once the output streams and logging are flushed): by then every file is written and
    swapped into place, and tearing down what the run leaves (XLA's client and compiled
    programs, the imported modules) takes ~0.6 s of a warm run's ~10 s. Other commands
    (a study's Dask cluster, for one) exit as usual.

    NumPy's OpenBLAS threads wait for the next job by spinning for ~0.1 s after each one
    (its default `OPENBLAS_THREAD_TIMEOUT`, 2²⁸ cycles) before they sleep; between the
    many small products of the PSFs' matrix Fourier transforms (poppy) they spun for
    1.5–4 s of CPU of a cold `simulate`'s 9 PSFs (6.6–9.0 s CPU for 4.0–5.6 s wall; 2⁴
    cycles: 5.0–5.3 s CPU for 4.2–4.4 s wall), taken from the thread compiling beside
    them. Set here, before anything imports NumPy, for this process only (a value the
    user set is kept); it changes when threads sleep, never a result."""
    os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "4")
    argv = sys.argv[1:]
    code = main(argv)
    if argv[:1] == ["simulate"]:
        import logging

        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError):      # a closed pipe: nothing left to say
                stream.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    console()
