"""The control-point table (as in QGIS's Georeferencer) of one frame's fine fit.

Rows come from a fine result (``registration.global_registration.fine.FineResult`` of the reference
frame, or a registered frame's control points in a result folder) plus the analyst's edits:
points switched on or off, deleted, or added by hand. "Enabled" starts as what REQCON kept.
A re-fit is the least-squares fit of the same model (warm-started from the current one, the
whole frame as its domain) to the enabled points: what the Georeferencer does, and what makes
disabling the worst point never raise the RMS shown. Every number comes from ``registration``:
the model's ``apply`` for residuals, ``PolyProjective.estimate`` for the fit, the Harris model
for raw <-> corrected pixels.

Library API that would be cleaner (reported to the lead): ``global_registration.refit_fine(
src, dst, enabled, start, config, domain) -> FineResult`` (this module's :func:`refit`), and
``register_intra(..., extra_points=...)`` so a manual point can rescue a sequence frame too.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

SOURCE_NAMES = {
    "reference": {0: "template"},
    "template": {0: "template", 1: "template (prev. frame)"},
    "gridded_sift": {0: "SIFT", 1: "SIFT (prev. frame)"},
}
"""Names of ``FineResult.source`` codes by how the points were found."""

MANUAL = "manual"
SORTS = ("residual", "id")


@dataclass
class Edits:
    """The analyst's changes to a frame's automatic control points.

    Attributes:
        enabled: ``{id: bool}`` for automatic points switched on or off (default: REQCON's kept).
        deleted: ids of automatic points removed from the table.
        manual: points added by hand, ``(fx, fy, bx, by)``: raw frame px, base px.
    """

    enabled: dict[int, bool] = field(default_factory=dict)
    deleted: set[int] = field(default_factory=set)
    manual: list[tuple[float, float, float, float]] = field(default_factory=list)
    manual_enabled: dict[int, bool] = field(default_factory=dict)

    @property
    def empty(self) -> bool:
        return not (self.enabled or self.deleted or self.manual)

    def to_json(self) -> dict:
        return {
            "enabled": {str(k): bool(v) for k, v in sorted(self.enabled.items())},
            "deleted": sorted(int(i) for i in self.deleted),
            "manual": [[float(v) for v in m] for m in self.manual],
            "manual_enabled": {str(k): bool(v) for k, v in sorted(self.manual_enabled.items())},
        }

    @classmethod
    def from_json(cls, data) -> Edits:
        """Edits from :meth:`to_json`'s dict; malformed parts are dropped."""
        out = cls()
        if not isinstance(data, dict):
            return out
        try:
            out.enabled = {int(k): bool(v) for k, v in dict(data.get("enabled", {})).items()}
            out.deleted = {int(i) for i in data.get("deleted", [])}
            out.manual = [tuple(float(v) for v in m) for m in data.get("manual", []) if len(m) == 4]
            out.manual_enabled = {
                int(k): bool(v) for k, v in dict(data.get("manual_enabled", {})).items()
            }
        except (TypeError, ValueError):
            return cls()
        return out

    def copy(self) -> Edits:
        return Edits(
            dict(self.enabled), set(self.deleted), list(self.manual), dict(self.manual_enabled)
        )


@dataclass
class ControlPointTable:
    """One frame's control points as rows (automatic ids ``0..M-1``, manual ``M..``).

    Attributes:
        ids: ``(N,)`` row ids.
        frame_xy: ``(N, 2)`` raw frame pixels.
        corrected_xy: ``(N, 2)`` corrected frame pixels (what the model maps).
        base_xy: ``(N, 2)`` base pixels.
        source: ``N`` names (:data:`SOURCE_NAMES`, or ``"manual"``).
        enabled: ``(N,)`` bool, used by the fit.
        kept_by_reqcon: ``(N,)`` bool, what REQCON kept (manual points: True).
        model: the fitted ``base_from_corrected`` model (None when the fit failed).
        residual_xy: ``(N, 2)`` ``model(corrected) - base`` in base px (NaN without a model).
        reason: why the fit failed ("" when it did not).
    """

    ids: NDArray[np.int_]
    frame_xy: NDArray[np.float64]
    corrected_xy: NDArray[np.float64]
    base_xy: NDArray[np.float64]
    source: list[str]
    enabled: NDArray[np.bool_]
    kept_by_reqcon: NDArray[np.bool_]
    model: object | None
    residual_xy: NDArray[np.float64]
    reason: str = ""

    @property
    def residual(self) -> NDArray[np.float64]:
        return np.hypot(self.residual_xy[:, 0], self.residual_xy[:, 1])

    @property
    def n_enabled(self) -> int:
        return int(self.enabled.sum())

    @property
    def rms(self) -> float:
        """RMS residual (base px) of the enabled points."""
        r = self.residual[self.enabled]
        r = r[np.isfinite(r)]
        return float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")

    def order(self, sort: str = "residual") -> NDArray[np.int_]:
        """Row positions sorted by residual (largest first, ties by id) or by id."""
        if sort == "id":
            return np.argsort(self.ids, kind="stable")
        r = np.where(np.isfinite(self.residual), self.residual, -1.0)
        return np.lexsort((self.ids, -r))

    def row(self, row_id: int) -> int | None:
        """Position of the row with id ``row_id``, or None."""
        hit = np.flatnonzero(self.ids == int(row_id))
        return int(hit[0]) if len(hit) else None

    def worst_enabled(self) -> int | None:
        """Id of the enabled point with the largest residual."""
        r = np.where(self.enabled & np.isfinite(self.residual), self.residual, -1.0)
        return int(self.ids[int(np.argmax(r))]) if (r >= 0).any() else None


def table_from_points(
    src_corrected: NDArray,
    dst: NDArray,
    kept: NDArray,
    source_codes: NDArray | None,
    kind: str,
    harris,
    model,
    edits: Edits | None = None,
) -> ControlPointTable:
    """Rows for automatic points (corrected frame px -> base px) plus the analyst's edits.

    ``model`` is the fit the residuals are shown for (the automatic one, or a re-fit).
    """
    edits = edits or Edits()
    src = np.asarray(src_corrected, np.float64).reshape(-1, 2)
    dst = np.asarray(dst, np.float64).reshape(-1, 2)
    kept = np.asarray(kept, bool).reshape(-1)
    m = len(src)
    names = SOURCE_NAMES.get(kind, {})
    codes = np.zeros(m, int) if source_codes is None else np.asarray(source_codes, int)
    source = [names.get(int(c), f"{kind} {int(c)}") for c in codes]
    enabled = kept.copy()
    for i, on in edits.enabled.items():
        if 0 <= i < m:
            enabled[i] = on
    alive = np.ones(m, bool)
    alive[[i for i in edits.deleted if 0 <= i < m]] = False
    ids = np.arange(m)[alive]
    frame_raw = harris.raw_from_corrected(src[alive]) if m else np.zeros((0, 2))
    man = np.asarray(edits.manual, np.float64).reshape(-1, 4)
    man_ids = np.arange(m, m + len(man))
    man_raw = man[:, :2]
    man_corr = harris.corrected_from_raw(man_raw) if len(man) else np.zeros((0, 2))
    man_on = np.array([edits.manual_enabled.get(int(i), True) for i in man_ids], bool)
    corrected = np.concatenate([src[alive], man_corr])
    base = np.concatenate([dst[alive], man[:, 2:]])
    table = ControlPointTable(
        ids=np.concatenate([ids, man_ids]).astype(int),
        frame_xy=np.concatenate([frame_raw, man_raw]),
        corrected_xy=corrected,
        base_xy=base,
        source=[s for s, a in zip(source, alive, strict=True) if a] + [MANUAL] * len(man),
        enabled=np.concatenate([enabled[alive], man_on]),
        kept_by_reqcon=np.concatenate([kept[alive], np.ones(len(man), bool)]),
        model=model,
        residual_xy=np.full((len(corrected), 2), np.nan),
    )
    return with_residuals(table, model)


def with_residuals(table: ControlPointTable, model, reason: str = "") -> ControlPointTable:
    """The table with ``model`` and its residuals ``model(corrected) - base``."""
    res = np.full((len(table.ids), 2), np.nan)
    if model is not None and len(table.ids):
        with np.errstate(all="ignore"):
            res = np.asarray(model.apply(table.corrected_xy), np.float64) - table.base_xy
    return replace(table, model=model, residual_xy=res, reason=reason)


def refit(table: ControlPointTable, start, *, domain=None, optimizer: str = "lm"):
    """Least-squares re-fit of ``start``'s model type and degree to the enabled rows.

    Returns ``(table with the new model's residuals, model or None)``; on failure the table keeps
    no model and ``reason`` says why (e.g. too few enabled points for the degree).
    """
    en = table.enabled & np.isfinite(table.corrected_xy).all(axis=1)
    en &= np.isfinite(table.base_xy).all(axis=1)
    fit = type(start).estimate(
        table.corrected_xy[en], table.base_xy[en], initial=start, optimizer=optimizer, domain=domain
    )
    if not fit:
        return with_residuals(table, None, reason=str(getattr(fit, "reason", fit))), None
    return with_residuals(table, fit), fit


def write_qgis_points(table: ControlPointTable, path, georef=None):
    """The table as a QGIS Georeferencer ``.points`` file at ``path`` (written atomically by
    :func:`registration.gis.vector.write_points_file`, the format QGIS 3 saves); returns the path.

    Source: the raw frame in QGIS's pixel coordinates (corner of the top-left pixel at (0, 0),
    rows negative: raw ``(x, y)`` is ``(x + 0.5, -(y + 0.5))``). Map: with a georeferenced base
    (``georef``, :class:`registration.gis.georef.GeoReference`) the points' map coordinates in its CRS
    (``#CRS:`` line), as QGIS expects; without one the base map's own pixel grid
    (:data:`registration.gis.georef.PIXEL_GRID`, the source's corner/y-up convention), as the
    export writes them. ``dX``, ``dY``, ``residual``: ``model(frame point) - map point`` in
    map units (base px without a georeference; 0 where there is no model).
    """
    from registration.gis import write_points_file
    from registration.gis.georef import PIXEL_GRID

    base = np.asarray(table.base_xy, np.float64).reshape(-1, 2)
    res = np.nan_to_num(np.asarray(table.residual_xy, np.float64).reshape(-1, 2), nan=0.0)
    grid = PIXEL_GRID if georef is None else georef  # a plain base: its own pixel grid
    map_xy = grid.map_from_base(base)
    residual = grid.map_from_base(base + res) - map_xy
    crs = grid.crs_wkt
    return write_points_file(
        path, table.frame_xy, map_xy, crs_wkt=crs, enabled=table.enabled, residual_xy=residual
    )


def read_qgis_points(path, frame_size, base_size, georef=None) -> tuple[NDArray, NDArray]:
    """Manual points ``(N, 4)`` (raw frame px, base px) and their ``enable`` column ``(N,)``
    from a QGIS Georeferencer ``.points`` file, the inverse of :func:`write_qgis_points`:
    the source is the frame, the map the base map's CRS where it is georeferenced (the file's
    ``#CRS:`` must then be the same, when it has one), else its pixels in QGIS's corner/y-up
    convention.

    Raises:
        ValueError: one line naming the file and the problem (malformed, another CRS, a map
            CRS for a plain image, a point outside the frame or the map).
    """
    from pathlib import Path

    from registration.gis import parse_crs, read_points_file
    from registration.gis.georef import PIXEL_GRID

    name = Path(path).name
    data = read_points_file(path)
    crs = data["crs"]
    if georef is None and crs:
        raise ValueError(
            f"{name}: its map coordinates are in {parse_crs(crs).name}, and the base map has no "
            "georeference"
        )
    if georef is not None and crs and georef.crs is not None:
        if not parse_crs(crs).equals(georef.crs):
            raise ValueError(
                f"{name}: its map coordinates are in {parse_crs(crs).name}, the base map's in "
                f"{georef.crs.name}"
            )
    grid = PIXEL_GRID if georef is None else georef  # a plain base: its own pixel grid
    base = grid.base_from_map(data["map"]) if len(data["map"]) else data["map"]
    src = data["source"]
    if not len(src):
        raise ValueError(f"{name}: no control points")
    for i, (f, b) in enumerate(zip(src, base, strict=True)):
        for what, xy, (w, h) in (("frame", f, frame_size), ("map", b, base_size)):
            if not (-0.5 <= xy[0] <= w - 0.5 and -0.5 <= xy[1] <= h - 0.5):
                raise ValueError(
                    f"{name} point {i + 1}: its {what} point ({xy[0]:.1f}, {xy[1]:.1f}) is "
                    f"outside the {w}x{h} {what}"
                )
    return np.c_[src, base], data["enable"]
