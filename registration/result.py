"""Registration result folders: the writer (:class:`ResultWriter`), the reader
(:class:`RegistrationResult`) and the mapping interface they share with the simulator's truth.

The interface (fixed by ``conventions.md``)::

    result.n_frames                               # int
    result.frame_to_base(k, xy, stage="local")    # (N,2) raw pixels of frame k -> (N,2) base px
    result.base_to_frame(k, xy, stage="local")    # (N,2) base pixels -> (N,2) raw pixels of k

``stage`` is ``"global"`` or ``"local"``. NaN for points of failed frames or outside what the
result covers; never raises for a valid ``k``.

For a georeferenced base (``result.json`` key ``base_georef``) the same in map coordinates::

    result.frame_to_map(k, xy, stage="local", to_crs=None)     # raw px -> map (base's CRS)
    result.map_to_frame(k, xy, stage="local", from_crs=None)   # map -> raw px
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import socket
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.camera import Camera
from registration.coords import as_points, image_size
from registration.georef import GeoReference
from registration.io import (
    SAMPLE_BYTES,
    encode_npz,
    file_sha256,
    read_image,
    read_text_file,
    write_bytes_atomic,
    write_image_atomic,
    write_json_atomic,
)

try:
    import fcntl
except ImportError:  # not POSIX: no lock (documented in README "Reliability")
    fcntl = None

log = logging.getLogger(__name__)

STAGES = ("global", "local")


class SequenceMapping(Protocol):
    """What a registration result and the simulator's ground truth both provide."""

    @property
    def n_frames(self) -> int: ...

    def frame_to_base(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]: ...

    def base_to_frame(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]: ...


FORMAT = "aerialreg-result"
VERSION = 1


LOCK_NAME = ".lock"
RESULT_JSON = "result.json"
MID_BASE = "mid_base.png"
MID_BASE_VALID = "mid_base_valid.png"
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
# What a result folder may hold; only these are ever deleted (``--force``).
_TEMP = re.compile(r"^\..+\.tmp$")
_OWN = {
    ".": re.compile(
        "^(" + "|".join(map(re.escape, (RESULT_JSON, MID_BASE, MID_BASE_VALID))) + ")$"
    ),
    "frames": re.compile(r"^\d{6}\.(json|npz)$"),
    "registered": re.compile(r"^registered\.mp4$"),
    "registered/frames": re.compile(r"^\d{6}\.png$"),
    "registered/overlay": re.compile(r"^\d{6}\.jpg$"),
    "registered/field": re.compile(r"^\d{6}_d[xy]\.png$"),
}


def frame_record_path(out_dir: Path, k: int, suffix: str) -> Path:
    return Path(out_dir) / "frames" / f"{k:06d}{suffix}"


