"""A result folder's per-frame records (``frames/KKKKKK.json`` and ``.npz``): paths, reading,
verification, arrays and statistics.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from registration.io import (
    file_sha256,
    read_text_file,
)

try:
    import fcntl
except ImportError:  # not POSIX: no lock (documented in README "Reliability")
    fcntl = None


FORMAT = "aerialreg-result"
VERSION = 1
RESULT_JSON = "result.json"
MID_BASE = "mid_base.png"
MID_BASE_VALID = "mid_base_valid.png"


def frame_record_path(out_dir: Path, k: int, suffix: str) -> Path:
    return Path(out_dir) / "frames" / f"{k:06d}{suffix}"


# --------------------------------------------------------------------------------------------
# Records


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _damaged(reason: str) -> dict:
    return {"status": "damaged", "reason": reason, "stats": {}}


def _expects_npz(record: dict) -> bool:
    """Whether a record's ``.npz`` must exist (``npz_bytes`` is its size). Records written
    before ``npz_bytes`` may or may not have one."""
    return record.get("npz_bytes") is not None


def read_record(out_dir: str | Path, k: int) -> dict:
    """Frame ``k``'s record: ``{"status": "pending", ...}`` without one, ``"damaged"`` when the
    record is unreadable or its ``.npz`` is missing or of the wrong size (checked with ``stat``
    only; a corrupt ``.npz`` of the right size is found when its arrays are read)."""
    path = frame_record_path(out_dir, k, ".json")
    if not path.is_file():
        return {"status": "pending", "reason": "not registered yet", "stats": {}}
    try:
        rec = json.loads(path.read_bytes())
    except (OSError, ValueError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        return _damaged(f"damaged record {path.name}: {_first_line(exc)}")
    if not isinstance(rec, dict) or rec.get("status") not in ("ok", "failed"):
        return _damaged(f"damaged record {path.name}: no valid status")
    if _expects_npz(rec):
        npz = path.with_suffix(".npz")
        try:
            size = npz.stat().st_size
        except OSError:
            return _damaged(f"damaged record {path.name}: {npz.name} is missing")
        want = rec.get("npz_bytes")
        if want is not None and size != want:
            return _damaged(f"damaged record {path.name}: {npz.name} has {size} bytes, not {want}")
    return rec


def verify_record(out_dir: str | Path, k: int) -> dict:
    """:func:`read_record`, and the ``.npz`` read whole and compared with the SHA-256 its record
    holds (records without one: every array decompressed, which checks the zip's CRCs). Used
    when a run resumes, so that it redoes frames whose arrays are corrupt."""
    rec = read_record(out_dir, k)
    path = frame_record_path(out_dir, k, ".npz")
    if rec.get("status") not in ("ok", "failed") or not (_expects_npz(rec) or path.is_file()):
        return rec
    try:
        if rec.get("npz_sha256"):
            if file_sha256(path) != rec["npz_sha256"]:
                return _damaged(f"damaged arrays {path.name}: content differs from its record")
        else:
            with np.load(path) as z:
                for name in z.files:
                    z[name]
    except Exception as exc:  # OSError, BadZipFile, EOFError, ValueError, zlib.error
        return _damaged(f"damaged arrays {path.name}: {_first_line(exc)}")
    return rec


def _read_meta(out_dir: Path) -> dict:
    path = out_dir / RESULT_JSON
    try:
        meta = json.loads(read_text_file(path, "result file"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"corrupt result.json in {out_dir}: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ValueError(f"not an aerialreg result folder: {out_dir}")
    return meta


def frame_arrays(fine, field, field_stats=None) -> dict[str, NDArray]:
    """A frame record's arrays from its fine step (``global_registration.FineResult``), its
    local field and the field's per-cell statistics (``registration.local``)."""
    arrays = {
        "src": fine.src.astype(np.float64),
        "dst": fine.dst.astype(np.float64),
        "kept": fine.kept.astype(np.uint8),
        "residuals": fine.residuals.astype(np.float64),
    }
    if fine.source is not None:
        arrays["source"] = np.asarray(fine.source, np.int16)
    if field is not None:
        arrays.update({f"field_{k}": np.asarray(v) for k, v in field.to_arrays().items()})
    if field_stats is not None:
        arrays.update({f"field_stats_{k}": v for k, v in field_stats.to_arrays().items()})
    return arrays


def _finite_or_none(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def frame_stats(coarse, fine, times: dict[str, float], field_stats=None) -> dict:
    """A frame record's ``stats``: counts of the coarse (``CoarseResult``) and fine steps,
    residuals, times (s) and the local stage's summary."""
    kept = fine.residuals[fine.kept] if len(fine.residuals) else np.zeros(0)
    stats = {
        "n_keypoints_frame": coarse.n_keypoints_frame,
        "n_keypoints_base": coarse.n_keypoints_base,
        "n_matches": coarse.n_matches,
        "n_gated": int(coarse.gated.sum()),
        "n_coarse_inliers": coarse.n_inliers,
        "n_control_points": int(len(fine.src)),
        "n_inliers": int(fine.kept.sum()),
        "reqcon_iterations": int(fine.iterations),
        "residual_rms_px": float(np.sqrt(np.mean(kept**2))) if len(kept) else None,
        "residual_mean_px": float(np.mean(kept)) if len(kept) else None,
        "time_s": {name: round(v, 4) for name, v in times.items()},
        "coarse_model": getattr(coarse, "model_kind", "projective"),
        "fine_model": getattr(fine, "model_kind", "polyprojective"),
        "fine_model_reason": getattr(fine, "model_reason", ""),
        # Rounded: REQCON's unquantized final fit varies in its last bits between processes.
        "residual_sigma_px": _finite_or_none(round(getattr(fine, "sigma_px", float("nan")), 9)),
    }
    if getattr(coarse, "path", ""):
        stats["coarse_path"] = coarse.path
        if coarse.fast_reason:
            stats["fast_path_reason"] = coarse.fast_reason
    if getattr(coarse, "heading_deg", None) is not None:
        stats["heading_deg"] = round(float(coarse.heading_deg), 3)
        stats["scale"] = round(float(coarse.scale), 5)
        stats["gate"] = coarse.gate
    if field_stats is not None:
        stats["local"] = field_stats.to_dict()
    return stats
