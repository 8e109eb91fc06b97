"""Counters and latency histograms of the service, written as Prometheus text (format 0.0.4) by hand.

Updated from worker threads and the event loop alike, so every update takes one lock. Label values
are pipeline names from the registry, error codes from `core.errors` and online states reported by
pipelines (sanitised): never raw client input. Values are per process (per uvicorn worker).
"""

from __future__ import annotations

import re
import threading
from collections import Counter, defaultdict
from collections.abc import Iterable

# Upper bounds of the latency histogram buckets, seconds (+Inf is implied).
LATENCY_BUCKETS_S = (0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
UNKNOWN_PIPELINE = "unknown"  # pipeline label of a request that named no registered pipeline


class Histogram:
    def __init__(self) -> None:
        self.counts = [0] * (len(LATENCY_BUCKETS_S) + 1)
        self.total = 0.0

    def observe(self, seconds: float) -> None:
        index = next((i for i, b in enumerate(LATENCY_BUCKETS_S) if seconds <= b), len(LATENCY_BUCKETS_S))
        self.counts[index] += 1
        self.total += seconds

    def lines(self, name: str, labels: str) -> Iterable[str]:
        cumulative = 0
        for bound, count in zip((*LATENCY_BUCKETS_S, "+Inf"), self.counts, strict=True):
            cumulative += count
            yield f'{name}_bucket{{{labels},le="{bound}"}} {cumulative}'
        yield f"{name}_sum{{{labels}}} {self.total:.6f}"
        yield f"{name}_count{{{labels}}} {cumulative}"


class Metrics:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.frames: Counter[tuple[str, str]] = Counter()  # (pipeline, route) -> frames denoised
        self.errors: Counter[tuple[str, str]] = Counter()  # (pipeline, code) -> frames refused or failed
        self.step = defaultdict(Histogram)  # pipeline -> seconds in pipeline.step
        self.request = defaultdict(Histogram)  # pipeline -> seconds from body received to response ready
        self.sessions_started = 0
        self.sessions_expired = 0

    def frame_done(self, pipeline: str, route: str, step_s: float, total_s: float) -> None:
        with self._lock:
            self.frames[pipeline, route] += 1
            self.step[pipeline].observe(step_s)
            self.request[pipeline].observe(total_s)

    def frame_failed(self, pipeline: str, code: str) -> None:
        with self._lock:
            self.errors[pipeline, code] += 1

    def session_started(self) -> None:
        with self._lock:
            self.sessions_started += 1

    def session_expired(self, count: int = 1) -> None:
        with self._lock:
            self.sessions_expired += count

    def render(
        self,
        *,
        live_sessions: int,
        max_sessions: int,
        inflight: int,
        max_inflight: int,
        rejected_busy: int,
        rejected_sessions: int,
        online_states: Iterable[str],
    ) -> str:
        """The Prometheus text exposition of every metric, ending with a newline."""
        out: list[str] = []

        def family(name: str, kind: str, help_text: str, samples: Iterable[str]) -> None:
            out.extend((f"# HELP {name} {help_text}", f"# TYPE {name} {kind}", *samples))

        def single(name: str, kind: str, help_text: str, value: float) -> None:
            family(name, kind, help_text, (f"{name} {value}",))

        with self._lock:
            family("mcdenoise_frames_total", "counter", "Frames denoised, by pipeline and route.",
                   (f'mcdenoise_frames_total{{pipeline="{p}",route="{r}"}} {n}'
                    for (p, r), n in sorted(self.frames.items())))
            family("mcdenoise_frame_errors_total", "counter", "Frames refused or failed, by pipeline and error code.",
                   (f'mcdenoise_frame_errors_total{{pipeline="{p}",code="{c}"}} {n}'
                    for (p, c), n in sorted(self.errors.items())))
            for name, histograms, help_text in (
                ("mcdenoise_step_seconds", self.step, "Time in the pipeline's step, per frame."),
                ("mcdenoise_frame_seconds", self.request,
                 "Time from a frame's body received to its answer encoded (queue, decode, step, encode)."),
            ):
                family(name, "histogram", help_text,
                       (line for p, h in sorted(histograms.items()) for line in h.lines(name, f'pipeline="{p}"')))
            single("mcdenoise_sessions_started_total", "counter", "Sessions created.", self.sessions_started)
            single("mcdenoise_sessions_expired_total", "counter", "Sessions ended for being idle.",
                   self.sessions_expired)
        single("mcdenoise_sessions_live", "gauge", "Live sessions.", live_sessions)
        single("mcdenoise_sessions_max", "gauge", "Most live sessions allowed.", max_sessions)
        single("mcdenoise_inflight_frames", "gauge", "Frames accepted and not yet answered.", inflight)
        single("mcdenoise_inflight_frames_max", "gauge", "Most frames accepted at once.", max_inflight)
        family("mcdenoise_rejected_total", "counter", "Requests refused for capacity, by reason.",
               (f'mcdenoise_rejected_total{{reason="busy"}} {rejected_busy}',
                f'mcdenoise_rejected_total{{reason="too_many_sessions"}} {rejected_sessions}'))
        states = Counter(_label(s) for s in online_states)
        family("mcdenoise_online_sessions", "gauge", "Sessions with online training, by the worker's reported state.",
               (f'mcdenoise_online_sessions{{state="{s}"}} {n}' for s, n in sorted(states.items())))
        return "\n".join(out) + "\n"


def _label(value: object) -> str:
    """A safe label value: at most 40 characters of [A-Za-z0-9_.-]."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", str(value))[:40] or "unknown"