class RegistrationResult:
    """A result folder written by :func:`registration.pipeline.register_sequence`.

    Layout of ``OUT``:

    * ``result.json``: ``n_frames``, ``gamma``, ``frame_size`` [W, H], ``base_size`` [W, H],
      ``base_path``, ``frames_source``, ``reference_frame``, ``seed``, ``preset``, ``config`` and
      ``inputs``, the identity of the frames and base map the run was made from (compared when a
      run resumes, see :class:`ResultWriter`), plus extra keys of other stages.
    * ``frames/KKKKKK.json``: one record per finished frame: ``status`` ("ok" or "failed"),
      ``reason``, ``stats``, the global ``model`` (``base_from_corrected``, a polyprojective),
      ``npz_bytes`` and ``npz_sha256`` (of the frame's ``.npz``; None without one) and
      ``input_sha256`` (of the frame's image file). Written last for a frame, atomically: its
      presence means the frame is done. The reference frame's record also holds ``lens_k2``,
      the lens's fourth-order term beyond Harris every frame was registered with (0 = Harris,
      :mod:`registration.lens_k2`; :attr:`camera` carries it), and ``stats["lens"]``, its
      estimate.
    * ``frames/KKKKKK.npz``: the frame's control points (``src`` corrected px, ``dst`` base px,
      ``kept``, ``residuals``) and its local displacement field (``field_*`` arrays).
    * ``mid_base.png``, ``mid_base_valid.png``: the reference frame in base pixels and its mask.
    * ``.lock``: held by the process writing the folder.

    Frames without a record (a run still going or interrupted) have status ``"pending"``; frames
    whose record or arrays are unreadable (truncated, missing ``.npz``) have status ``"damaged"``
    (``register --resume`` redoes them). Both map to NaN like failed frames.
    """

    def __init__(self, out_dir: str | Path) -> None:
        self.out_dir = Path(out_dir)
        meta_path = self.out_dir / RESULT_JSON
        if not meta_path.is_file():
            raise FileNotFoundError(f"not a registration result (no result.json): {self.out_dir}")
        meta = _read_meta(self.out_dir)
        self.meta = meta
        try:
            self.gamma = float(meta["gamma"])
            self.frame_size = tuple(int(v) for v in meta["frame_size"])
            self.base_size = tuple(int(v) for v in meta["base_size"])
            self.reference_frame = int(meta["reference_frame"])
            n = int(meta["n_frames"])
            # The frames' camera (its k2 comes with the reference frame's record, reload()).
            self.camera = Camera(self.gamma, *self.frame_size)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(
                f"corrupt result.json in {self.out_dir}: bad or missing {exc}"
            ) from None
        if n < 1 or len(self.frame_size) != 2 or len(self.base_size) != 2:
            raise ValueError(f"corrupt result.json in {self.out_dir}: bad n_frames or sizes")
        self.config = meta.get("config", {})
        self.preset = meta.get("preset")
        self.mid_base_path = self.out_dir / MID_BASE
        # The base map's georeference (None for a plain image base): base px <-> map.
        self.georef = GeoReference.from_dict(meta.get("base_georef"))
        self._models: dict[int, object] = {}
        self._arrays: dict[int, dict] = {}
        self.reload()

    @property
    def n_frames(self) -> int:
        return int(self.meta["n_frames"])

    def reload(self) -> None:
        """Re-read the per-frame records (a run may still be writing them)."""
        self.records: list[dict] = [read_record(self.out_dir, k) for k in range(self.n_frames)]
        self._models.clear()
        self._arrays.clear()
        # The lens beyond Harris that the reference frame's registration found (0 = Harris).
        ref = self.reference_frame
        k2 = self.records[ref].get("lens_k2", 0.0) if 0 <= ref < self.n_frames else 0.0
        try:
            self.camera = self.camera.with_k2(float(k2))
        except (TypeError, ValueError):
            raise ValueError(
                f"corrupt record {self.reference_frame:06d}.json in {self.out_dir}: bad "
                f"lens_k2 {k2!r}"
            ) from None

    @property
    def lens(self):
        """The frames' radial lens model (:attr:`Camera.lens`): raw <-> corrected pixels."""
        return self.camera.lens

    # -- per-frame data -------------------------------------------------------------------
    def _check_k(self, k: int) -> int:
        k = int(k)
        if not 0 <= k < self.n_frames:
            raise IndexError(f"frame {k} out of range: the result has {self.n_frames} frames")
        return k

    def status(self, k: int) -> str:
        """ "ok", "failed", "pending" or "damaged"."""
        return str(self.records[self._check_k(k)].get("status"))

    def is_ok(self, k: int) -> bool:
        return self.records[self._check_k(k)].get("status") == "ok"

    def _damage(self, k: int, reason: str) -> None:
        self.records[k] = _damaged(reason)
        self._models.pop(k, None)
        self._arrays[k] = {}

    def model(self, k: int):
        """The frame's global ``base_from_corrected`` model, or None when it failed."""
        k = self._check_k(k)
        if not self.is_ok(k):
            return None
        if k not in self._models:
            from registration.models import model_from_dict

            try:
                self._models[k] = model_from_dict(self.records[k]["model"])
            except (KeyError, TypeError, ValueError) as exc:
                self._damage(k, f"damaged record {k:06d}.json: bad model ({_first_line(exc)})")
                return None
        return self._models[k]

    def _npz(self, k: int) -> dict:
        k = self._check_k(k)
        if k not in self._arrays:
            path = frame_record_path(self.out_dir, k, ".npz")
            arrays: dict = {}
            rec = self.records[k]
            if _expects_npz(rec) or ("npz_bytes" not in rec and path.is_file()):
                try:
                    with np.load(path) as z:
                        arrays = {name: z[name] for name in z.files}
                except Exception as exc:  # BadZipFile, EOFError, OSError, ValueError, zlib.error
                    self._damage(k, f"damaged arrays {path.name}: {_first_line(exc)}")
                    return {}
            self._arrays[k] = arrays
        return self._arrays[k]

    def inputs_difference(self, frames, base: NDArray) -> str:
        """ "" when this result was made from ``frames`` (:class:`registration.io.FrameSource`)
        and ``base``; otherwise one line saying what differs (as ``register --resume`` would).
        For a viewer that must not show another input's result as this one's."""
        old = self.meta.get("inputs")
        if not old:
            return "the result has no record of its inputs (written by an older aerialreg)"
        identity = getattr(frames, "identity", None)
        return _frames_difference(
            old.get("frames"), identity() if identity else None, self.records, frames
        ) or _base_difference(old.get("base"), base_identity(base))

    def _usable(self, k: int, stage: str) -> bool:
        """Whether frame ``k`` maps at ``stage``; reading its model and arrays may find them
        damaged, which marks the frame so."""
        if not self.is_ok(k) or self.model(k) is None:
            return False
        if stage == "local":
            self._npz(k)
        return self.is_ok(k)

    def control_points(self, k: int):
        """``(src, dst, kept, residuals)`` of the frame's fine step, or None."""
        a = self._npz(k)
        if "src" not in a:
            return None
        return a["src"], a["dst"], a["kept"].astype(bool), a["residuals"]

    def field(self, k: int):
        """The frame's local :class:`registration.local.DisplacementField`, or None."""
        a = self._npz(k)
        if "field_vectors" not in a:
            return None
        from registration.local import DisplacementField

        return DisplacementField.from_arrays(
            {
                name[len("field_") :]: a[name]
                for name in a
                if name.startswith("field_") and not name.startswith("field_stats_")
            }
        )

    def field_stats(self, k: int) -> dict[str, NDArray] | None:
        """Per-cell arrays of the local stage (status codes, matches, kept, residuals), or None."""
        a = self._npz(k)
        out = {n[len("field_stats_") :]: a[n] for n in a if n.startswith("field_stats_")}
        return out or None

    # -- the fixed interface --------------------------------------------------------------
    def _inside_frame(self, xy: NDArray) -> NDArray[np.bool_]:
        w, h = self.frame_size
        with np.errstate(invalid="ignore"):
            return (
                (xy[:, 0] >= -0.5)
                & (xy[:, 0] <= w - 0.5)
                & (xy[:, 1] >= -0.5)
                & (xy[:, 1] <= h - 0.5)
            )

    def _global_frame_to_base(self, k: int, xy: NDArray) -> NDArray:
        out = self.model(k).apply(self.lens.corrected_from_raw(xy))
        out[~self._inside_frame(xy)] = np.nan
        return out

    def _global_base_to_frame(self, k: int, xy: NDArray) -> NDArray:
        raw = self.lens.raw_from_corrected(self.model(k).inverse(xy))
        raw[~self._inside_frame(raw)] = np.nan
        return raw

    def frame_to_base(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]:
        """``(N, 2)`` raw pixels of frame ``k`` -> ``(N, 2)`` base pixels (NaN where unknown)."""
        pts = as_points(xy, "xy")
        k = self._check_k(k)
        _check_stage(stage)
        if not self._usable(k, stage):
            return np.full_like(pts, np.nan)
        field = self.field(k) if stage == "local" else None
        if field is None:
            return self._global_frame_to_base(k, pts)
        from registration.local import local_frame_to_base

        return local_frame_to_base(lambda q: self._global_frame_to_base(k, q), field, pts)

    def base_to_frame(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]:
        """``(N, 2)`` base pixels -> ``(N, 2)`` raw pixels of frame ``k`` (NaN where unknown)."""
        pts = as_points(xy, "xy")
        k = self._check_k(k)
        _check_stage(stage)
        if not self._usable(k, stage):
            return np.full_like(pts, np.nan)
        field = self.field(k) if stage == "local" else None
        if field is None:
            return self._global_base_to_frame(k, pts)
        from registration.local import local_base_to_frame

        return local_base_to_frame(lambda b: self._global_base_to_frame(k, b), field, pts)

    # -- map coordinates (georeferenced base) --------------------------------------------------
    def _require_georef(self):
        if self.georef is None:
            raise ValueError(
                f"the base map of {self.out_dir} is not georeferenced: no map coordinates "
                "(register with a GeoTIFF or a world-file base, or export with --georef)"
            )
        return self.georef

    def frame_to_map(
        self, k: int, xy: ArrayLike, stage: str = "local", *, to_crs=None
    ) -> NDArray[np.float64]:
        """``(N, 2)`` raw pixels of frame ``k`` -> ``(N, 2)`` map coordinates in the base's CRS
        (``to_crs``: in that CRS instead, e.g. ``"EPSG:4326"`` gives (longitude, latitude)).
        NaN where :meth:`frame_to_base` is NaN.

        Raises:
            ValueError: the base map is not georeferenced.
        """
        georef = self._require_georef()
        out = georef.map_from_base(self.frame_to_base(k, xy, stage))
        return out if to_crs is None else georef.to_crs(out, to_crs)

    def map_to_frame(
        self, k: int, xy: ArrayLike, stage: str = "local", *, from_crs=None
    ) -> NDArray[np.float64]:
        """``(N, 2)`` map coordinates (the base's CRS, or ``from_crs``) -> ``(N, 2)`` raw pixels
        of frame ``k``; NaN where :meth:`base_to_frame` is NaN.

        Raises:
            ValueError: the base map is not georeferenced.
        """
        georef = self._require_georef()
        pts = as_points(xy, "xy") if from_crs is None else georef.from_crs(xy, from_crs)
        return self.base_to_frame(k, georef.base_from_map(pts), stage)


