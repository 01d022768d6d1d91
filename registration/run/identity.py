"""The identity of a run's inputs and settings (``result.json``), and what differs when a resume
is asked with other inputs.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from registration.coords import image_size
from registration.io import (
    SAMPLE_BYTES,
    file_sha256,
)

try:
    import fcntl
except ImportError:  # not POSIX: no lock (documented in README "Reliability")
    fcntl = None
from registration.run.records import FORMAT, VERSION, read_record

# Keys of result.json that must agree for a resume to continue a result rather than mix two runs
# (the inputs' identity is compared separately, see _frames_difference).
RESUME_KEYS = (
    "n_frames",
    "gamma",
    "frame_size",
    "base_size",
    "reference_frame",
    "seed",
    "config",
    "base_georef",  # absent (None) for a plain image base
)


# --------------------------------------------------------------------------------------------
# Metadata and the identity of a run's inputs


def base_identity(base: NDArray, base_path: str | os.PathLike | None = None) -> dict:
    """The base map's identity: its shape and the SHA-256 of its pixels (it is in memory anyway;
    the pixels are what the registration used, whatever the file's encoding)."""
    pixels = np.ascontiguousarray(base)
    return {
        "file": Path(base_path).name if base_path else None,
        "shape": list(pixels.shape),
        "pixels_sha256": hashlib.sha256(pixels.data).hexdigest(),
    }


def _seed_json(seed) -> list | None:
    """One seed as ``[fx, fy, bx, by]``, two as a list of two such lists (as given)."""
    if seed is None:
        return None
    arr = np.asarray(seed, dtype=np.float64)
    return [float(v) for v in arr] if arr.ndim == 1 else [[float(v) for v in row] for row in arr]


def make_metadata(
    frames,
    base: NDArray,
    base_path,
    gamma: float,
    seed,
    reference_frame: int,
    config,
    preset: str | None,
    extra: dict[str, Any] | None = None,
) -> dict:
    """``result.json`` of a new run. ``extra``: further keys (e.g. the base's georeference)."""
    from registration.run.config import config_to_dict

    identity = getattr(frames, "identity", None)
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "n_frames": len(frames),
        "gamma": float(gamma),
        "frame_size": list(frames.size),
        "base_size": list(image_size(base)),
        "base_path": str(base_path) if base_path else None,
        "frames_source": getattr(frames, "description", None),
        "reference_frame": int(reference_frame),
        "seed": _seed_json(seed),
        "preset": preset,
        "config": config_to_dict(config),
        "inputs": {
            "frames": identity() if identity else None,
            "base": base_identity(base, base_path),
        },
    }
    meta.update(extra or {})
    return meta


def _differs(label: str, what: str) -> str:
    return f"{label} differs from the run's input ({what})"


def _frames_difference(old: dict | None, new: dict | None, records: list[dict], frames) -> str:
    """What differs between the recorded and the current frames ("" when nothing does).

    Sizes and the SHA-256 of each file's first and last 64 KB must agree. When only a file's
    mtime differs (copied, touched) and it is larger than the sampled bytes, a frame already
    registered is hashed whole and compared with the hash its record holds.
    """
    if old is None or new is None:
        return "" if old == new else "the frames' identity is not recorded for both runs"
    if old.get("kind") != new.get("kind"):
        return f"the frames were {old.get('kind')}, now {new.get('kind')}"
    if old.get("n_frames") != new.get("n_frames"):
        return f"the frames were {old.get('n_frames')}, now {new.get('n_frames')}"
    if new["kind"] == "video":
        label = f"the video {new.get('name')}"
        if old.get("size") != new.get("size"):
            return _differs(label, f"size {new.get('size')} vs {old.get('size')} bytes")
        if old.get("sample_sha256") != new.get("sample_sha256"):
            return _differs(label, "content of its first or last 64 KB")
        return ""
    for k, (o, n) in enumerate(zip(old.get("files", []), new.get("files", []), strict=False)):
        path = frames.path(k) if hasattr(frames, "path") else n.get("name")
        label = f"frame {k} ({path})"
        if "error" in n:
            return f"{label} cannot be read now ({n['error']})"
        if o.get("size") != n.get("size"):
            return _differs(label, f"size {n.get('size')} vs {o.get('size')} bytes")
        if o.get("sample_sha256") != n.get("sample_sha256"):
            return _differs(label, "content of its first or last 64 KB")
        if o.get("mtime_ns") != n.get("mtime_ns") and n["size"] > 2 * SAMPLE_BYTES:
            want = records[k].input_sha256 if k < len(records) else None
            if want and path is not None and file_sha256(path) != want:
                return _differs(label, "content changed since it was registered")
    return ""


def _base_difference(old: dict | None, new: dict | None) -> str:
    if not old or not new:
        return ""
    label = f"the base map ({new.get('file')})"
    if old.get("shape") != new.get("shape"):
        return _differs(label, f"shape {new.get('shape')} vs {old.get('shape')}")
    if old.get("pixels_sha256") != new.get("pixels_sha256"):
        return _differs(label, "other pixels of the same size")
    return ""


def _resume_problem(out_dir: Path, old: dict, meta: dict, frames) -> tuple[str, str | None]:
    """``(what differs, the result.json key that does or None)``; ``("", None)`` when a resume
    may continue the result."""
    for key in RESUME_KEYS:
        if old.get(key) != json.loads(json.dumps(meta.get(key))):
            if key == "config":
                return "it was made with a different configuration", key
            return f"its {key} differs from this run's ({old.get(key)!r} vs {meta.get(key)!r})", key
    if "inputs" not in old:
        return "it has no record of its inputs (written by an older aerialreg)", None
    records = [read_record(out_dir, k) for k in range(int(old["n_frames"]))]
    new = meta.get("inputs") or {}
    frames_text = _frames_difference(
        old["inputs"].get("frames"), new.get("frames"), records, frames
    )
    if frames_text:
        return frames_text, None
    return _base_difference(old["inputs"].get("base"), new.get("base")), None
