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


class JobRunner:
    """Runs one long job at a time on its own thread, with a cancel event."""

    def __init__(self, on_error: Callable[[str, BaseException], None] | None = None) -> None:
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self.cancel = threading.Event()
        self.name = ""
        self._on_error = on_error

    @property
    def busy(self) -> bool:
        with self._lock:
            return self._thread is not None and self._thread.is_alive()

    def start(self, name: str, fn: Callable[[threading.Event], None]) -> bool:
        """Start ``fn(cancel_event)`` unless a job is running; returns whether it started."""
        with self._lock:
            if self._thread is not None and self._thread.is_alive():
                return False
            self.cancel = threading.Event()
            self.name = name
            cancel = self.cancel

            def run() -> None:
                try:
                    fn(cancel)
                except Exception as exc:
                    log.exception("job %s failed", name)
                    if self._on_error is not None:
                        self._on_error(name, exc)

            self._thread = threading.Thread(target=run, name=f"job-{name}", daemon=True)
            self._thread.start()
            return True

    def request_cancel(self) -> None:
        self.cancel.set()

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the running job; True when none is running afterwards."""
        t = self._thread
        if t is not None:
            t.join(timeout)
        return not self.busy
