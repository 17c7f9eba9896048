"""Wall time of pipeline stages, split into compilation and running.

JAX reports each tracing, lowering and XLA compilation (or persistent-cache load) as a
time span (`jax.monitoring`), in the thread that does the work. `StageClock` collects
those spans while a stage is open and, per stage, counts as "compile" the union of the
spans inside the stage *in the stage's own thread* (a jit traced inside another's tracing
is counted once) and as "run" the rest of the stage's wall time. Stages may run side by
side in several threads (the pipeline loads and launches programs in the background while
it writes): each is timed in its own thread, so their totals can add up to more than the
wall time of the run.
"""

from __future__ import annotations

import contextlib
import threading
import time

import jax.monitoring as monitoring

# tracing to a jaxpr, lowering to StableHLO, XLA compilation or loading from the cache
COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
                  "/jax/core/compile/jaxpr_to_mlir_module_duration",
                  "/jax/core/compile/backend_compile_duration")


def _union_length(spans):
    """Total length covered by (start, end) intervals."""
    total, reach = 0.0, -float("inf")
    for start, end in sorted(spans):
        if end > reach:
            total += end - max(start, reach)
            reach = end
    return total


class StageClock:
    """Per-stage wall, compile and run seconds.

    ``clock = StageClock(); with clock.stage("render"): ...`` then
    ``clock.split()`` → {stage: {"total": s, "compile": s, "run": s}}. JAX's spans are
    listened to only while some stage is open; a stage counts the spans of its own thread.
    """

    def __init__(self):
        self._spans = []           # (thread id, start, end)
        self._stages = []          # (name, thread id, start, end), in time.time() seconds as JAX's spans
        self._lock = threading.Lock()
        self._open = 0

    def _listener(self, event, start, end, **_):
        if event in COMPILE_EVENTS:
            self._spans.append((threading.get_ident(), start, end))

    @contextlib.contextmanager
    def stage(self, name: str):
        with self._lock:
            if self._open == 0:
                monitoring.register_event_time_span_listener(self._listener)
            self._open += 1
        start = time.time()
        try:
            yield
        finally:
            self._stages.append((name, threading.get_ident(), start, time.time()))
            with self._lock:
                self._open -= 1
                if self._open == 0:
                    monitoring.unregister_event_time_span_listener(self._listener)

    def split(self, digits: int = 3) -> dict:
        out = {}
        for name, tid, start, end in self._stages:
            inside = [(max(s, start), min(e, end)) for t, s, e in self._spans
                      if t == tid and e > start and s < end]
            comp = min(_union_length(inside), end - start)
            out[name] = {"total": round(end - start, digits), "compile": round(comp, digits),
                         "run": round(end - start - comp, digits)}
        return out
