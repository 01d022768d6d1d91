"""The frames' camera: Harris γ, the raw frame size and the exact Harris model made from them
(paper section 3, ``conventions.md``), built once per run and passed to every stage; beyond
the paper, a fourth-order radial term ``k2`` that the registration may estimate
(:mod:`registration.lens.k2`) when the lens is not exactly Harris.

The stages need the lens only through its model of the frame size: raw pixels to corrected
ones and back, the corrected frame on the raw frame's canvas, and where a grid or the outline of
the raw frame lies in corrected pixels. :class:`Camera` holds that model and gives exactly those
conversions, so no stage rebuilds it from a bare γ.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import frame_outline, image_size
from registration.lens.correction import undistort_image
from registration.lens.radial import HarrisModel, TwoTermHarrisModel


@dataclass(frozen=True)
class Camera:
    """The camera of a sequence's raw frames.

    Attributes:
        gamma: Harris radial distortion γ (paper eq. 4; 0.7 for the paper's camera).
        width, height: raw frame size in pixels.
        k2: beyond the paper: the lens's fourth-order radial term
            (:class:`registration.lens.radial.TwoTermHarrisModel`); 0 = exactly Harris.
        lens: the radial model of that γ, k2 and size, centred on the frame (built once; the
            run's distortion centre is the frame centre, ``conventions.md``): the
            :class:`HarrisModel` itself when ``k2`` is 0.
    """

    gamma: float
    width: int
    height: int
    k2: float = 0.0
    lens: HarrisModel | TwoTermHarrisModel = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "gamma", float(self.gamma))
        object.__setattr__(self, "k2", float(self.k2))
        lens = (
            TwoTermHarrisModel(self.gamma, self.k2, self.width, self.height)
            if self.k2
            else HarrisModel(self.gamma, self.width, self.height)
        )
        object.__setattr__(self, "lens", lens)

    @classmethod
    def of(cls, frame: NDArray, gamma: float) -> Camera:
        """The camera of ``frame`` (``(H, W[, C])``, raw) with Harris ``gamma``."""
        return cls(gamma, *image_size(frame))

    def with_k2(self, k2: float) -> Camera:
        """The same camera with the fourth-order term ``k2``."""
        return Camera(self.gamma, self.width, self.height, k2)

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` of the raw frames."""
        return self.width, self.height

    def corrected_from_raw(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` raw pixels -> ``(N, 2)`` corrected pixels."""
        return self.lens.corrected_from_raw(xy)

    def raw_from_corrected(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` corrected pixels -> ``(N, 2)`` raw pixels (NaN where undefined)."""
        return self.lens.raw_from_corrected(xy)

    def stretch(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N,)``: how much the radial correction enlarges the raw image at each of ``(N, 2)``
        corrected pixels, ``sqrt |det J|`` of corrected-from-raw there (1 at the centre; 1
        where the point has no raw pixel)."""
        raw = self.raw_from_corrected(xy)
        h = 0.5
        dx = self.corrected_from_raw(raw + [h, 0.0]) - self.corrected_from_raw(raw - [h, 0.0])
        dy = self.corrected_from_raw(raw + [0.0, h]) - self.corrected_from_raw(raw - [0.0, h])
        out = np.sqrt(np.abs(dx[:, 0] * dy[:, 1] - dx[:, 1] * dy[:, 0])) / (2 * h)
        return np.where(np.isfinite(out) & (out > 0), out, 1.0)

    def raw_radius(self) -> NDArray[np.float32]:
        """``(H, W)``: each raw pixel's distance from the frame's centre as a share of the
        half-diagonal (0 at the centre, 1 in the corners)."""
        w, h = self.size
        ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
        return np.hypot(xs - (w - 1) / 2, ys - (h - 1) / 2) / np.float32(np.hypot(w, h) / 2)

    def outline(self, per_edge: int = 32) -> NDArray[np.float64]:
        """The raw frame's border (:func:`registration.coords.frame_outline`) in corrected
        pixels: under a ``base_from_corrected`` model, the frame's footprint."""
        return self.corrected_from_raw(frame_outline(self.width, self.height, per_edge))

    def grid(self, nx: int, ny: int) -> NDArray[np.float64]:
        """An ``nx`` x ``ny`` grid over the raw frame, corners included, in corrected pixels
        (row by row)."""
        gx, gy = np.meshgrid(
            np.linspace(0, self.width - 1, nx), np.linspace(0, self.height - 1, ny)
        )
        return self.corrected_from_raw(np.c_[gx.ravel(), gy.ravel()])

    def cell_centres(self, cells: int) -> NDArray[np.float64]:
        """Centres of a ``cells`` x ``cells`` grid of equal cells over the raw frame, in corrected
        pixels (row by row)."""
        t = (np.arange(cells) + 0.5) / cells
        gx, gy = np.meshgrid(t * self.width - 0.5, t * self.height - 0.5)
        return self.corrected_from_raw(np.c_[gx.ravel(), gy.ravel()])

    def undistort(self, frame_raw: NDArray) -> NDArray:
        """The radially corrected frame on the raw frame's canvas (paper section 3)."""
        self.check(frame_raw)
        return undistort_image(frame_raw, self.lens, canvas="same")[0]

    def check(self, frame: NDArray) -> None:
        """ValueError when ``frame`` is not of the camera's size."""
        if image_size(frame) != self.size:
            w, h = image_size(frame)
            raise ValueError(f"a {w}x{h} frame given to the camera of {self.width}x{self.height}")


def as_camera(camera: Camera | float, frame: NDArray) -> Camera:
    """``camera`` itself (checked against ``frame``'s size), or the camera of ``frame`` with
    Harris γ ``camera``: the library's entry points still take a bare γ."""
    if isinstance(camera, Camera):
        camera.check(frame)
        return camera
    return Camera.of(frame, camera)
