"""Text inputs with a size limit, and the identity of input files (size, mtime, sampled and full
SHA-256).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

MAX_TEXT_FILE_BYTES = 64 << 20  # JSON and CSV inputs (LINES.json, POINTS.csv, result records)


def read_text_file(
    path: str | os.PathLike, what: str, *, max_bytes: int = MAX_TEXT_FILE_BYTES
) -> str:
    """A UTF-8 text file (JSON, CSV) of at most ``max_bytes``.

    Raises:
        FileNotFoundError: ``{what} not found: {path}``.
        ValueError: one line naming the file: a directory, too large, or not UTF-8.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{what} not found: {p}")
    if p.is_dir():
        raise ValueError(f"{what} {p} is a directory, not a file")
    n = p.stat().st_size
    if n > max_bytes:
        raise ValueError(
            f"{what} {p} has {n / 2**20:.1f} MiB, over the {max_bytes >> 20} MiB limit"
        )
    data = p.read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(
            f"{what} {p} is not UTF-8 text ({exc.reason} at byte {exc.start})"
        ) from None


SAMPLE_BYTES = 64 << 10


def file_fingerprint(path: str | os.PathLike) -> dict:
    """A cheap identity of a file: ``size``, ``mtime_ns`` and ``sample_sha256``, the SHA-256 of
    its first and last ``SAMPLE_BYTES`` (the whole file when it is at most twice that)."""
    p = Path(path)
    st = p.stat()
    h = hashlib.sha256()
    with open(p, "rb") as f:
        if st.st_size <= 2 * SAMPLE_BYTES:
            h.update(f.read())
        else:
            h.update(f.read(SAMPLE_BYTES))
            f.seek(-SAMPLE_BYTES, os.SEEK_END)
            h.update(f.read(SAMPLE_BYTES))
    return {
        "size": int(st.st_size),
        "mtime_ns": int(st.st_mtime_ns),
        "sample_sha256": h.hexdigest(),
    }


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a whole file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()
