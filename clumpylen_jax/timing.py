"""Wall time of pipeline stages, split into compilation and running.

JAX reports each tracing, lowering and XLA compilation (or persistent-cache load) as a
time span (`jax.monitoring`). `StageClock` collects those spans while it is open and,
per stage, counts as "compile" the union of the spans inside the stage (a jit traced
inside another's tracing is counted once) and as "run" the rest of the stage's wall time.
"""

from __future__ import annotations

import contextlib
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
    listened to only while a stage is open.
    """

    def __init__(self):
        self._spans = []
        self._stages = []          # (name, start, end), in time.time() seconds as JAX's spans

    def _listener(self, event, start, end, **_):
        if event in COMPILE_EVENTS:
            self._spans.append((start, end))

    @contextlib.contextmanager
    def stage(self, name: str):
        monitoring.register_event_time_span_listener(self._listener)
        start = time.time()
        try:
            yield
        finally:
            self._stages.append((name, start, time.time()))
            monitoring.unregister_event_time_span_listener(self._listener)

    def split(self, digits: int = 3) -> dict:
        out = {}
        for name, start, end in self._stages:
            inside = [(max(s, start), min(e, end)) for s, e in self._spans if e > start and s < end]
            comp = min(_union_length(inside), end - start)
            out[name] = {"total": round(end - start, digits), "compile": round(comp, digits),
                         "run": round(end - start - comp, digits)}
        return out
