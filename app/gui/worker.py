"""Background execution for the app: GUI callbacks post requests here and return at once.

viser runs plain ``def`` callbacks concurrently in a thread pool, so a slider dragged at 20 Hz
would otherwise start many overlapping renders. :class:`LatestWorker` runs every request on one
thread, and a request replaces any not-yet-started request with the same key (latest wins): the
final value is always rendered, stale intermediate ones are dropped.

Long jobs (building the demo, a sequence registration) run on :class:`JobRunner`'s own thread, one
at a time, with a cancel event, so interactive previews stay responsive while they run.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable

log = logging.getLogger(__name__)


class LatestWorker:
    """One thread; ``submit(key, fn)`` replaces a pending request with the same key."""

    def __init__(self, on_error: Callable[[str, BaseException], None] | None = None) -> None:
        self._cv = threading.Condition()
        self._pending: OrderedDict[str, Callable[[], None]] = OrderedDict()
        self._busy = False
        self._stop = False
        self._on_error = on_error
        self._thread = threading.Thread(target=self._loop, name="app-worker", daemon=True)
        self._thread.start()

    def submit(self, key: str, fn: Callable[[], None]) -> None:
        """Queue ``fn`` under ``key``; a pending request with that key is dropped."""
        with self._cv:
            self._pending.pop(key, None)
            self._pending[key] = fn
            self._cv.notify_all()

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Block until nothing is pending or running (for tests and the benchmark)."""
        with self._cv:
            return self._cv.wait_for(lambda: not self._pending and not self._busy, timeout)

    def stop(self) -> None:
        """Drop pending requests and end the thread after the running one."""
        with self._cv:
            self._stop = True
            self._pending.clear()
            self._cv.notify_all()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def _loop(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._pending or self._stop)
                if self._stop:
                    return
                key, fn = self._pending.popitem(last=False)
                self._busy = True
            try:
                fn()
            except (
                Exception
            ) as exc:  # report and keep serving: one bad request must not kill the app
                log.exception("request %s failed", key)
                if self._on_error is not None:
                    try:
                        self._on_error(key, exc)
                    except Exception:
                        log.exception("error handler failed")
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()


class Job:
    """A long job's handle, passed to the job's function: ``job.cancel`` (an Event to check) and
    ``job(done, total, note)`` to report progress; the runner's listener shows it with the time
    left, estimated from the rate since the first report (a resumed run starts part-done)."""

    def __init__(self, name: str, on_progress: Callable[[Job], None] | None = None) -> None:
        self.name = name
        self.cancel = threading.Event()
        self.start = time.monotonic()
        self.done = 0
        self.total: int | None = None
        self.note = ""
        self._first: tuple[float, int] | None = None
        self._on_progress = on_progress

    def __call__(self, done: int, total: int | None = None, note: str = "") -> None:
        self.done, self.total, self.note = int(done), total, note
        if self._first is None:
            self._first = (time.monotonic(), self.done)
        if self._on_progress is not None:
            self._on_progress(self)

    @property
    def elapsed_s(self) -> float:
        return time.monotonic() - self.start

    @property
    def fraction(self) -> float | None:
        if not self.total:
            return None
        return min(max(self.done / self.total, 0.0), 1.0)

    @property
    def eta_s(self) -> float | None:
        """Seconds left at the rate since the first report; None before any step finished."""
        if not self.total or self._first is None:
            return None
        t0, d0 = self._first
        steps = self.done - d0
        if steps <= 0:
            return None
        return (time.monotonic() - t0) / steps * (self.total - self.done)

    def describe(self) -> str:
        """E.g. ``register: 3/10 frames, 12 s, about 25 s left``."""
        text = self.name
        if self.total:
            text += f": {self.done}/{self.total}" + (f" {self.note}" if self.note else "")
        elif self.note:
            text += f": {self.note}"
        text += f", {_duration(self.elapsed_s)}"
        eta = self.eta_s
        if eta is not None:
            text += f", about {_duration(eta)} left"
        return text


def _duration(s: float) -> str:
    if s < 60:
        return f"{s:.0f} s"
    if s < 3600:
        return f"{int(s // 60)} min {int(s % 60):02d} s"
    return f"{int(s // 3600)} h {int(s % 3600 // 60):02d} min"


class JobRunner:
    """Runs one long job at a time on its own thread.

    ``start(name, fn)`` runs ``fn(job)`` (a :class:`Job`); with ``queue=True`` a request made
    while a job runs waits and runs after it (only the newest such request is kept).
    """

    def __init__(
        self,
        on_error: Callable[[str, BaseException], None] | None = None,
        on_progress: Callable[[Job], None] | None = None,
        on_finish: Callable[[Job], None] | None = None,
        on_start: Callable[[Job], None] | None = None,
    ) -> None:
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._queued: tuple[str, Callable[[Job], None]] | None = None
        self.job: Job | None = None
        self._on_error = on_error
        self._on_progress = on_progress
        self._on_finish = on_finish
        self._on_start = on_start

    @property
    def busy(self) -> bool:
        with self._lock:
            return (
                self._thread is not None and self._thread.is_alive()
            ) or self._queued is not None

    @property
    def name(self) -> str:
        job = self.job
        return job.name if job is not None else ""

    @property
    def cancel(self) -> threading.Event:
        job = self.job
        return job.cancel if job is not None else threading.Event()

    def start(self, name: str, fn: Callable[[Job], None], *, queue: bool = False) -> bool:
        """Start ``fn(job)`` unless a job is running; returns whether it started (or, with
        ``queue``, was queued behind the running job)."""
        with self._lock:
            if self._thread is not None and self._thread.is_alive():
                if queue:
                    self._queued = (name, fn)
                    return True
                return False
            self._launch(name, fn)
            return True

    def _launch(self, name: str, fn: Callable[[Job], None]) -> None:
        job = Job(name, self._on_progress)
        self.job = job
        if self._on_start is not None:
            # Before the thread starts, so a job that ends at once cannot finish before it.
            self._on_start(job)

        def run() -> None:
            try:
                fn(job)
            except Exception as exc:
                log.exception("job %s failed", name)
                if self._on_error is not None:
                    self._on_error(name, exc)
            finally:
                if self._on_finish is not None:
                    try:
                        self._on_finish(job)
                    except Exception:
                        log.exception("job finish handler failed")
                with self._lock:
                    nxt, self._queued = self._queued, None
                    if nxt is not None:
                        self._launch(*nxt)

        self._thread = threading.Thread(target=run, name=f"job-{name}", daemon=True)
        self._thread.start()

    def request_cancel(self) -> None:
        with self._lock:
            self._queued = None
        job = self.job
        if job is not None:
            job.cancel.set()

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the running job and any queued after it; True when none is left."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            with self._lock:
                t = self._thread
            if t is not None:
                t.join(None if deadline is None else max(deadline - time.monotonic(), 0))
            with self._lock:
                if self._thread is t and (t is None or not t.is_alive()):
                    return self._queued is None
            if deadline is not None and time.monotonic() >= deadline:
                return not self.busy
