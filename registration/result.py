"""Registration result folders and the mapping interface they share with the simulator's truth.

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

import json
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points
from registration.distortion import HarrisModel
from registration.georef import GeoReference

STAGES = ("global", "local")


class SequenceMapping(Protocol):
    """What a registration result and the simulator's ground truth both provide."""

    @property
    def n_frames(self) -> int: ...

    def frame_to_base(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]: ...

    def base_to_frame(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]: ...


FORMAT = "aerialreg-result"
VERSION = 1


def frame_record_path(out_dir: Path, k: int, suffix: str) -> Path:
    return Path(out_dir) / "frames" / f"{k:06d}{suffix}"


class RegistrationResult:
    """A result folder written by :func:`registration.pipeline.register_sequence`.

    Layout of ``OUT``:

    * ``result.json``: ``n_frames``, ``gamma``, ``frame_size`` [W, H], ``base_size`` [W, H],
      ``base_path``, ``frames_source``, ``reference_frame``, ``seed``, ``preset``, ``config``.
    * ``frames/KKKKKK.json``: one record per finished frame: ``status`` ("ok" or "failed"),
      ``reason``, ``stats`` and the global ``model`` (``base_from_corrected``, a polyprojective).
      Written last for a frame, atomically: its presence means the frame is done.
    * ``frames/KKKKKK.npz``: the frame's control points (``src`` corrected px, ``dst`` base px,
      ``kept``, ``residuals``) and its local displacement field (``field_*`` arrays).
    * ``mid_base.png``, ``mid_base_valid.png``: the reference frame in base pixels and its mask.

    Frames without a record (a run still going or interrupted) have status ``"pending"`` and map
    to NaN like failed frames.
    """

    def __init__(self, out_dir: str | Path) -> None:
        self.out_dir = Path(out_dir)
        meta_path = self.out_dir / "result.json"
        if not meta_path.is_file():
            raise FileNotFoundError(f"not a registration result (no result.json): {self.out_dir}")
        try:
            meta = json.loads(meta_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"corrupt result.json in {self.out_dir}: {exc}") from None
        if meta.get("format") != FORMAT:
            raise ValueError(f"not an aerialreg result folder: {self.out_dir}")
        self.meta = meta
        self.gamma = float(meta["gamma"])
        self.frame_size = tuple(int(v) for v in meta["frame_size"])
        self.base_size = tuple(int(v) for v in meta["base_size"])
        self.reference_frame = int(meta["reference_frame"])
        self.config = meta.get("config", {})
        self.preset = meta.get("preset")
        self.mid_base_path = self.out_dir / "mid_base.png"
        # The base map's georeference (None for a plain image base): base px <-> map.
        self.georef = GeoReference.from_dict(meta.get("base_georef"))
        self.harris = HarrisModel(self.gamma, *self.frame_size)
        self._models: dict[int, object] = {}
        self._arrays: dict[int, dict] = {}
        self.reload()

    @property
    def n_frames(self) -> int:
        return int(self.meta["n_frames"])

    def reload(self) -> None:
        """Re-read the per-frame records (a run may still be writing them)."""
        self.records: list[dict] = []
        for k in range(self.n_frames):
            path = frame_record_path(self.out_dir, k, ".json")
            rec = {"status": "pending", "reason": "not registered yet", "stats": {}}
            if path.is_file():
                try:
                    rec = json.loads(path.read_text())
                except (json.JSONDecodeError, UnicodeDecodeError):
                    rec = {"status": "failed", "reason": f"corrupt record {path.name}", "stats": {}}
            self.records.append(rec)
        self._models.clear()
        self._arrays.clear()

    # -- per-frame data -------------------------------------------------------------------
    def _check_k(self, k: int) -> int:
        k = int(k)
        if not 0 <= k < self.n_frames:
            raise IndexError(f"frame {k} out of range: the result has {self.n_frames} frames")
        return k

    def is_ok(self, k: int) -> bool:
        return self.records[self._check_k(k)].get("status") == "ok"

    def model(self, k: int):
        """The frame's global ``base_from_corrected`` model, or None when it failed."""
        k = self._check_k(k)
        if not self.is_ok(k):
            return None
        if k not in self._models:
            from registration.models import model_from_dict

            self._models[k] = model_from_dict(self.records[k]["model"])
        return self._models[k]

    def _npz(self, k: int) -> dict:
        k = self._check_k(k)
        if k not in self._arrays:
            path = frame_record_path(self.out_dir, k, ".npz")
            self._arrays[k] = dict(np.load(path)) if path.is_file() else {}
        return self._arrays[k]

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
        out = self.model(k).apply(self.harris.corrected_from_raw(xy))
        out[~self._inside_frame(xy)] = np.nan
        return out

    def _global_base_to_frame(self, k: int, xy: NDArray) -> NDArray:
        raw = self.harris.raw_from_corrected(self.model(k).inverse(xy))
        raw[~self._inside_frame(raw)] = np.nan
        return raw

    def frame_to_base(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]:
        """``(N, 2)`` raw pixels of frame ``k`` -> ``(N, 2)`` base pixels (NaN where unknown)."""
        pts = as_points(xy, "xy")
        k = self._check_k(k)
        _check_stage(stage)
        if not self.is_ok(k):
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
        if not self.is_ok(k):
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
