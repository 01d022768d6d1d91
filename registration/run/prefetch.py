"""Keeping both cores busy on a sequence: frames decoded ahead of the registration, and the
local stages of frames run while the next frames' global stages run.

Decoding a 2560x1920 frame (PNG: ~0.1 s of CPU; a video frame, sequentially: ~0.03 s) and
the local stage (~0.05-0.2 s: with the default preset it only turns the global stage's flow into
a field) are both mostly C code that releases the GIL, so background threads run them on the
second core while the main thread registers. The global stages form a chain (each frame starts
from its predecessor's model); the local stages do not, so two of them may run at once, and
whichever core is free takes the next piece of work:

* :class:`FramesAhead` returns exactly the frames the wrapped source returns (it only decodes
  them earlier, in the order the run will ask for them);
* :class:`LocalAhead` runs :func:`registration.local.refine.frame_field` on inputs that no later step
  modifies (the frame, its final global model and flow, and the mid base image's flow
  reference).

Exact: the overlapped run gives the serial run's result to the bit. (Before the project's own
Levenberg-Marquardt replaced MINPACK's, whose last bits depend on memory alignment, it did not,
and REQCON amplified the difference to up to 2 px at a later frame's corner.) The pipeline uses
it for runs in one process (``register_sequence(overlap=None)``), not on Dask workers.

Everything here is plumbing for :func:`registration.run.intra_frames.run_chunk`.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor

from numpy.typing import NDArray


class FramesAhead:
    """A frame source that decodes the frames of ``order`` ahead, in a background thread.

    Behaves like the wrapped :class:`registration.io.frames.FrameSource` (``len``, ``size``,
    ``get``, ``identity``, every other attribute): ``get(k)`` returns the frame decoded ahead
    when ``k`` is the next one of ``order`` (or re-raises its read error, exactly as
    ``frames.get(k)`` would), and reads directly otherwise (a resumed run's earlier frames,
    the previous frame of a failed one). At most ``depth`` decoded frames wait in memory.

    Args:
        frames: the source.
        order: the frame indices in the order the run will ask for them.
        depth: how many frames may be decoded ahead (2 keeps one ready while the next decodes).
        skip: called with ``k`` before decoding it; True = the run will not ask for frame ``k``
            (e.g. already done when resuming), so it is not decoded.
    """

    def __init__(
        self,
        frames,
        order: Iterable[int],
        depth: int = 2,
        skip: Callable[[int], bool] | None = None,
    ) -> None:
        if depth < 1:
            raise ValueError(f"FramesAhead depth must be >= 1, got {depth}")
        self._frames = frames
        self._order = [int(k) for k in order if not (skip and skip(int(k)))]
        self._pos = {k: i for i, k in enumerate(self._order)}
        self._depth = depth
        self._ready: OrderedDict[int, Future] = OrderedDict()
        self._next = 0  # index into _order of the next frame to submit
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="frames-ahead")
        self._lock = threading.Lock()
        self._fill()

    def __getattr__(self, name: str):
        return getattr(self._frames, name)

    def __len__(self) -> int:
        return len(self._frames)

    def _read(self, k: int):
        try:
            return self._frames.get(k), None
        except Exception as exc:  # handed to the caller of get(k), unchanged
            return None, exc

    def _fill(self) -> None:
        while len(self._ready) < self._depth and self._next < len(self._order):
            k = self._order[self._next]
            self._next += 1
            self._ready[k] = self._pool.submit(self._read, k)

    def get(self, k: int) -> NDArray:
        """Frame ``k`` (see the class doc)."""
        with self._lock:
            future = self._ready.pop(k, None)
            if future is not None:
                # Frames before k in the order that the run did not ask for: dropped.
                pos = self._pos[k]
                for j in [j for j in self._ready if self._pos[j] < pos]:
                    self._ready.pop(j).cancel()
                self._fill()
        if future is None:
            return self._frames.get(k)
        frame, exc = future.result()
        if exc is not None:
            raise exc
        return frame

    def close(self) -> None:
        """Stop decoding ahead (frames already submitted finish; nothing new starts)."""
        with self._lock:
            self._next = len(self._order)
            for f in self._ready.values():
                f.cancel()
            self._ready.clear()
        self._pool.shutdown(wait=True)

    def __enter__(self) -> FramesAhead:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class LocalAhead:
    """Runs a function (the local stage of a frame) in up to ``workers`` background threads,
    and hands the results back by key.

    ``submit(key, fn, *args)`` starts ``fn(*args)``; ``result(key)`` waits for it. With
    ``enabled=False`` the call runs at once in the caller's thread (same results, for runs that
    must not start threads). Exceptions are re-raised by ``result``.
    """

    def __init__(self, enabled: bool = True, workers: int = 1) -> None:
        if workers < 1:
            raise ValueError(f"LocalAhead workers must be >= 1, got {workers}")
        pool = ThreadPoolExecutor(workers, thread_name_prefix="local-ahead") if enabled else None
        self._pool = pool
        self._futures: dict = {}

    def submit(self, key, fn: Callable, *args, **kwargs) -> None:
        if self._pool is None:
            f: Future = Future()
            try:
                f.set_result(fn(*args, **kwargs))
            except Exception as exc:  # re-raised by result()
                f.set_exception(exc)
        else:
            f = self._pool.submit(fn, *args, **kwargs)
        self._futures[key] = f

    def pending(self) -> list:
        """Keys submitted and not yet collected, in submission order."""
        return list(self._futures)

    def done(self, key) -> bool:
        """Whether the call of ``key`` has finished (``result`` will not wait)."""
        return self._futures[key].done()

    def result(self, key):
        return self._futures.pop(key).result()

    def close(self) -> None:
        """Wait for the calls running; calls not started yet (a run stopped early: nobody will
        ask for their results) are dropped."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> LocalAhead:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
