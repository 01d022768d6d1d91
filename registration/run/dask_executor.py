"""Scale-out on Dask (``aerialreg register --workers N`` / ``--scheduler ADDRESS``).

The chunks of a run (:func:`registration.run.chunks.chunk_plan`) are independent, so each runs as
one task on a ``dask.distributed`` cluster: a :class:`distributed.LocalCluster` of N
single-threaded worker processes on this machine, or an existing cluster reached through its
scheduler. The process that calls :func:`registration.run.pipeline.register_sequence` (the driver)
registers the reference frame, sends every worker the run's shared context once (base map, mid
base image, configuration, the frames' paths), and writes each frame's record and arrays
through its :class:`registration.run.writer.ResultWriter` (lock, atomic files, identity checks) as
soon as a worker has the frame: workers stream frames back through a Dask queue, frame by
frame. Workers read the frames themselves from the paths the driver gives, so on a real cluster
the frames must be on storage every worker sees at the same path (the base map is sent).

The result is the serial run's with the same ``chunk_frames``: each chunk computes exactly what
it computes serially (seeded randomness per frame, quantized models), wherever it runs. A chunk
whose worker dies is run again by Dask; frames the driver already wrote are not written twice.

Requires ``dask[distributed]`` (``pip install 'aerialreg[dask]'``); imported only when used.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import functools
import hashlib
import logging
import pickle
import socket
import threading
import time
import uuid
from collections.abc import Iterator, Sequence
from pathlib import Path

from registration.run.chunks import ChunkContext, ChunkJob, FrameOutput
from registration.run.intra_frames import run_chunk

log = logging.getLogger(__name__)


# Frames per chunk when a run is distributed and no size is given (``--chunk-frames``). A
# chunk's first frame has no predecessor and costs up to one inter-sensor coarse step (a few
# seconds, at any heading) when it lies off the mid base image; 100 frames (20 s of the
# paper's 5 fps video, minutes of work at 2560x1920) make that a small share, and a 5-minute
# flight (1500 frames) still gives 15 chunks to spread over workers.
DEFAULT_CHUNK_FRAMES = 100
# How long the driver waits for a frame before it looks at the chunks' state (s).
POLL_S = 0.25
# Environment of local worker processes: Dask's default without MALLOC_TRIM_THRESHOLD_=65536,
# which makes glibc hand freed memory back at once, so every large array of a frame (templates,
# flow, remaps) faults its pages in again: measured 1.3-2x slower fine and local steps at
# 1280x960. One BLAS thread per worker (Dask's default): workers already fill the cores.
WORKER_ENVIRON = {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1}
# Connecting to a scheduler that does not answer fails after this long (s).
CONNECT_TIMEOUT_S = 20


class DaskUnavailable(ImportError):
    """dask.distributed is not installed."""


def require_distributed():
    """The ``distributed`` module; :class:`DaskUnavailable` (one line) without it."""
    try:
        import distributed
    except ImportError:
        raise DaskUnavailable(
            "running on Dask needs dask.distributed: pip install 'aerialreg[dask]' "
            "(or pip install 'dask[distributed]')"
        ) from None
    return distributed


@contextlib.contextmanager
def open_client(workers: int | None = None, scheduler: str | None = None) -> Iterator:
    """A ``distributed.Client``: on a new local cluster of ``workers`` single-threaded worker
    processes (closed on exit), or connected to the scheduler at ``scheduler`` (e.g.
    ``tcp://10.0.0.5:8786``; the cluster stays up). The workers are checked to run this
    process's aerialreg and have imported it (:func:`check_workers`).

    Raises:
        DaskUnavailable: dask.distributed is not installed.
        ValueError: neither or both given, ``workers`` < 1, the scheduler does not answer, or a
            worker runs another aerialreg or none.
    """
    if (workers is None) == (scheduler is None):
        raise ValueError("give either a number of local workers or a scheduler address")
    distributed = require_distributed()
    if scheduler is not None:
        try:
            client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError) as exc:
            raise ValueError(
                f"cannot connect to the Dask scheduler at {scheduler}: {_first_line(exc)}"
            ) from None
        # Not ``with client``: that makes it the current client of this thread's context, which
        # open_executor enters in another thread than it leaves.
        try:
            check_workers(client)
            yield client
        finally:
            client.close()
        return
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"the number of workers must be 1 or more, got {workers!r}")
    import dask

    # One thread per worker: a chunk's frames are sequential, and OpenCV already uses the cores
    # inside a frame. On this machine only (127.0.0.1), without the dashboard; the scheduler's
    # small HTTP server (health, metrics) takes a free port rather than 8787.
    with dask.config.set({"distributed.nanny.pre-spawn-environ": WORKER_ENVIRON}):
        cluster = distributed.LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
            silence_logs=logging.ERROR,
        )
    try:
        client = distributed.Client(cluster)
        try:
            check_workers(client)
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


@contextlib.contextmanager
def open_executor(workers: int | None = None, scheduler: str | None = None) -> Iterator:
    """A :class:`DaskExecutor` on :func:`open_client`'s client. A local cluster starts in the
    background, so that it comes up while this process registers the reference frame (its
    errors are raised when the chunks start); a scheduler is connected to at once, so that an
    unreachable one is refused before any work."""
    if scheduler is not None or workers is None:
        with open_client(workers, scheduler) as client:
            yield DaskExecutor(client)
        return
    require_distributed()
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"the number of workers must be 1 or more, got {workers!r}")
    stack = contextlib.ExitStack()
    pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="aerialreg-dask")
    starting = pool.submit(lambda: stack.enter_context(open_client(workers)))
    try:
        yield DaskExecutor(starting.result)
    finally:
        pool.shutdown(wait=True)  # a start still under way ends before the cluster closes
        stack.close()


def check_workers(client) -> None:
    """Make every worker import aerialreg now (not in its first chunk) and check that it runs
    this process's code (:func:`code_fingerprint`); ValueError (one line) otherwise. Workers
    that join later are checked by each chunk task."""
    try:
        codes = client.run(code_fingerprint)
    except ModuleNotFoundError as exc:
        raise ValueError(
            f"a Dask worker cannot import aerialreg ({_first_line(exc)}): install it, the "
            "same version, on every worker"
        ) from None
    for address, code in codes.items():
        if code != code_fingerprint():
            raise ValueError(
                f"the Dask worker at {address} runs another version of aerialreg than this "
                "process (its registration package differs): install the same version on "
                "every worker"
            )
    if not codes:
        log.warning("the Dask scheduler has no workers yet: the chunks wait for some to join")


class DaskExecutor:
    """Runs chunk jobs on a ``distributed.Client`` (see the module docstring); a
    :class:`registration.run.chunks.ChunkExecutor`.

    Frames arrive as their workers finish them, in any order. Closing the iterator (or setting
    ``cancel``) tells the workers to stop after the frame in progress and cancels the chunks not
    started.
    """

    def __init__(self, client, *, poll_s: float = POLL_S) -> None:
        """``client``: a ``distributed.Client``, or a callable that returns one (waited for
        when the chunks start)."""
        self._client = client
        self.poll_s = poll_s

    @property
    def client(self):
        return self._client() if callable(self._client) else self._client

    def run(
        self,
        context: ChunkContext,
        jobs: Sequence[ChunkJob],
        cancel: threading.Event | None = None,
    ) -> Iterator[FrameOutput]:
        distributed = require_distributed()
        client = self.client
        run_id = uuid.uuid4().hex[:12]
        context = dataclasses.replace(context, frames=context.frames.resolved())
        queue = distributed.Queue(f"aerialreg-frames-{run_id}", client=client)
        stop = distributed.Event(f"aerialreg-stop-{run_id}", client=client)
        shared = client.scatter(context, broadcast=True, hash=False)
        futures = {
            client.submit(
                _chunk_task, shared, job, queue.name, stop.name, code_fingerprint(),
                key=f"aerialreg-chunk-{job.chunk.index}-{run_id}", pure=False,
            ): job
            for job in jobs
        }  # fmt: skip
        pending = dict(futures)
        sent: dict[int, set[int]] = {}  # chunk index -> frames its finished task sent
        received: dict[int, set[int]] = {job.chunk.index: set() for job in jobs}
        try:
            while True:
                for item in self._take(queue):
                    chunk_index, k, record, arrays = pickle.loads(item)
                    received[chunk_index].add(k)
                    yield k, record, arrays
                if cancel is not None and cancel.is_set():
                    return
                for future in [f for f in pending if f.done()]:
                    job = pending.pop(future)
                    if future.status != "finished":
                        # Frames already queued are written before the error is raised.
                        for item in self._take(queue, wait=False):
                            chunk_index, k, record, arrays = pickle.loads(item)
                            yield k, record, arrays
                        _raise_worker_error(future, job)
                    sent[job.chunk.index] = set(future.result())
                if not pending and all(sent[c] <= received[c] for c in sent):
                    return
        finally:
            stop.set()
            client.cancel(list(futures))
            with contextlib.suppress(Exception):
                client.cancel(shared)
                queue.close()

    def _take(self, queue, *, wait: bool = True) -> list:
        """The frames waiting in the queue; when there is none, after ``poll_s`` (a blocking
        ``get`` with a timeout would log an error on the scheduler each time it expires)."""
        items = queue.get(batch=True)
        if not items and wait:
            time.sleep(self.poll_s)
            items = queue.get(batch=True)
        return items


@functools.cache
def code_fingerprint() -> str:
    """SHA-256 of the ``registration`` package's source files: workers must run the driver's
    code for the result to be the serial run's. Computing it imports the package's pipeline
    (what a chunk needs), so that a worker pays the imports once, up front."""
    import registration.run.pipeline  # noqa: F401

    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def _chunk_task(
    context: ChunkContext, job: ChunkJob, queue_name: str, stop_name: str, code: str
) -> list:
    """One chunk on a worker: each frame's output is queued for the driver as soon as it is
    computed. Returns the frames sent."""
    from distributed import Event, Queue

    if code != code_fingerprint():
        raise ValueError(
            f"the Dask worker on {socket.gethostname()} runs another version of aerialreg than "
            "this process (its registration package differs): install the same version on every "
            "worker"
        )
    check_frames(context, job)
    queue, stop = Queue(queue_name), Event(stop_name)
    sent = []
    for k, record, arrays in run_chunk(context, job):
        if stop.is_set():
            break
        queue.put(pickle.dumps((job.chunk.index, k, record, arrays), protocol=5))
        sent.append(k)
    return sent


def check_frames(context: ChunkContext, job: ChunkJob) -> None:
    """Raise ValueError (one line, naming this host and the file) when this process does not see
    the chunk's frames and the reference frame as the driver recorded them: missing (no shared
    storage) or of other content. Compares sizes and the SHA-256 of each file's first and last
    64 KB (a video: the whole file's fingerprint)."""
    from registration.io import file_fingerprint

    identity = context.frames_identity
    if not identity:
        return
    host = socket.gethostname()
    frames = context.frames
    if identity.get("kind") == "video":
        paths = [(None, frames.video_path, identity)]
    else:
        files = identity.get("files", [])
        ks = [context.reference_frame, *job.chunk.frames]  # done ones are read to replay them
        paths = [(k, frames.path(k), files[k]) for k in ks if k < len(files)]
    for k, path, want in paths:
        if "error" in want:  # unreadable on the driver too: the frame fails the same way
            continue
        try:
            have = file_fingerprint(path)
        except OSError as exc:
            raise ValueError(
                f"Dask worker on {host} cannot read {path} ({_first_line(exc)}): the frames "
                "must be on storage every worker sees at the same path"
            ) from None
        if have.get("size") != want.get("size") or have.get("sample_sha256") != want.get(
            "sample_sha256"
        ):
            which = f"frame {k} ({path})" if k is not None else str(path)
            raise ValueError(
                f"Dask worker on {host} sees another {which} than the driver: the frames must "
                "be the same files on every worker"
            )


def _raise_worker_error(future, job: ChunkJob) -> None:
    """Raise what made a chunk's task fail: the worker's exception (a worker that cannot import
    aerialreg as a one-line ValueError)."""
    try:
        future.result()
    except ModuleNotFoundError as exc:
        if (exc.name or "").split(".")[0] in ("registration", "app"):
            raise ValueError(
                f"a Dask worker cannot import aerialreg ({_first_line(exc)}): install it, the "
                "same version, on every worker"
            ) from None
        raise
    raise RuntimeError(f"chunk {job.chunk.index} ended as {future.status!r} on its Dask worker")


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
