"""The displacement field (paper section 5): a regular grid of vectors in base px, its sampling,
serialisation and node lattice, and mapping images and points through it.

Layout and direction: node ``(i, j)`` (row ``i``, column ``j``) sits at base pixel ``origin + (j,
i) * spacing``; ``vectors`` is ``(Gy, Gx, 2)`` float32 ``(dx, dy)`` in base px; ``valid`` marks
the nodes whose vector was measured (the others are filled from their neighbours).
``registered_local(x) = registered_global(x + d(x))``: ``d(x)`` says where, in the globally
registered frame (base px), the content that belongs at base pixel ``x`` actually is; hence
``base_to_frame_local(x) = base_to_frame_global(x + d(x))``, and ``frame_to_base_local(q)`` solves
``x + d(x) = frame_to_base_global(q)`` (:func:`local_frame_to_base`). The field is estimated by
:mod:`registration.local`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points
from registration.geometry import warp

# --------------------------------------------------------------------------------------------
# Applying the field


def apply_field(
    image: NDArray,
    field_: DisplacementField,
    origin: tuple[float, float] = (0.0, 0.0),
    *,
    interpolation: str = "linear",
    border_value: float | tuple[float, ...] = 0,
) -> NDArray:
    """Locally register a globally registered image: ``out(x) = image(x + d(x))``.

    Args:
        image: ``(H, W[, C])`` globally registered frame over a crop of base px starting at
            ``origin``.
    Returns:
        Same shape and dtype; pixels outside the field get ``border_value``.
    """
    h, w = image.shape[:2]
    source = warp.pixel_grid(w, h) + field_.dense(w, h, origin)
    return warp.remap(image, source, interpolation=interpolation, border_value=border_value)


def local_base_to_frame(
    global_base_to_frame: Callable[[NDArray], NDArray], field_: DisplacementField, xy: ArrayLike
) -> NDArray[np.float64]:
    """``base_to_frame_local(x) = base_to_frame_global(x + d(x))``; ``(N, 2)`` base px -> frame px.

    Beyond the field's extent the field is extended constantly (``sample(outside="clamp")``):
    the global mapping decides what is covered. NaN where it does not cover a point."""
    x = as_points(xy, "xy")
    return np.asarray(global_base_to_frame(x + field_.sample(x, outside="clamp")), np.float64)


def local_frame_to_base(
    global_frame_to_base: Callable[[NDArray], NDArray],
    field_: DisplacementField,
    xy: ArrayLike,
    *,
    tol_px: float = 1e-4,
    max_iterations: int = 100,
) -> NDArray[np.float64]:
    """Frame px -> base px through the global mapping and the field.

    Solves ``x + d(x) = g(q)`` with ``g = global_frame_to_base`` by the fixed-point iteration
    ``x <- g(q) - d(x)``, which converges because the field is smooth (its gradient is far below 1:
    a few px over 200 px). Beyond the field's extent the field is extended constantly, as in
    :func:`local_base_to_frame`. NaN where ``g`` is NaN or the iteration has not converged to
    ``tol_px``.
    """
    q = as_points(xy, "xy")
    y = np.asarray(global_frame_to_base(q), np.float64)
    x = y - np.nan_to_num(field_.sample(y, outside="clamp"))
    done = ~np.isfinite(y).all(axis=1)
    for _ in range(max_iterations):
        todo = ~done
        if not todo.any():
            break
        d = field_.sample(x[todo], outside="clamp")
        x_new = y[todo] - d
        step = np.linalg.norm(x_new - x[todo], axis=1)
        x[todo] = x_new
        conv = step < tol_px
        idx = np.nonzero(todo)[0]
        done[idx[conv | ~np.isfinite(step)]] = True
    final = x + field_.sample(x, outside="clamp") - y
    bad = ~(np.linalg.norm(final, axis=1) < 10 * tol_px)
    x[bad] = np.nan
    return x


@dataclass(frozen=True)
class DisplacementField:
    """A grid of displacement vectors in base pixels (layout and direction: module docstring).

    Attributes:
        origin: ``(x0, y0)`` base px of grid node ``(0, 0)``.
        spacing: distance between nodes in base px (paper: 200).
        vectors: ``(Gy, Gx, 2)`` float32 ``(dx, dy)`` base px; complete (invalid nodes filled).
        valid: ``(Gy, Gx)`` bool, True where the vector was measured.

    The field covers the nodes' cells: ``[x0 - spacing/2, x0 + (Gx - 1/2) spacing]`` and likewise
    in y; outside it :meth:`sample` returns NaN. Inside, it is bilinear between nodes and constant
    beyond the outermost nodes.
    """

    origin: tuple[float, float]
    spacing: float
    vectors: NDArray[np.float32]
    valid: NDArray[np.bool_]

    def __post_init__(self) -> None:
        v = np.asarray(self.vectors)
        if v.ndim != 3 or v.shape[2] != 2 or v.shape[0] < 1 or v.shape[1] < 1:
            raise ValueError(f"vectors must have shape (Gy, Gx, 2), got {v.shape}")
        if np.asarray(self.valid).shape != v.shape[:2]:
            raise ValueError(
                f"valid must have shape {v.shape[:2]}, got {np.asarray(self.valid).shape}"
            )
        if not self.spacing > 0:
            raise ValueError(f"spacing must be positive, got {self.spacing}")

    @property
    def shape(self) -> tuple[int, int]:
        """``(Gy, Gx)``."""
        return int(self.vectors.shape[0]), int(self.vectors.shape[1])

    @property
    def node_xy(self) -> NDArray[np.float64]:
        """``(Gy, Gx, 2)`` base px of every node."""
        gy, gx = self.shape
        xs = self.origin[0] + self.spacing * np.arange(gx)
        ys = self.origin[1] + self.spacing * np.arange(gy)
        mx, my = np.meshgrid(xs, ys, indexing="xy")
        return np.stack([mx, my], axis=-1)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(x_min, y_min, x_max, y_max)`` base px covered by the field."""
        gy, gx = self.shape
        h = self.spacing / 2.0
        return (
            self.origin[0] - h,
            self.origin[1] - h,
            self.origin[0] + (gx - 1) * self.spacing + h,
            self.origin[1] + (gy - 1) * self.spacing + h,
        )

    def _weights(self, coord: NDArray, o: float, n: int):
        u = (coord - o) / self.spacing
        inside = (u >= -0.5) & (u <= n - 0.5)
        u = np.clip(np.where(np.isfinite(u), u, 0.0), 0.0, n - 1.0)
        i0 = np.minimum(np.floor(u).astype(np.intp), max(n - 2, 0))
        f = u - i0
        i1 = np.minimum(i0 + 1, n - 1)
        return i0, i1, f, inside

    def bilinear(self, xy: ArrayLike) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
        """How :meth:`sample` (``outside="clamp"``) interpolates at base points ``(N, 2)``: the
        flat (row-major) indices ``(N, 4)`` of the nodes it reads and their weights ``(N, 4)``
        (for solving for node values that interpolate to given values)."""
        p = as_points(xy, "xy")
        gy, gx = self.shape
        with np.errstate(invalid="ignore"):
            j0, j1, fx, _ = self._weights(p[:, 0], self.origin[0], gx)
            i0, i1, fy, _ = self._weights(p[:, 1], self.origin[1], gy)
        idx = np.stack([i0 * gx + j0, i0 * gx + j1, i1 * gx + j0, i1 * gx + j1], axis=1)
        w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
        return idx, w

    def sample(self, xy: ArrayLike, *, outside: str = "nan") -> NDArray[np.float64]:
        """Displacement at base points: ``(N, 2)`` -> ``(N, 2)`` base px.

        Args:
            outside: what points outside the field get: "nan" or "clamp" (the value at the
                nearest point of the field, i.e. constant extrapolation like the filling of
                cells without a measurement).
        """
        if outside not in ("nan", "clamp"):
            raise ValueError(f"outside must be 'nan' or 'clamp', got {outside!r}")
        p = as_points(xy, "xy")
        gy, gx = self.shape
        v = self.vectors.astype(np.float64)
        with np.errstate(invalid="ignore"):
            j0, j1, fx, in_x = self._weights(p[:, 0], self.origin[0], gx)
            i0, i1, fy, in_y = self._weights(p[:, 1], self.origin[1], gy)
        fx, fy = fx[:, None], fy[:, None]
        out = (
            v[i0, j0] * (1 - fx) * (1 - fy)
            + v[i0, j1] * fx * (1 - fy)
            + v[i1, j0] * (1 - fx) * fy
            + v[i1, j1] * fx * fy
        )
        if outside == "nan":
            out[~(in_x & in_y)] = np.nan
        out[~np.isfinite(p).all(axis=1)] = np.nan
        return out

    def dense(
        self, width: int, height: int, origin: tuple[float, float] = (0.0, 0.0)
    ) -> NDArray[np.float32]:
        """The field at every pixel of a ``width`` x ``height`` crop of the base whose pixel
        ``(0, 0)`` is base ``origin``: ``(height, width, 2)`` float32, NaN outside the field.

        Same values as :meth:`sample` (bilinear, separable so it costs two passes).
        """
        gy, gx = self.shape
        xs = origin[0] + np.arange(width, dtype=np.float64)
        ys = origin[1] + np.arange(height, dtype=np.float64)
        j0, j1, fx, in_x = self._weights(xs, self.origin[0], gx)
        i0, i1, fy, in_y = self._weights(ys, self.origin[1], gy)
        v = self.vectors.astype(np.float32)
        fx32 = fx.astype(np.float32)[None, :, None]
        rows = v[:, j0] * (1 - fx32) + v[:, j1] * fx32  # (Gy, W, 2)
        fy32 = fy.astype(np.float32)[:, None, None]
        out = rows[i0] * (1 - fy32) + rows[i1] * fy32  # (H, W, 2)
        out[~in_y, :, :] = np.nan
        out[:, ~in_x, :] = np.nan
        return out

    def to_arrays(self) -> dict[str, NDArray]:
        """Plain arrays for ``np.savez`` (round trip: :meth:`from_arrays`)."""
        return {
            "origin": np.asarray(self.origin, np.float64),
            "spacing": np.asarray(self.spacing, np.float64),
            "vectors": np.asarray(self.vectors, np.float32),
            "valid": np.asarray(self.valid, bool),
        }

    def to_dict(self) -> dict[str, NDArray]:
        """Alias of :meth:`to_arrays`."""
        return self.to_arrays()

    @classmethod
    def from_arrays(cls, arrays: Any, prefix: str = "") -> DisplacementField:
        """Rebuild from :meth:`to_arrays` output (a dict or an ``np.load`` NpzFile); keys may carry
        ``prefix`` (e.g. ``"field_"``)."""
        origin = np.asarray(arrays[prefix + "origin"], np.float64)
        return cls(
            origin=(float(origin[0]), float(origin[1])),
            spacing=float(np.asarray(arrays[prefix + "spacing"])),
            vectors=np.asarray(arrays[prefix + "vectors"], np.float32),
            valid=np.asarray(arrays[prefix + "valid"], bool),
        )

    @classmethod
    def zeros(
        cls, width: int, height: int, spacing: float, origin: tuple[float, float] = (0.0, 0.0)
    ):
        """An all-zero, all-invalid field on the grid :func:`grid_nodes` lays over the crop."""
        (ox, oy), (gx, gy) = grid_nodes(width, height, spacing, origin)
        return cls(
            (ox, oy), float(spacing), np.zeros((gy, gx, 2), np.float32), np.zeros((gy, gx), bool)
        )


