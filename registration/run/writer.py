"""Writing a result folder frame by frame and atomically, under its lock, resumable."""

from __future__ import annotations

import hashlib
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from registration.errors import ResumeMismatch
from registration.io import (
    encode_npz,
    file_sha256,
    read_image,
    write_bytes_atomic,
    write_image_atomic,
    write_json_atomic,
)

try:
    import fcntl
except ImportError:  # not POSIX: no lock (documented in README "Reliability")
    fcntl = None
from registration.run.identity import _resume_problem
from registration.run.records import (
    MID_BASE,
    MID_BASE_VALID,
    RESULT_JSON,
    FrameRecord,
    _read_meta,
    frame_record_path,
    verify_record,
)
from registration.run.result_folder import ResultLock, check_out_dir, remove_result

log = logging.getLogger(__name__)


class ResultWriter:
    """Writes a result folder frame by frame, atomically, holding its lock.

    Use::

        with ResultWriter.create(out_dir, meta, frames=frames, resume=..., force=...) as w:
            if not w.done(k):
                w.write_frame(k, record, arrays)

    ``meta`` is :func:`make_metadata`'s. Every file is written to a temporary name and moved
    into place; a frame's arrays before its record, so a record means a complete frame.
    """

    def __init__(self, out_dir: Path, lock: ResultLock, frames=None) -> None:
        self.out_dir = out_dir
        self._lock = lock
        self._frames = frames
        meta = _read_meta(out_dir)
        self.n_frames = int(meta["n_frames"])
        self._status = [verify_record(out_dir, k).status for k in range(self.n_frames)]

    @classmethod
    def create(
        cls,
        out_dir: str | Path,
        meta: dict,
        *,
        frames=None,
        resume: bool = False,
        force: bool = False,
    ) -> ResultWriter:
        """Open ``out_dir`` for writing and take its lock.

        * a missing or empty folder: a new result (``result.json`` = ``meta``);
        * a result folder: ``resume`` continues it if it was made from the same inputs and
          configuration; ``force`` deletes it (:func:`remove_result`) and starts over;
        * anything else (a file, a folder holding other files): refused.

        Raises:
            ValueError: one line naming the folder and what to do (another process writes it:
                :class:`ResultBusy`; it holds another run; it is not a result folder).
        """
        out_dir = Path(out_dir)
        check_out_dir(out_dir, resume=resume, force=force)  # before anything is written
        out_dir.mkdir(parents=True, exist_ok=True)
        lock = ResultLock(out_dir).acquire()
        try:
            state = check_out_dir(out_dir, resume=resume, force=force)  # now no one else writes
            if state in ("result", "damaged") and force:
                log.info("starting over: removing the result in %s", out_dir)
                remove_result(out_dir)
                state = "empty"
            if state == "result":
                problem, key = _resume_problem(out_dir, _read_meta(out_dir), meta, frames)
                if problem:
                    raise ResumeMismatch(out_dir, problem, key)
            else:
                (out_dir / "frames").mkdir(exist_ok=True)
                write_json_atomic(out_dir / RESULT_JSON, meta)
            return cls(out_dir, lock, frames)
        except BaseException:
            lock.release()
            raise

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Release the lock (the folder stays as written)."""
        self._lock.release()

    # -- frames ---------------------------------------------------------------------------
    def done(self, k: int) -> bool:
        """Frame ``k`` has a complete record ("ok" or "failed"); pending and damaged frames
        are (re)done."""
        return self._status[k] in ("ok", "failed")

    def is_damaged(self, k: int) -> bool:
        return self._status[k] == "damaged"

    def write_frame(
        self,
        k: int,
        record: FrameRecord,
        arrays: dict[str, NDArray] | None = None,
        *,
        keep_input_hash: bool = False,
    ) -> None:
        """Write frame ``k``'s arrays (if any), then its record, each atomically.
        ``keep_input_hash``: the record already holds its input's hash (a registered frame
        rewritten by the sequence adjustment): it stays, rather than hashing the input again
        (0.007 s of CPU per 2560x1920 PNG)."""
        npz_bytes = npz_sha256 = input_sha256 = None
        if arrays:
            data = encode_npz(**arrays)
            write_bytes_atomic(frame_record_path(self.out_dir, k, ".npz"), data)
            npz_bytes, npz_sha256 = len(data), hashlib.sha256(data).hexdigest()
        path = self._frames.path(k) if hasattr(self._frames, "path") else None
        if keep_input_hash:
            input_sha256, path = record.input_sha256, None
        if path is not None:
            try:
                input_sha256 = file_sha256(path)
            except OSError:
                pass
        record = replace(
            record,
            k=int(k),
            npz_bytes=npz_bytes,
            npz_sha256=npz_sha256,
            input_sha256=input_sha256,
        )
        write_json_atomic(frame_record_path(self.out_dir, k, ".json"), record.to_json())
        self._status[k] = record.status

    def write_record(self, k: int, record: FrameRecord) -> None:
        """Rewrite frame ``k``'s record, its arrays file as it is (a record written before
        records held their arrays' size gets it now, so that the arrays stay its own)."""
        npz = frame_record_path(self.out_dir, k, ".npz")
        if record.legacy_arrays and npz.is_file():
            record = replace(record, npz_bytes=npz.stat().st_size, npz_sha256=file_sha256(npz))
        write_json_atomic(
            frame_record_path(self.out_dir, k, ".json"), replace(record, k=int(k)).to_json()
        )
        self._status[k] = record.status

    # -- the mid base image -----------------------------------------------------------------
    def write_mid_base(self, mid: NDArray, valid: NDArray[np.bool_]) -> None:
        write_image_atomic(self.out_dir / MID_BASE, mid)
        write_image_atomic(self.out_dir / MID_BASE_VALID, valid.astype(np.uint8) * 255)

    def read_mid_base(self) -> tuple[NDArray, NDArray[np.bool_]] | None:
        """``(mid, valid)`` as written, or None when either file is missing or unreadable."""
        try:
            mid = read_image(self.out_dir / MID_BASE)
            valid = read_image(self.out_dir / MID_BASE_VALID, grey=True) > 127
        except (OSError, ValueError):
            return None
        return mid, valid
