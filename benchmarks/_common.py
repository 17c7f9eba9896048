"""Shared helpers of the benchmark scripts: timing, memory, result files.

Times are wall-clock seconds on whatever machine runs the script (the numbers
in benchmarks/README.md say which). "cold" includes building the model and
compiling; "warm" is the median of repeated calls of the compiled function.
Memory is XLA's own accounting of the compiled function (arguments + outputs +
temporaries, `Compiled.memory_analysis()`), plus the peak RSS of the process.
"""

from __future__ import annotations

import json
import os
import platform
import resource
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def machine():
    """A short description of the machine and software the numbers come from."""
    return {
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "cpu_count": os.cpu_count(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def block(x):
    return jax.block_until_ready(x)


def timed(fn, *args):
    """(result, seconds) of one call, waiting for the device."""
    t = time.perf_counter()
    out = block(fn(*args))
    return out, time.perf_counter() - t


def warm_time(fn, *args, repeats=5, min_total=0.2):
    """Median seconds of repeated calls of an already-compiled `fn` (at least `repeats`)."""
    times = []
    t_start = time.perf_counter()
    while len(times) < repeats or (time.perf_counter() - t_start < min_total and len(times) < 50):
        _, dt = timed(fn, *args)
        times.append(dt)
    return statistics.median(times)


def compiled_bytes(jitted, *args):
    """Bytes XLA needs for one call: arguments + outputs + temporaries (None if unknown)."""
    try:
        ma = jitted.lower(*args).compile().memory_analysis()
        return int(ma.argument_size_in_bytes + ma.output_size_in_bytes + ma.temp_size_in_bytes)
    except Exception:  # noqa: BLE001 - a backend without memory stats
        return None


def peak_rss_mb():
    """Peak resident set size of this process so far, MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def tree_bytes(tree):
    """Bytes held by the arrays of a pytree (e.g. a built model's rays and operators)."""
    return int(sum(np.asarray(x).nbytes for x in jax.tree_util.tree_leaves(tree)
                   if hasattr(x, "nbytes")))


def write_json(name, payload):
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(payload, indent=1, default=_jsonable))
    os.replace(tmp, path)
    return path


def write_text(name, text):
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / name
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
    return path


def _jsonable(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)


def fmt(v, digits=3):
    if v is None:
        return "–"
    if isinstance(v, str):
        return v
    if isinstance(v, (int, np.integer)):
        return str(v)
    if not np.isfinite(v):
        return str(v)
    if v == 0:
        return "0"
    if abs(v) >= 1e4 or abs(v) < 1e-3:
        return f"{v:.{digits - 1}e}"
    return f"{v:.{digits}g}"


def markdown_table(rows, columns):
    """A Markdown table of dict rows; columns: list of (key, header)."""
    head = "| " + " | ".join(h for _, h in columns) + " |"
    sep = "|" + "|".join("---" for _ in columns) + "|"
    body = ["| " + " | ".join(fmt(r.get(k)) for k, _ in columns) + " |" for r in rows]
    return "\n".join([head, sep] + body)
