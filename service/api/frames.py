"""The operations the routes call: denoise one stateless frame, open a session, denoise a session's next frame.

Each frame is one job in the worker pool (decode, step, encode), accounted in the metrics whether it
succeeds or fails. A session's frames run under its lock, so they step its state strictly in order;
a frame refused before its step (not EXR, too large, a layer over its limit) changes nothing in the session
but its error count, and one the pipeline refuses (a missing layer, another size, values its stages could not
denoise: 422) also starts its sequence again (`SequenceState.forget`). A frame past the deadline
(MCDENOISE_FRAME_TIMEOUT_S) is answered 504 at once, but its step runs on (see workers.py): in a session
it still advances the state, and the session's next frame waits for it.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass

import numpy as np

from service import pipelines
from service.api import codec
from service.api.core.errors import UnknownSessionError, to_api_error
from service.api.sessions import Session, SessionSpec, build_session, close_state
from service.api.state import Services
from service.api.telemetry import UNKNOWN_PIPELINE
from service.frame import RADIANCE_LAYERS, Frame, FrameError
from service.pipelines import Pipeline, SequenceState

log = logging.getLogger("mcdenoise.api")


@dataclass(frozen=True)
class Denoised:
    """One answered frame."""

    body: bytes  # EXR or PNG bytes
    media_type: str
    frame_index: int  # index of this frame in its sequence (0 for a stateless frame)
    step_ms: float  # wall time of pipeline.step, milliseconds
    nonfinite: int  # NaN/Inf input values repaired
    error_mean: float | None = None  # mean of the pipeline's `error` estimate (auto), when it makes one


def _step(
    pipeline: Pipeline, state: SequenceState | None, body: bytes, output: codec.Output, services: Services,
    session: Session | None = None,
) -> tuple[Denoised, SequenceState]:
    """Decode (in the session's dialect), check, step and encode one frame (in a pool thread). `state` None:
    a first frame."""
    mapping, view_layer = (session.channel_map, session.spec.view_layer) if session else (None, None)
    frame = codec.decode(body, services.settings, pipeline.reads(), mapping, view_layer)
    if state is None:
        state = pipeline.start(frame.height, frame.width)
    index = state.frame_index
    start = time.perf_counter()
    try:
        out, state = pipeline.step(frame, state)
    except FrameError:
        raise
    except (ArithmeticError, ValueError) as err:  # numerics the frame's values broke (FloatingPointError, ...)
        raise _unprocessable(pipeline, frame, err) from err
    step_ms = 1e3 * (time.perf_counter() - start)
    error = float(out["error"].mean()) if "error" in out else None
    return Denoised(codec.encode(out, output), output.media_type, index, step_ms, frame.nonfinite_total,
                    error), state


def _unprocessable(pipeline: Pipeline, frame: Frame, err: Exception) -> FrameError:
    """The 422 of a frame that `pipeline` could not denoise, naming its radiance layer of largest magnitude:
    the frame door bounds every other layer a stage could overflow on (albedo, normal), so extreme radiance
    is what a client can change. Logged with its traceback (a stage may need a fix)."""
    log.warning("pipeline %s failed on a frame: %s", pipeline.name, err, exc_info=err)
    peaks = {name: float(np.abs(frame[name]).max()) for name in RADIANCE_LAYERS if name in frame}
    layer = max(peaks, key=peaks.__getitem__)
    return FrameError(f"pipeline '{pipeline.name}' could not denoise this frame ({type(err).__name__}: {err}); "
                      f"layer '{layer}' has values up to {peaks[layer]:.3g} in magnitude", layer)


async def denoise_once(services: Services, name: str, body: bytes, output: codec.Output) -> Denoised:
    """Denoise one frame as the first frame of a sequence of pipeline `name` (default options)."""
    received = time.perf_counter()
    try:
        pipelines.pipeline_class(name)
    except pipelines.UnknownPipelineError:
        services.metrics.frame_failed(UNKNOWN_PIPELINE, "unknown_pipeline")
        raise

    def job() -> Denoised:
        return _step(services.stateless_pipeline(name), None, body, output, services)[0]

    try:
        result = await services.pool.run(job, deadline=services.settings.frame_timeout_s)
    except Exception as exc:
        services.metrics.frame_failed(name, to_api_error(exc).code)
        raise
    services.metrics.frame_done(name, "rest", result.step_ms / 1e3, time.perf_counter() - received)
    return result


async def open_session(services: Services, spec: SessionSpec, owner: str | None) -> Session:
    """Create a session (429 when the store is full; pipeline construction runs in the pool)."""
    codec.check_size(spec.width, spec.height, services.settings.max_width, services.settings.max_height)
    with services.sessions.reserve():
        session = await services.pool.run(build_session, spec, owner, services.sessions.new_id())
        services.sessions.add(session)
    services.metrics.session_started()
    return session


async def end_session(services: Services, session: Session) -> None:
    """End `session`: it is gone at once for new requests; its state is closed after the frame in progress.
    Waits for that close at most MCDENOISE_FRAME_TIMEOUT_S; past it the close happens in the background."""
    services.sessions.pop(session.id, session.owner)

    async def close_after_frame() -> None:
        async with session.lock:
            await asyncio.get_running_loop().run_in_executor(None, close_state, session)

    closing = asyncio.ensure_future(close_after_frame())
    _background.add(closing)
    closing.add_done_callback(_background.discard)
    await asyncio.wait({closing}, timeout=services.settings.frame_timeout_s)


_background: set[asyncio.Future] = set()  # closes still running after their DELETE answered (kept referenced)


async def session_frame(
    services: Services, session: Session, body: bytes, output: codec.Output, *, route: str, wait: float = 0.0
) -> Denoised:
    """Denoise the next frame of `session`, in order with its other frames.

    A frame refused before its step (not EXR, too large, a layer over its limit) leaves the state as it was;
    one the pipeline refuses (FrameError, a stage's numerics) starts the sequence again (module docstring).
    """
    received = time.perf_counter()

    def job() -> Denoised:
        if session.ended:  # ended while this frame waited for its turn
            raise UnknownSessionError(session.id)
        result, session.state = _step(session.pipeline, session.state, body, output, services, session)
        session.record(result.step_ms)
        return result

    session.busy += 1
    try:
        result = await services.pool.run(job, wait=wait, hold=session.lock,
                                         deadline=services.settings.frame_timeout_s)
    except Exception as exc:
        session.errors += 1
        services.metrics.frame_failed(session.spec.pipeline, to_api_error(exc).code)
        raise
    finally:
        session.busy -= 1
        session.last_used = time.monotonic()
    services.metrics.frame_done(session.spec.pipeline, route, result.step_ms / 1e3, time.perf_counter() - received)
    return result
