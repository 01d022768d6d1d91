"""Reading a registration result folder (:class:`RegistrationResult`, ``registration.load``): the
mapping interface it shares with the simulator's truth, and the records, models, fields and
control points of each frame. The folder is written by :mod:`registration.run.writer`.

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

import copy
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.adjustment.links import LINKS_PREFIX
from registration.coords import as_points
from registration.errors import NotGeoreferenced
from registration.gis import GeoReference
from registration.io import frames_difference
from registration.lens import Camera
from registration.mapping import _check_stage
from registration.run.identity import _base_difference, base_identity
from registration.run.records import (
    MID_BASE,
    RESULT_JSON,
    FrameRecord,
    _first_line,
    _read_meta,
    damaged_record,
    frame_record_path,
    read_record,
)


class RegistrationResult:
    """A result folder written by :func:`registration.run.pipeline.register_sequence`.

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
      :mod:`registration.lens.k2`; :attr:`camera` carries it), and ``stats["lens"]``, its
      estimate. A run with the sequence adjustment (``config.adjust``) adds to each frame
      ``adjusted_model`` (which :meth:`model` and both stages then use; ``model`` stays the
      frame's own) and ``stats["adjustment"]`` (its window, links, residuals, predicted error
      and flag; :class:`registration.adjustment.FrameAdjustment`).
    * ``frames/KKKKKK.npz``: the frame's control points (``src`` corrected px, ``dst`` base px,
      ``kept``, ``residuals``) and its local displacement field (``field_*`` arrays), measured
      on its own model; with the adjustment, where the frame has neighbours close enough, the
      field that makes its local stage consistent with theirs (``consistency_field_*``,
      :mod:`registration.adjustment.fields`), which stage ``"local"`` applies on top of its
      own. :meth:`unadjusted` sets the adjustment aside.
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
        self._own_only = False
        self.reload()

    @property
    def n_frames(self) -> int:
        return int(self.meta["n_frames"])

    def reload(self) -> None:
        """Re-read the per-frame records (a run may still be writing them)."""
        self.records: list[FrameRecord] = [
            read_record(self.out_dir, k) for k in range(self.n_frames)
        ]
        if self._own_only:
            self.records = [replace(r, adjusted_model=None) for r in self.records]
        self._models.clear()
        self._arrays.clear()
        # The lens beyond Harris that the reference frame's registration found (0 = Harris).
        ref = self.reference_frame
        k2 = self.records[ref].lens_k2 if 0 <= ref < self.n_frames else None
        k2 = 0.0 if k2 is None else k2
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
        return self.records[self._check_k(k)].status

    def is_ok(self, k: int) -> bool:
        return self.records[self._check_k(k)].ok

    def _damage(self, k: int, reason: str) -> None:
        self.records[k] = damaged_record(reason)
        self._models.pop(k, None)
        self._arrays[k] = {}

    def model(self, k: int):
        """The frame's global ``base_from_corrected`` model (after the sequence adjustment where
        the run made one), or None when it failed."""
        k = self._check_k(k)
        if not self.is_ok(k):
            return None
        if k not in self._models:
            from registration.geometry import model_from_dict

            rec = self.records[k]
            try:
                own = model_from_dict(rec.model)
                adjusted = None if rec.adjusted_model is None else (
                    model_from_dict(rec.adjusted_model)
                )  # fmt: skip
            except (KeyError, TypeError, ValueError) as exc:
                self._damage(k, f"damaged record {k:06d}.json: bad model ({_first_line(exc)})")
                return None
            self._models[k] = (own, adjusted)
        own, adjusted = self._models[k]
        return own if adjusted is None else adjusted

    def own_model(self, k: int):
        """The frame's model from its own registration (before any sequence adjustment), or
        None when it failed: what the run's later frames were registered with."""
        if self.model(k) is None:
            return None
        return self._models[k][0]

    def is_adjusted(self, k: int) -> bool:
        """Whether the frame's model and field come from the sequence adjustment."""
        return self.is_ok(k) and self.records[k].adjusted_model is not None

    def _npz(self, k: int) -> dict:
        k = self._check_k(k)
        if k not in self._arrays:
            path = frame_record_path(self.out_dir, k, ".npz")
            arrays: dict = {}
            if self.records[k].may_have_arrays(path):
                try:
                    with np.load(path) as z:
                        # Links between frames are read only by the sequence adjustment,
                        # a few frames at a time (:meth:`stored_links`).
                        arrays = {n: z[n] for n in z.files if not n.startswith(LINKS_PREFIX)}
                except Exception as exc:  # BadZipFile, EOFError, OSError, ValueError, zlib.error
                    self._damage(k, f"damaged arrays {path.name}: {_first_line(exc)}")
                    return {}
            self._arrays[k] = arrays
        return self._arrays[k]

    def inputs_difference(self, frames, base: NDArray, base_valid: NDArray | None = None) -> str:
        """ "" when this result was made from ``frames`` (:class:`registration.io.frames.FrameSource`)
        and ``base``; otherwise one line saying what differs (as ``register --resume`` would).
        For a viewer that must not show another input's result as this one's."""
        old = self.meta.get("inputs")
        if not old:
            return "the result has no record of its inputs (written by an older aerialreg)"
        identity = getattr(frames, "identity", None)
        hashes = [getattr(r, "input_sha256", None) for r in self.records]
        return frames_difference(
            old.get("frames"), identity() if identity else None, hashes, frames
        ) or _base_difference(old.get("base"), base_identity(base, None, base_valid))

    def _usable(self, k: int, stage: str) -> bool:
        """Whether frame ``k`` maps at ``stage``; reading its model and arrays may find them
        damaged, which marks the frame so."""
        if not self.is_ok(k) or self.model(k) is None:
            return False
        if stage == "local":
            self._npz(k)
        return self.is_ok(k)

    def arrays(self, k: int) -> dict[str, NDArray]:
        """Every array of the frame's ``.npz`` by name, its stored links included (a new dict;
        empty without)."""
        return {**self._npz(k), **self.stored_links(k)}

    def stored_links(self, k: int) -> dict[str, NDArray]:
        """The links between frames the run measured as frame ``k`` was registered (arrays
        :func:`registration.adjustment.links_to_arrays` names; read from the file each time,
        not kept)."""
        k = self._check_k(k)
        path = frame_record_path(self.out_dir, k, ".npz")
        if not self._npz(k):
            return {}
        try:
            with np.load(path) as z:
                return {n: z[n] for n in z.files if n.startswith(LINKS_PREFIX)}
        except Exception as exc:  # as _npz: a file damaged since it was read
            self._damage(k, f"damaged arrays {path.name}: {_first_line(exc)}")
            return {}

    def control_points(self, k: int):
        """``(src, dst, kept, residuals)`` of the frame's fine step, or None."""
        a = self._npz(k)
        if "src" not in a:
            return None
        return a["src"], a["dst"], a["kept"].astype(bool), a["residuals"]

    def field(self, k: int):
        """The frame's own local
        :class:`registration.geometry.displacement_field.DisplacementField` (measured on its own
        model, :meth:`own_model`), or None."""
        return _field(self._npz(k), "field_")

    def local_stage(self, k: int):
        """``(model, field, consistency)``: the frame's own model and the local field measured
        on it, and where the sequence adjustment made one, the field that makes its local stage
        consistent with its neighbours' (:mod:`registration.adjustment.fields`), applied on top
        (``x' + δ(x') = own_local(q)``); None where there is none."""
        consistency = _field(self._npz(k), "consistency_field_") if self.is_adjusted(k) else None
        return self.own_model(k), self.field(k), consistency

    def unadjusted(self) -> RegistrationResult:
        """This result as each frame's own registration left it: the sequence adjustment's
        models and fields set aside (to compare the two; the folder is not changed)."""
        view = copy.copy(self)
        view.records = [replace(r, adjusted_model=None) for r in self.records]
        view._models, view._arrays, view._own_only = {}, {}, True
        return view

    def release(self, k: int) -> None:
        """Forget frame ``k``'s cached model and arrays (a long pass over the frames keeps
        memory flat); they are read again when asked for."""
        if 0 <= k < self.n_frames:
            self._models.pop(k, None)
            self._arrays.pop(k, None)

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

    def _global_frame_to_base(self, k: int, xy: NDArray, model=None) -> NDArray:
        out = (model or self.model(k)).apply(self.lens.corrected_from_raw(xy))
        out[~self._inside_frame(xy)] = np.nan
        return out

    def _global_base_to_frame(self, k: int, xy: NDArray, model=None, clip: bool = True) -> NDArray:
        raw = self.lens.raw_from_corrected((model or self.model(k)).inverse(xy))
        if clip:
            raw[~self._inside_frame(raw)] = np.nan
        return raw

    def frame_to_base(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]:
        """``(N, 2)`` raw pixels of frame ``k`` -> ``(N, 2)`` base pixels (NaN where unknown)."""
        pts = as_points(xy, "xy")
        k = self._check_k(k)
        _check_stage(stage)
        if not self._usable(k, stage):
            return np.full_like(pts, np.nan)
        model, field, consistency = self.local_stage(k) if stage == "local" else (None,) * 3
        if field is None:
            return self._global_frame_to_base(k, pts)
        from registration.geometry import local_frame_to_base

        def own_local(q):
            return local_frame_to_base(lambda p: self._global_frame_to_base(k, p, model), field, q)

        if consistency is None:
            return own_local(pts)
        return local_frame_to_base(own_local, consistency, pts)

    def base_to_frame(
        self, k: int, xy: ArrayLike, stage: str = "local", *, clip: bool = True
    ) -> NDArray[np.float64]:
        """``(N, 2)`` base pixels -> ``(N, 2)`` raw pixels of frame ``k`` (NaN where unknown).

        ``clip=False`` (beyond the fixed interface): points whose raw px fall beyond the frame's
        edge keep them instead of NaN, the same mapping carried on, for a caller that
        interpolates between points on both sides of the edge and masks by the raw px itself
        (:func:`registration.traffic.background.warp_frame`)."""
        pts = as_points(xy, "xy")
        k = self._check_k(k)
        _check_stage(stage)
        if not self._usable(k, stage):
            return np.full_like(pts, np.nan)
        model, field, consistency = self.local_stage(k) if stage == "local" else (None,) * 3
        if field is None:
            return self._global_base_to_frame(k, pts, clip=clip)
        from registration.geometry import local_base_to_frame

        def own_local(b):
            return local_base_to_frame(
                lambda x: self._global_base_to_frame(k, x, model, clip), field, b
            )

        if consistency is None:
            return own_local(pts)
        return local_base_to_frame(own_local, consistency, pts)

    # -- map coordinates (georeferenced base) --------------------------------------------------
    def _require_georef(self):
        if self.georef is None:
            raise NotGeoreferenced(
                f"the base map of {self.out_dir} is not georeferenced: no map coordinates "
                "(register with a GeoTIFF or a world-file base)",
                self.out_dir,
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


def _field(arrays: dict, prefix: str):
    if prefix + "vectors" not in arrays:
        return None
    from registration.geometry import DisplacementField

    return DisplacementField.from_arrays(arrays, prefix)


def load_result(out_dir: str | Path) -> RegistrationResult:
    """Open a result folder (see :class:`RegistrationResult`)."""
    return RegistrationResult(out_dir)
