"""The built-in demo sequence: simulated once on first use and cached.

Location: ``$AERIALREG_CACHE_DIR/demo-v1`` if the variable is set, else
``platformdirs.user_cache_dir("aerialreg")/demo-v1``. The folder has the layout of
:func:`registration.synth.simulate` plus ``COMPLETE.json`` (written last): a manifest of every
file's size and SHA-256. A folder without the marker, with a missing, empty or changed file, or
built with another config, truth format or renderer (``render.RENDER_VERSION``) is rebuilt (into
a temporary sibling, then swapped in).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path

from registration.io import write_bytes_atomic
from registration.synth.config import SimConfig
from registration.synth.render import RENDER_VERSION
from registration.synth.sequence import Progress, simulate
from registration.synth.truth import TRUTH_VERSION

DEMO_NAME = "demo-v1"
MARKER = "COMPLETE.json"
# 1280x960 (half the paper's frame), 24 frames at 5 fps = 4.8 s of flight.
DEMO_CONFIG = SimConfig(frame_size=(1280, 960), n_frames=24, frame_scale=1.0, seed=2024)


def cache_root() -> Path:
    env = os.environ.get("AERIALREG_CACHE_DIR")
    if env:
        return Path(env)
    import platformdirs

    return Path(platformdirs.user_cache_dir("aerialreg"))


def demo_dir() -> Path:
    """Where the demo sequence lives (it may not exist yet)."""
    return cache_root() / DEMO_NAME


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _manifest(root: Path) -> dict[str, list]:
    files = sorted(
        p
        for p in root.rglob("*")
        if p.is_file() and p.name != MARKER and not p.name.startswith(".")
    )
    return {p.relative_to(root).as_posix(): [p.stat().st_size, _sha256(p)] for p in files}


def _config_dict() -> dict:
    return json.loads(json.dumps(dataclasses.asdict(DEMO_CONFIG)))


def _versions() -> dict:
    return {"truth": TRUTH_VERSION, "render": RENDER_VERSION}


def is_complete(root: Path) -> bool:
    """True when ``root`` holds a finished demo whose files match the marker's manifest."""
    marker = root / MARKER
    try:
        data = json.loads(marker.read_text())
        files = data["files"]
        if data.get("config") != _config_dict() or data.get("versions") != _versions():
            return False
        expected = {f"frames/{k:06d}.png" for k in range(DEMO_CONFIG.n_frames)} | {
            "base.png",
            "truth.json",
        }
        if not expected <= set(files):
            return False
        for rel, (size, digest) in files.items():
            p = root / rel
            if not p.is_file() or size <= 0 or p.stat().st_size != size or _sha256(p) != digest:
                return False
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return True


def demo_sequence(progress: Progress | None = None, *, rebuild: bool = False) -> Path:
    """Path of the demo sequence, simulating it first if the cache is missing or damaged.

    Args:
        progress: ``progress(done, total)`` while building (not called when cached).
        rebuild: build again even if the cache is complete.
    """
    root = demo_dir()
    if not rebuild and is_complete(root):
        return root
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{DEMO_NAME}.build-", dir=root.parent))
    try:
        simulate(tmp, DEMO_CONFIG, progress=progress)
        marker = {"config": _config_dict(), "versions": _versions(), "files": _manifest(tmp)}
        write_bytes_atomic(tmp / MARKER, json.dumps(marker, indent=1).encode())
        # Swap the finished folder in; a concurrent builder may have won the race.
        trash = None
        if root.exists():
            trash = root.parent / f".{DEMO_NAME}.old-{os.getpid()}"
            os.replace(root, trash)
        try:
            os.replace(tmp, root)
        except OSError:
            if not is_complete(root):
                raise
        if trash is not None:
            shutil.rmtree(trash, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return root
