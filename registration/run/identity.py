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
from registration.io import frames_difference, input_differs

try:
    import fcntl
except ImportError:  # not POSIX: no lock (documented in README "Reliability")
    fcntl = None
from registration.run.records import FORMAT, VERSION, read_record

# Keys of result.json that must agree for a resume to continue a result rather than mix two runs
# (the inputs' identity is compared separately, see registration.io.frames_difference).
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


def base_identity(
    base: NDArray, base_path: str | os.PathLike | None = None, base_valid: NDArray | None = None
) -> dict:
    """The base map's identity: its shape, the SHA-256 of its pixels (it is in memory anyway;
    the pixels are what the registration used, whatever the file's encoding) and of its
    no-data mask (``base_valid``, which ``--base-nodata`` decides; None when all is valid)."""
    pixels = np.ascontiguousarray(base)
    valid = None
    if base_valid is not None and not np.asarray(base_valid).all():
        valid = hashlib.sha256(np.packbits(np.asarray(base_valid, bool)).data).hexdigest()
    return {
        "file": Path(base_path).name if base_path else None,
        "shape": list(pixels.shape),
        "pixels_sha256": hashlib.sha256(pixels.data).hexdigest(),
        "valid_sha256": valid,
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
    base_valid: NDArray | None = None,
) -> dict:
    """``result.json`` of a new run. ``extra``: further keys (e.g. the base's georeference);
    ``base_valid``: the base map's no-data mask (part of its identity)."""
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
        # Absolute: a command run from another folder reopens these frames, not others.
        "frames_source": _absolute(getattr(frames, "description", None)),
        "reference_frame": int(reference_frame),
        "seed": _seed_json(seed),
        "preset": preset,
        "config": config_to_dict(config),
        "inputs": {
            "frames": identity() if identity else None,
            "base": base_identity(base, base_path, base_valid),
        },
    }
    meta.update(extra or {})
    return meta


def _absolute(spec: str | None) -> str | None:
    """A frames path or glob pattern as an absolute path (None stays None)."""
    return None if spec is None else os.path.abspath(spec)


def _base_difference(old: dict | None, new: dict | None) -> str:
    if not old or not new:
        return ""
    label = f"the base map ({new.get('file')})"
    if old.get("shape") != new.get("shape"):
        return input_differs(label, f"shape {new.get('shape')} vs {old.get('shape')}")
    if old.get("pixels_sha256") != new.get("pixels_sha256"):
        return input_differs(label, "other pixels of the same size")
    if "valid_sha256" in old and old.get("valid_sha256") != new.get("valid_sha256"):
        return input_differs(label, "another no-data mask (--base-nodata)")
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
    frames_text = frames_difference(
        old["inputs"].get("frames"),
        new.get("frames"),
        [getattr(r, "input_sha256", None) for r in records],
        frames,
    )
    if frames_text:
        return frames_text, None
    return _base_difference(old["inputs"].get("base"), new.get("base")), None
