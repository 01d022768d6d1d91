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


def input_locations(
    frames_source: str | None, base_path: str | None
) -> tuple[list[Path], list[Path]]:
    """``(folders, files)`` holding a run's inputs: the frames' folder (a folder of images, or
    the folder of a glob pattern's images), the video file and the base map file."""
    folders: list[Path] = []
    files: list[Path] = []
    if frames_source:
        p = Path(frames_source)
        if p.is_dir():
            folders.append(p)
        elif p.is_file():
            files.append(p)
        elif any(ch in str(frames_source) for ch in "*?["):
            folders.append(p.parent)
    if base_path:
        files.append(Path(base_path))
    return folders, files


def check_not_an_input(
    path: str | os.PathLike, folders: list[Path], files: list[Path], what: str
) -> None:
    """ValueError (one line) when ``path`` is one of ``files`` or lies in one of ``folders``
    (nothing is ever written into an input folder or onto an input file)."""
    p = Path(path).resolve()
    for f in files:
        if p == Path(f).resolve():
            raise ValueError(f"{what} {path} is an input of the run; give another one")
    for d in folders:
        d = Path(d).resolve()
        if p == d or d in p.parents:
            raise ValueError(
                f"{what} {path} is inside {d}, which holds the run's inputs or records; give "
                "another one"
            )
