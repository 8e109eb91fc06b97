"""The bounded pool that runs CPU work (EXR decode, pipeline steps, encode) off the event loop.

At most `threads` jobs run at once and at most `max_inflight` are accepted (running or queued); a
request that finds every slot taken is answered `503 busy` with Retry-After at once (or after
`wait` seconds for streamed frames), so the service never hangs under load. A job's slot, and an
optional asyncio lock the caller holds for ordering (a session's), are released when the job has
really finished in its thread, not when the awaiting request goes away: a cancelled request cannot let
two steps of one session overlap or let the pool take more than its share.

Deadline: a job not finished `deadline` seconds after it was accepted (waiting for its lock included)
is answered `504 timeout` at once. Python cannot stop a thread, and a numba kernel or an ONNX Runtime
run cannot be interrupted, so the job itself runs on to its end and keeps its slot (and lock) until
then: the request is freed, the capacity is not. The options' caps (service/pipelines/options.py) and
the frame limits bound how long any job can run.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

from service.api.core.errors import ApiError

T = TypeVar("T")


class WorkerPool:
    def __init__(self, threads: int, max_inflight: int, retry_after_s: int):
        self.threads = threads
        self.max_inflight = max_inflight
        self.retry_after_s = retry_after_s
        self.inflight = 0  # accepted jobs: running or waiting for a thread or for their lock
        self.rejected = 0  # requests answered 503 busy since start
        self._slots = asyncio.Semaphore(max_inflight)
        self._executor = ThreadPoolExecutor(threads, thread_name_prefix="mcdenoise-frame")

    async def run(
        self,
        fn: Callable[..., T],
        *args: Any,
        wait: float = 0.0,
        hold: asyncio.Lock | None = None,
        deadline: float | None = None,
    ) -> T:
        """Run `fn(*args)` in a pool thread and return its result (or raise its exception).

        wait: seconds to wait for a free slot before answering busy (0: answer at once).
        hold: a lock acquired after the slot and released when `fn` has finished (ordering of a session).
        deadline: seconds from taking the slot to the result before ApiError 504 (None: no deadline).
        """
        await self._take_slot(wait)
        loop = asyncio.get_running_loop()
        start = loop.time()
        try:
            if hold is not None:
                await asyncio.wait_for(hold.acquire(), deadline)
        except TimeoutError:
            self._give_slot()
            raise self._timeout(deadline) from None
        except BaseException:
            self._give_slot()
            raise
        future = loop.run_in_executor(self._executor, functools.partial(fn, *args))

        def finished(done: asyncio.Future) -> None:
            if not done.cancelled():
                done.exception()  # retrieved: a job that outlived its deadline may fail with nobody awaiting it
            self._give_slot()
            if hold is not None:
                hold.release()

        future.add_done_callback(finished)
        remaining = None if deadline is None else max(0.0, deadline - (loop.time() - start))
        try:
            return await asyncio.wait_for(asyncio.shield(future), remaining)
        except TimeoutError:
            if future.done() and future.exception() is not None:  # the job's own TimeoutError
                raise
            raise self._timeout(deadline) from None

    async def _take_slot(self, wait: float) -> None:
        if self._slots.locked() and wait <= 0:
            raise self._busy()
        try:
            await asyncio.wait_for(self._slots.acquire(), timeout=wait if wait > 0 else None)
        except TimeoutError:
            raise self._busy() from None
        self.inflight += 1

    def _give_slot(self) -> None:
        self.inflight -= 1
        self._slots.release()

    def _busy(self) -> ApiError:
        self.rejected += 1
        return ApiError(503, "busy", f"all {self.max_inflight} frame slots are taken; retry later",
                        retry_after=self.retry_after_s)

    def _timeout(self, deadline: float | None) -> ApiError:
        """504 timeout (counted per pipeline in /metrics as a frame error with code `timeout`)."""
        return ApiError(504, "timeout", f"the frame was not done within {deadline:g} s (MCDENOISE_FRAME_TIMEOUT_S); "
                                        "its work runs on to its end in the background")

    def shutdown(self) -> None:
        with contextlib.suppress(RuntimeError):
            self._executor.shutdown(wait=False, cancel_futures=True)
