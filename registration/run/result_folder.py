"""A result folder on disk: its lock, what it holds, whether a run may write into it, and removing
exactly its own files.
"""

from __future__ import annotations

import json
import os
import re
import socket
from pathlib import Path

try:
    import fcntl
except ImportError:  # not POSIX: no lock (documented in README "Reliability")
    fcntl = None
from registration.errors import (
    ForeignFolder,
    NotAFolder,
    ResultBusy,
    ResultDamaged,
    ResultExists,
)
from registration.io import temp_target
from registration.run.records import (
    MAP_POINTS_JSON,
    MID_BASE,
    MID_BASE_VALID,
    RESULT_JSON,
    _read_meta,
)

LOCK_NAME = ".lock"
# What a result folder may hold; only these are ever deleted (``--force``).
_OWN = {
    ".": re.compile(
        "^("
        + "|".join(map(re.escape, (RESULT_JSON, MID_BASE, MID_BASE_VALID, MAP_POINTS_JSON)))
        + ")$"
    ),
    "frames": re.compile(r"^\d{6}\.(json|npz)$"),
    "registered": re.compile(r"^registered\.mp4$"),
    "registered/frames": re.compile(r"^\d{6}\.png$"),
    "registered/overlay": re.compile(r"^\d{6}\.jpg$"),
    "registered/field": re.compile(r"^\d{6}_d[xy]\.png$"),
}


# --------------------------------------------------------------------------------------------
# The lock


class ResultLock:
    """An exclusive ``flock`` on ``OUT/.lock``, held while a process writes the folder. The
    kernel releases it when the process dies, so a killed run never blocks the next one; the
    file keeps the holder's pid and host for the message."""

    def __init__(self, out_dir: Path) -> None:
        self.path = out_dir / LOCK_NAME
        self.fd: int | None = None

    def acquire(self) -> ResultLock:
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 4096).decode("utf-8", "replace")
                os.close(fd)
                try:
                    info = json.loads(holder)
                    who = f"pid {info['pid']} on {info['host']}"
                except (ValueError, KeyError, TypeError):
                    who = "pid unknown"
                raise ResultBusy(self.path.parent, who) from None
        os.ftruncate(fd, 0)
        os.write(fd, json.dumps({"pid": os.getpid(), "host": socket.gethostname()}).encode())
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)  # releases the flock
            self.fd = None


# --------------------------------------------------------------------------------------------
# The writer


def _own_entry(rel: str, name: str) -> bool:
    """Whether ``name`` in ``rel`` is one of the folder's own files, its lock or a temporary
    file of one of its own files (a user's ".notes.tmp" is not)."""
    pattern = _OWN.get(rel)
    return bool(name == LOCK_NAME or (pattern and pattern.match(name)) or _own_temp(rel, name))


def _own_temp(rel: str, name: str) -> bool:
    """Whether ``name`` in ``rel`` is a temporary file of one of the folder's own files."""
    target = temp_target(name)
    pattern = _OWN.get(rel)
    return bool(target and pattern and pattern.match(target))


def folder_state(out_dir: Path) -> str:
    """``"missing"``, ``"empty"``, ``"result"`` (result.json of this format), ``"damaged"``
    (only result entries but no readable result.json) or ``"foreign"`` (anything else).

    Raises:
        ValueError: ``out_dir`` exists and is not a folder.
    """
    if not out_dir.exists():
        return "missing"
    if not out_dir.is_dir():
        raise NotAFolder(out_dir)
    names = [n for n in os.listdir(out_dir) if n != LOCK_NAME and not _own_temp(".", n)]
    if not names:
        return "empty"
    try:
        _read_meta(out_dir)
        return "result"
    except (OSError, ValueError):
        pass
    known = {RESULT_JSON, MID_BASE, MID_BASE_VALID, "frames", "registered"}
    frames = out_dir / "frames"
    records = os.listdir(frames) if frames.is_dir() and not frames.is_symlink() else None
    if names == ["frames"] and records == []:
        return "empty"  # a run killed between creating frames/ and writing result.json
    only_records = records is not None and all(_own_entry("frames", n) for n in records)
    return "damaged" if set(names) <= known and only_records else "foreign"


def check_out_dir(out_dir: Path, *, resume: bool = False, force: bool = False) -> str:
    """:func:`folder_state` of ``out_dir``; ValueError (one line, saying what to do) for what
    :meth:`ResultWriter.create` refuses whatever the inputs: a file, a folder holding other
    files, a result without ``resume`` or ``force``, a damaged result without ``force``."""
    if resume and force:
        raise ValueError("resuming and starting over exclude each other")
    state = folder_state(out_dir)
    if state == "foreign":
        raise ForeignFolder(out_dir, _foreign_example(out_dir))
    if state == "damaged" and not force:
        raise ResultDamaged(out_dir, resuming=resume)
    if state == "result" and not (resume or force):
        raise ResultExists(out_dir)
    return state


def remove_result(out_dir: Path) -> None:
    """Delete what an aerialreg result folder holds: only its own files (records, arrays, mid
    base, rendered frames), ``result.json`` last so that an interruption leaves a result that
    is still recognised as one. Other files stay."""
    for rel in ("frames", "registered/frames", "registered/overlay", "registered/field"):
        sub = out_dir / rel
        if sub.is_dir() and not _has_symlink(out_dir, rel):
            for entry in os.scandir(sub):
                if entry.is_file(follow_symlinks=False) and _own_entry(rel, entry.name):
                    os.unlink(entry.path)
            _rmdir_if_empty(sub)
    for rel in ("registered", "."):
        sub = out_dir / rel
        if sub.is_dir() and (rel == "." or not _has_symlink(out_dir, rel)):
            for entry in os.scandir(sub):
                if (
                    entry.is_file(follow_symlinks=False)
                    and _own_entry(rel, entry.name)
                    and entry.name not in (RESULT_JSON, LOCK_NAME)
                ):
                    os.unlink(entry.path)
    _rmdir_if_empty(out_dir / "registered")
    if (out_dir / RESULT_JSON).is_file():
        os.unlink(out_dir / RESULT_JSON)


def _has_symlink(root: Path, rel: str) -> bool:
    parts = Path(rel).parts
    return any((root.joinpath(*parts[: i + 1])).is_symlink() for i in range(len(parts)))


def _rmdir_if_empty(path: Path) -> None:
    try:
        path.rmdir()
    except OSError:
        pass


def _foreign_example(out_dir: Path) -> str:
    """A name in ``out_dir`` that is not a result folder's (for the message)."""
    names = sorted(n for n in os.listdir(out_dir) if not _own_entry(".", n))
    return (names or sorted(os.listdir(out_dir)))[0]