# --------------------------------------------------------------------------------------------
# Grid


def grid_nodes(
    width: int, height: int, spacing: float, origin: tuple[float, float] = (0.0, 0.0)
) -> tuple[tuple[float, float], tuple[int, int]]:
    """Lay a node grid over a ``width`` x ``height`` crop whose pixel (0,0) is base ``origin``.

    Nodes sit on the base map's lattice of multiples of ``spacing`` (so a crop that moves by a
    pixel, e.g. because the global model changed in its last digits, keeps the same nodes, and
    all frames' fields share one lattice); the first node is at or left of/above the crop's first
    pixel and the last at or beyond its last, so the nodes' cells cover the whole crop. A 1280
    wide crop at x = 0 with spacing 200 gets nodes at 0, 200, ..., 1400 (8).

    Returns:
        ``((x0, y0), (Gx, Gy))``: base px of node (0, 0) and the grid size.
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"crop size must be positive, got {width}x{height}")
    if not spacing > 0:
        raise ValueError(f"spacing must be positive, got {spacing}")

    def axis(o: float, n: int) -> tuple[float, int]:
        first = np.floor(o / spacing + 1e-9) * spacing
        last = np.ceil((o + n - 1) / spacing - 1e-9) * spacing
        return float(first), int(round((last - first) / spacing)) + 1

    x0, gx = axis(float(origin[0]), width)
    y0, gy = axis(float(origin[1]), height)
    return (x0, y0), (gx, gy)