def _check_stage(stage: str) -> None:
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {', '.join(STAGES)}, got {stage!r}")


def load_result(out_dir: str | Path) -> RegistrationResult:
    """Open a result folder (see :class:`RegistrationResult`)."""
    return RegistrationResult(out_dir)


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
    from registration.config import config_to_dict

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
            want = records[k].get("input_sha256") if k < len(records) else None
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


def _resume_problem(out_dir: Path, old: dict, meta: dict, frames) -> str:
    for key in RESUME_KEYS:
        if old.get(key) != json.loads(json.dumps(meta.get(key))):
            if key == "config":
                return "it was made with a different configuration"
            return f"its {key} differs from this run's ({old.get(key)!r} vs {meta.get(key)!r})"
    if "inputs" not in old:
        return "it has no record of its inputs (written by an older aerialreg)"
    records = [read_record(out_dir, k) for k in range(int(old["n_frames"]))]
    new = meta.get("inputs") or {}
    return _frames_difference(
        old["inputs"].get("frames"), new.get("frames"), records, frames
    ) or _base_difference(old["inputs"].get("base"), new.get("base"))


# --------------------------------------------------------------------------------------------
# The lock


class ResultBusy(ValueError):
    """Another process is writing the result folder."""


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
                raise ResultBusy(
                    f"{self.path.parent} is being written by another aerialreg process ({who}); "
                    "wait for it or use another --out"
                ) from None
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
    pattern = _OWN.get(rel)
    return bool(_TEMP.match(name) or name == LOCK_NAME or (pattern and pattern.match(name)))


