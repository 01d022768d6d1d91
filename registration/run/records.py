"""A result folder's per-frame records (``frames/KKKKKK.json`` and ``.npz``): paths, reading,
verification, arrays and statistics.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from registration.io import (
    file_sha256,
    read_text_file,
)

FORMAT = "aerialreg-result"
VERSION = 1
RESULT_JSON = "result.json"
MID_BASE = "mid_base.png"
MID_BASE_VALID = "mid_base_valid.png"
MAP_POINTS_JSON = "map_points.json"


def frame_record_path(out_dir: Path, k: int, suffix: str) -> Path:
    return Path(out_dir) / "frames" / f"{k:06d}{suffix}"


# --------------------------------------------------------------------------------------------
# Records

STATUSES = ("ok", "failed", "pending", "damaged")


@dataclass(frozen=True)
class FrameRecord:
    """What a result folder says about one frame (``frames/KKKKKK.json``), read and written only
    through :meth:`from_json` and :meth:`to_json`.

    Attributes:
        status: ``"ok"`` or ``"failed"`` (written); ``"pending"`` (no record yet) or
            ``"damaged"`` (unreadable record or arrays) when read.
        reason: why it failed or is damaged (``""`` when ok).
        stage: how an ok frame was registered: ``"inter-sensor"`` (the reference frame),
            ``"intra-sensor"`` or ``"inter-sensor anchor"`` (re-anchored to the map); None
            otherwise.
        stats: counts, residuals (px) and times (s) of its steps (:func:`frame_stats`); built
            before the record and not changed after.
        model: its global model ``base_from_corrected`` as a dict
            (:func:`registration.geometry.model_from_dict`); None unless ok.
        adjusted_model: its model after the sequence adjustment
            (:mod:`registration.adjustment.sequence`; ``stats["adjustment"]`` says how it was
            made), which the result then uses; ``model`` stays the frame's own. None: not
            adjusted.
        lens_k2: the fourth-order lens term the reference frame's registration found (the
            reference frame's record only).
        k: the frame's index (set when written).
        npz_bytes, npz_sha256: size and SHA-256 of its arrays file (None: it has none).
        input_sha256: SHA-256 of its input image (frames read from image files).
        legacy_arrays: a record written before ``npz_bytes`` existed: its arrays file is read
            when there is one.
    """

    status: str
    reason: str = ""
    stage: str | None = None
    stats: dict = field(default_factory=dict)
    model: dict | None = None
    adjusted_model: dict | None = None
    lens_k2: float | None = None
    k: int | None = None
    npz_bytes: int | None = None
    npz_sha256: str | None = None
    input_sha256: str | None = None
    legacy_arrays: bool = False

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def done(self) -> bool:
        """A complete record ("ok" or "failed"); pending and damaged frames are (re)done."""
        return self.status in ("ok", "failed")

    def may_have_arrays(self, npz: Path) -> bool:
        """Whether its arrays file ``npz`` is to be read."""
        return self.npz_bytes is not None or (self.legacy_arrays and npz.is_file())

    def with_stats(self, **updates) -> FrameRecord:
        """The record with ``stats`` extended (or entries replaced) by ``updates``."""
        return replace(self, stats={**self.stats, **updates})

    @classmethod
    def failed(cls, reason: str, stats: dict | None = None) -> FrameRecord:
        """The record of a frame that could not be registered, with the reason."""
        return cls("failed", reason, stats=dict(stats or {}))

    def to_json(self) -> dict:
        """The record as written (key order as in every result folder so far)."""
        out: dict = {"k": self.k, "status": self.status, "reason": self.reason}
        if self.stage is not None:
            out["stage"] = self.stage
        out["stats"] = self.stats
        out["model"] = self.model
        if self.adjusted_model is not None:
            out["adjusted_model"] = self.adjusted_model
        if self.lens_k2 is not None:
            out["lens_k2"] = self.lens_k2
        out["npz_bytes"] = self.npz_bytes
        for name in ("npz_sha256", "input_sha256"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        return out

    @classmethod
    def from_json(cls, obj: object) -> FrameRecord:
        """A written record; ValueError naming what is wrong with it."""
        if not isinstance(obj, dict) or obj.get("status") not in ("ok", "failed"):
            raise ValueError("no valid status")
        stats, model = obj.get("stats", {}), obj.get("model")
        if not isinstance(stats, dict):
            raise ValueError("stats is not an object")
        if obj["status"] == "ok" and not isinstance(model, dict):
            raise ValueError("an ok record without its model")
        adjusted = obj.get("adjusted_model")
        if adjusted is not None and not isinstance(adjusted, dict):
            raise ValueError("adjusted_model is not an object")
        k = obj.get("k")
        return cls(
            status=obj["status"],
            reason=str(obj.get("reason", "")),
            stage=obj.get("stage"),
            stats=stats,
            model=model,
            adjusted_model=adjusted,
            lens_k2=obj.get("lens_k2"),
            k=None if k is None else int(k),
            npz_bytes=obj.get("npz_bytes"),
            npz_sha256=obj.get("npz_sha256"),
            input_sha256=obj.get("input_sha256"),
            legacy_arrays="npz_bytes" not in obj,
        )


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def damaged_record(reason: str) -> FrameRecord:
    return FrameRecord("damaged", reason)


def read_record(out_dir: str | Path, k: int) -> FrameRecord:
    """Frame ``k``'s record: status ``"pending"`` without one, ``"damaged"`` when the record is
    unreadable or its ``.npz`` is missing or of the wrong size (checked with ``stat`` only; a
    corrupt ``.npz`` of the right size is found when its arrays are read)."""
    path = frame_record_path(out_dir, k, ".json")
    if not path.is_file():
        return FrameRecord("pending", "not registered yet")
    try:
        rec = FrameRecord.from_json(json.loads(path.read_bytes()))
    except (OSError, ValueError, TypeError) as exc:  # JSON and Unicode errors are ValueErrors
        return damaged_record(f"damaged record {path.name}: {_first_line(exc)}")
    if rec.npz_bytes is not None:
        npz = path.with_suffix(".npz")
        try:
            size = npz.stat().st_size
        except OSError:
            return damaged_record(f"damaged record {path.name}: {npz.name} is missing")
        if size != rec.npz_bytes:
            return damaged_record(
                f"damaged record {path.name}: {npz.name} has {size} bytes, not {rec.npz_bytes}"
            )
    return rec


def verify_record(out_dir: str | Path, k: int) -> dict:
    """:func:`read_record`, and the ``.npz`` read whole and compared with the SHA-256 its record
    holds (records without one: every array decompressed, which checks the zip's CRCs). Used
    when a run resumes, so that it redoes frames whose arrays are corrupt."""
    rec = read_record(out_dir, k)
    path = frame_record_path(out_dir, k, ".npz")
    if not rec.done or not (rec.npz_bytes is not None or path.is_file()):
        return rec
    try:
        if rec.npz_sha256:
            if file_sha256(path) != rec.npz_sha256:
                return damaged_record(
                    f"damaged arrays {path.name}: content differs from its record"
                )
        else:
            with np.load(path) as z:
                for name in z.files:
                    z[name]
    except Exception as exc:  # OSError, BadZipFile, EOFError, ValueError, zlib.error
        return damaged_record(f"damaged arrays {path.name}: {_first_line(exc)}")
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
    if getattr(fine, "click_note", ""):
        stats["click"] = fine.click_note
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
