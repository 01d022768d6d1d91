"""Writing a simulator output folder safely: nothing overwritten without ``force``, everything
rendered into a staging folder first, and ``truth.json`` written last.

A simulator output folder ``OUT`` holds the *owned* entries :data:`OWNED` (``frames/``,
``base.png``, ``truth.json``, ``sequence.mp4``). A run:

1. checks ``OUT`` (:func:`check_target`): missing or empty is fine; anything else needs
   ``force`` (a previous output and a foreign folder get different one-line messages);
2. renders into ``OUT/.simulate-<pid>-<token>/`` (:class:`Staging`), so a killed run leaves the
   previous contents of ``OUT`` untouched (and its own leftovers are removed by the next run);
3. commits (:meth:`Staging.commit`): removes the old ``truth.json`` *first*, swaps every owned
   entry in, writes the new ``truth.json`` *last*. A kill during the commit leaves no truth at all
   (``load_truth`` refuses the folder), never a truth beside frames of another run.

With ``force`` only the owned entries are replaced; other files in ``OUT`` are left alone (so a
mistyped ``OUT`` with ``force`` never loses anything the simulator did not write itself).
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import shutil
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.io import write_bytes_atomic

OWNED = ("frames", "base.png", "truth.json", "sequence.mp4", "vehicles.csv")
STAGING_PREFIX = ".simulate-"
TRUTH_NAME = "truth.json"


def encode_png(rgb: NDArray[np.uint8], name: str = "image") -> bytes:
    """PNG bytes of an RGB (or grey) uint8 image (fast compression: frames are large)."""
    img = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR) if rgb.ndim == 3 else rgb
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise OSError(f"could not encode {name} as PNG")
    return buf.tobytes()


def write_bytes(path: Path, data: bytes) -> str:
    """Write ``data`` to ``path`` atomically; return its SHA-256 (hex)."""
    write_bytes_atomic(path, data)
    return hashlib.sha256(data).hexdigest()


def write_png(path: Path, rgb: NDArray[np.uint8]) -> str:
    """Write an RGB (or grey) uint8 image as PNG, atomically; returns the file's SHA-256."""
    return write_bytes(path, encode_png(rgb, str(path)))


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def _stale_staging(out: Path) -> list[Path]:
    """Staging folders in ``out`` left by runs that are no longer alive."""
    stale = []
    for p in out.glob(STAGING_PREFIX + "*"):
        try:
            pid = int(p.name[len(STAGING_PREFIX) :].split("-")[0])
        except ValueError:
            continue
        if p.is_dir() and (pid == os.getpid() or not _pid_alive(pid)):
            stale.append(p)
    return stale


def is_simulator_output(out: Path) -> bool:
    """True when ``out/truth.json`` is a simulator truth file."""
    from registration.synth.truth import TRUTH_FORMAT

    try:
        return json.loads((out / TRUTH_NAME).read_text()).get("format") == TRUTH_FORMAT
    except (OSError, ValueError, AttributeError):
        return False


def check_target(out: Path, force: bool) -> None:
    """Refuse (one-line ``FileExistsError`` naming the folder) to write into a non-empty ``out``
    without ``force``; ``NotADirectoryError`` when ``out`` is a file."""
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"output {out} exists and is not a folder")
    if not out.exists() or force:
        return
    stale = set(_stale_staging(out))
    entries = sorted(p.name for p in out.iterdir() if p not in stale)
    if not entries:
        return
    if is_simulator_output(out):
        raise FileExistsError(
            f"{out} already holds a simulated sequence; use --force (force=True in Python) to replace "
            "its frames/, base.png, truth.json, sequence.mp4 and vehicles.csv"
        )
    shown = ", ".join(entries[:4]) + (", ..." if len(entries) > 4 else "")
    raise FileExistsError(
        f"{out} is not empty and is not a simulator output (holds {shown}); choose an empty or "
        "new folder, or use --force (force=True in Python) to replace its frames/, base.png, truth.json, "
        "sequence.mp4 and vehicles.csv (other files are left alone)"
    )


class Staging:
    """A hidden staging folder inside ``out`` that becomes ``out``'s owned entries on commit.

    Use as a context manager: on an exception (or a kill, cleaned up by the next run) the staging
    folder is removed and ``out`` keeps what it had.
    """

    def __init__(self, out: Path, force: bool = False):
        check_target(out, force)
        out.mkdir(parents=True, exist_ok=True)
        for old in _stale_staging(out):
            shutil.rmtree(old, ignore_errors=True)
        self.out = out
        self.dir = out / f"{STAGING_PREFIX}{os.getpid()}-{secrets.token_hex(4)}"
        self.dir.mkdir()
        (self.dir / "frames").mkdir()

    def __enter__(self) -> Staging:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)

    def commit(self, truth: dict) -> None:
        """Swap the staged entries into ``out`` and write ``truth`` as ``truth.json`` last."""
        out = self.out
        trash = self.dir / ".replaced"
        trash.mkdir()
        # The old truth goes first: from here until the new one is written the folder has no
        # truth at all, so no reader can pair a truth with frames of another run.
        if (out / TRUTH_NAME).exists() or (out / TRUTH_NAME).is_symlink():
            os.replace(out / TRUTH_NAME, trash / TRUTH_NAME)
        for name in OWNED:
            if name == TRUTH_NAME:
                continue
            target = out / name
            if target.exists() or target.is_symlink():
                os.replace(target, trash / name)
            if (self.dir / name).exists():
                os.replace(self.dir / name, target)
        write_bytes_atomic(out / TRUTH_NAME, (json.dumps(truth, indent=1) + "\n").encode())