def folder_state(out_dir: Path) -> str:
    """``"missing"``, ``"empty"``, ``"result"`` (result.json of this format), ``"damaged"``
    (only result entries but no readable result.json) or ``"foreign"`` (anything else).

    Raises:
        ValueError: ``out_dir`` exists and is not a folder.
    """
    if not out_dir.exists():
        return "missing"
    if not out_dir.is_dir():
        raise ValueError(f"{out_dir} exists and is a file, not a folder; give a folder for --out")
    names = [n for n in os.listdir(out_dir) if n != LOCK_NAME and not _TEMP.match(n)]
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
        raise ValueError("--resume and --force exclude each other")
    state = folder_state(out_dir)
    if state == "foreign":
        raise ValueError(_foreign_message(out_dir))
    if state == "damaged" and not force:
        what = f"cannot resume {out_dir}: it holds" if resume else f"{out_dir} holds"
        raise ValueError(
            f"{what} a damaged registration result (result.json missing or corrupt); use "
            "another --out or --force to start over"
        )
    if state == "result" and not (resume or force):
        raise ValueError(
            f"{out_dir} already holds a registration result; pass --resume to continue it, "
            "--force to start over, or choose another folder"
        )
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
        self._status = [verify_record(out_dir, k)["status"] for k in range(self.n_frames)]

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
                log.info("--force: removing the result in %s", out_dir)
                remove_result(out_dir)
                state = "empty"
            if state == "result":
                problem = _resume_problem(out_dir, _read_meta(out_dir), meta, frames)
                if problem:
                    raise ValueError(
                        f"cannot resume {out_dir}: {problem}; use another --out or --force to "
                        "start over"
                    )
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

    def write_frame(self, k: int, record: dict, arrays: dict[str, NDArray] | None = None) -> None:
        """Write frame ``k``'s arrays (if any), then its record, each atomically."""
        rec = {"k": int(k), **record, "npz_bytes": None}
        if arrays:
            data = encode_npz(**arrays)
            write_bytes_atomic(frame_record_path(self.out_dir, k, ".npz"), data)
            rec["npz_bytes"] = len(data)
            rec["npz_sha256"] = hashlib.sha256(data).hexdigest()
        path = self._frames.path(k) if hasattr(self._frames, "path") else None
        if path is not None:
            try:
                rec["input_sha256"] = file_sha256(path)
            except OSError:
                pass
        write_json_atomic(frame_record_path(self.out_dir, k, ".json"), rec)
        self._status[k] = rec.get("status", "failed")

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


def _foreign_message(out_dir: Path) -> str:
    names = sorted(n for n in os.listdir(out_dir) if not _own_entry(".", n))
    names = names or sorted(os.listdir(out_dir))
    return (
        f"{out_dir} is not an aerialreg result folder (it holds e.g. {names[0]!r}); give a new "
        "or empty folder for --out"
    )
