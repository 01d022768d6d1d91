"""The order frames are registered in and the chunks of a sequence (beyond the paper's single
chain): processing order from the reference frame outwards, chunks of consecutive frames, and the
context every chunk shares.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from numpy.typing import NDArray

from registration.geometry import DisplacementField
from registration.global_registration import (
    CoarseBase,
    IntraConfig,
    JointBase,
    make_joint_base,
)
from registration.io import FrameSource
from registration.lens import Camera
from registration.matching import grey
from registration.run.anchoring import ANCHOR_STAGE
from registration.run.config import PipelineConfig
from registration.run.records import FrameRecord
from registration.run.result import RegistrationResult
from registration.run.writer import ResultWriter

# What a chunk gives for each frame: ``(k, record, arrays)``, as ResultWriter.write_frame takes.
FrameOutput = tuple[int, FrameRecord, "dict[str, NDArray] | None"]


def processing_order(n_frames: int, reference_frame: int) -> list[int]:
    """Reference first, then forwards, then backwards from the reference."""
    return [
        reference_frame,
        *range(reference_frame + 1, n_frames),
        *range(reference_frame - 1, -1, -1),
    ]


def previous_in_order(k: int, reference_frame: int) -> int:
    """The neighbour of ``k`` that is processed before it (nearer to the reference)."""
    return k - 1 if k > reference_frame else k + 1


@dataclass(frozen=True)
class Chunk:
    """Consecutive frames in processing order, registered together (``PipelineConfig
    .chunk_frames``).

    Attributes:
        index: the chunk's place in :func:`chunk_plan`.
        frames: the frames, in processing order.
        follows_reference: the first frame's predecessor is the reference frame; otherwise the
            first frame has no registered predecessor and is registered to the mid base image
            alone or, where that fails, to the base map (a chunk start, :func:`run_chunk`).
    """

    index: int
    frames: tuple[int, ...]
    follows_reference: bool


def chunk_plan(n_frames: int, reference_frame: int, chunk_frames: int) -> list[Chunk]:
    """The chunks of a sequence: the frames after the reference frame (forwards) and those
    before it (backwards from it), each split into runs of at most ``chunk_frames`` consecutive
    frames of (nearly) equal length, the longer ones first; ``chunk_frames`` 0 gives one chunk
    of every frame but the reference, in processing order (the paper's single chain)."""
    forwards = list(range(reference_frame + 1, n_frames))
    backwards = list(range(reference_frame - 1, -1, -1))
    if chunk_frames <= 0:
        rest = forwards + backwards
        return [Chunk(0, tuple(rest), True)] if rest else []
    chunks: list[Chunk] = []
    for run in (forwards, backwards):
        n_chunks = math.ceil(len(run) / chunk_frames)
        start = 0
        for i in range(n_chunks):
            size = len(run) // n_chunks + (i < len(run) % n_chunks)
            chunks.append(Chunk(len(chunks), tuple(run[start : start + size]), start == 0))
            start += size
    return chunks


@dataclass
class DoneFrame:
    """A frame of a chunk that a resumed run already has: what the chunk needs to carry on as
    the uninterrupted run did (its model for the next frame, an anchor's field to add it to the
    chunk's mid base image)."""

    ok: bool
    anchor: bool = False
    model: dict | None = None
    field: DisplacementField | None = None


@dataclass
class ChunkJob:
    """A chunk to register: its frames, less those in ``done`` (already written)."""

    chunk: Chunk
    done: dict[int, DoneFrame] = field(default_factory=dict)

    @property
    def todo(self) -> list[int]:
        return [k for k in self.chunk.frames if k not in self.done]


@dataclass
class ChunkContext:
    """What every chunk of a run shares (built once by the driver; pickled to Dask workers).

    Attributes:
        frames: the sequence (paths: a worker reads the frames itself).
        base: base map, BGR uint8 (Hb, Wb, 3); base_valid: (Hb, Wb) bool or None.
        camera: the frames' camera (Harris γ and frame size).
        config: the run's configuration.
        reference_frame: the reference frame's index; reference_model: its model as recorded.
        mid, mid_valid: the mid base image (the reference frame in base pixels) and its mask.
        frames_identity: the frames' identity as the driver recorded it (``result.json``
            ``inputs.frames``); a worker checks that it reads the same files.
        overlap: keep both cores busy within a chunk (frames decoded ahead, the local stage
            in a second thread; :func:`run_chunk`). Off by default: see ``register_sequence``.
    """

    frames: FrameSource
    base: NDArray
    base_valid: NDArray | None
    camera: Camera
    config: PipelineConfig
    reference_frame: int
    reference_model: dict
    mid: NDArray
    mid_valid: NDArray
    frames_identity: dict | None = None
    overlap: bool = False
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_cache"] = {}  # per process
        return state

    def coarse_base(self) -> CoarseBase:
        """The base map's coarse features, computed once per process (chunk starts)."""
        if "coarse_base" not in self._cache:
            self._cache["coarse_base"] = CoarseBase(self.base, self.config.coarse, self.base_valid)
        return self._cache["coarse_base"]

    def joint_base(self) -> JointBase:
        """A fresh joint base: the reference frame's mid base image, no anchors yet."""
        return _joint_base(self.mid.copy(), self.mid_valid.copy(), self.base, self.base_valid,
                           self.config.intra)  # fmt: skip


class ChunkExecutor(Protocol):
    """Runs chunk jobs and yields each frame's output as it is ready, in any order. Closing the
    iterator, or setting ``cancel``, stops the work still running."""

    def run(
        self,
        context: ChunkContext,
        jobs: Sequence[ChunkJob],
        cancel: threading.Event | None = None,
    ) -> Iterator[FrameOutput]: ...


def chunk_jobs(writer: ResultWriter, n_frames: int, ref: int, config) -> list[ChunkJob]:
    """The chunks of :func:`chunk_plan` that have frames left to do, each with what it needs of
    the frames already done (a resumed run)."""
    result = None
    jobs = []
    for chunk in chunk_plan(n_frames, ref, config.chunk_frames):
        done_ks = [k for k in chunk.frames if writer.done(k)]
        if len(done_ks) == len(chunk.frames):
            continue
        done = {}
        if done_ks:
            result = result or RegistrationResult(writer.out_dir)
            for k in done_ks:
                rec = result.records[k]
                anchor = rec.ok and rec.stage == ANCHOR_STAGE
                done[k] = DoneFrame(
                    rec.ok,
                    anchor,
                    rec.model if rec.ok else None,
                    result.field(k) if anchor else None,
                )
        jobs.append(ChunkJob(chunk, done))
    return jobs


def _joint_base(mid, valid, base, base_valid, intra: IntraConfig) -> JointBase:
    joint = make_joint_base(mid, valid)
    if intra.base_fallback:
        joint.base_grey = grey.to_grey(base)
        joint.base_valid = base_valid
    return joint
