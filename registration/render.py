"""Registered outputs (paper sections 5 and 6): frames rendered into base-map pixels, cropped to
the sequence's footprint, an mp4 of them, the displacement field's components as images (paper
Fig. 5) and semi-transparent overlays of a frame over the reference (paper Fig. 6).

Pure functions return arrays (BGR uint8, like cv2); the ``write_*`` functions write files
atomically (temporary file + ``os.replace``), so a reader never sees half a file.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from registration import warp
from registration.camera import Camera, as_camera
from registration.coords import frame_outline, image_size
from registration.io import read_image, write_image_atomic
from registration.local import DisplacementField

Box = tuple[int, int, int, int]  # (x0, y0, width, height) in base px


def render_to_base(
    frame_raw: NDArray,
    camera: Camera | float,
    base_from_corrected,
    box: tuple[int, int, int, int],
    field=None,
) -> tuple[NDArray, NDArray[np.bool_]]:
    """The raw frame resampled once into the base-pixel box ``(x0, y0, x1, y1)``, with its
    validity mask: base pixels map to raw pixels through the displacement field (when given:
    ``x + d(x)``, :mod:`registration.local`), the model's inverse and the Harris model
    (:func:`render_registered`), so the frame is interpolated only once. ``camera``: the frames'
    :class:`registration.camera.Camera` (or their Harris γ)."""
    camera = as_camera(camera, frame_raw)
    x0, y0, x1, y1 = box

    def raw_from_base(b):
        if field is not None:
            b = b + field.sample(b, outside="clamp")
        return camera.raw_from_corrected(base_from_corrected.inverse(b))

    return warp.warp_image(frame_raw, raw_from_base, x1 - x0, y1 - y0, origin=(x0, y0))


def render_registered(
    frame_raw: NDArray,
    base_to_frame_fn: Callable[[NDArray], NDArray],
    out_size: tuple[int, int],
    origin: tuple[float, float] = (0.0, 0.0),
    *,
    step: int = 8,
    interpolation: str = "linear",
    return_mask: bool = False,
):
    """A raw frame rendered into base pixels.

    Args:
        frame_raw: ``(H, W[, C])`` the frame as recorded.
        base_to_frame_fn: ``(N, 2)`` base px -> ``(N, 2)`` raw px of the frame (NaN = none), e.g.
            ``lambda b: result.base_to_frame(k, b, "local")``.
        out_size: ``(width, height)`` of the output crop.
        origin: base px of output pixel ``(0, 0)``.
        step: the mapping is evaluated every ``step`` px and interpolated in between
            (:func:`registration.warp.source_map_from_function`).
        return_mask: also return the ``(height, width)`` bool mask of pixels with data.

    Returns:
        The image (``frame_raw``'s dtype and channels; 0 where the frame has no data), or
        ``(image, mask)``.
    """
    w, h = (int(v) for v in out_size)
    if w <= 0 or h <= 0:
        raise ValueError(f"output size must be positive, got {w}x{h}")
    source = warp.source_map_from_function(
        base_to_frame_fn, w, h, step=step, origin=origin, source_size=image_size(frame_raw)
    )
    if step > 1:
        # The coarse map is NaN wherever one of the surrounding nodes falls outside the frame,
        # which would eat up to ``step`` px of every frame border: evaluate that band exactly.
        nan = ~np.isfinite(source).all(axis=2)
        if nan.any() and not nan.all():
            k = np.ones((2 * step + 1, 2 * step + 1), np.uint8)
            band = nan & (cv2.dilate((~nan).astype(np.uint8), k) > 0)
            ys, xs = np.nonzero(band)
            pts = np.c_[xs + float(origin[0]), ys + float(origin[1])]
            source[ys, xs] = np.asarray(base_to_frame_fn(pts), np.float32)
    image = warp.remap(frame_raw, source, interpolation=interpolation)
    if not return_mask:
        return image
    fw, fh = image_size(frame_raw)
    with np.errstate(invalid="ignore"):
        mask = (
            np.isfinite(source).all(axis=2)
            & (source[..., 0] >= -0.5)
            & (source[..., 0] <= fw - 0.5)
            & (source[..., 1] >= -0.5)
            & (source[..., 1] <= fh - 0.5)
        )
    return image, mask


def footprint(
    frame_to_base_fns: Iterable[Callable[[NDArray], NDArray]],
    frame_size: tuple[int, int],
    base_size: tuple[int, int] | None = None,
    *,
    pad: int = 0,
) -> Box:
    """Bounding box of the union of the frames' footprints in base pixels.

    Args:
        frame_to_base_fns: one ``(N, 2)`` raw px -> ``(N, 2)`` base px mapping per frame (failed
            frames may return NaN; they are skipped).
        frame_size: ``(W, H)`` of the raw frames.
        base_size: clip the box to the base map ``(W, H)``; None = no clipping.
        pad: px added on every side before clipping.

    Returns:
        ``(x0, y0, width, height)`` integers; ``(0, 0, 0, 0)`` when no frame maps anywhere.
    """
    outline = frame_outline(*frame_size)
    lo = np.array([np.inf, np.inf])
    hi = -lo
    for fn in frame_to_base_fns:
        pts = np.asarray(fn(outline), float)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if len(pts):
            lo = np.minimum(lo, pts.min(axis=0))
            hi = np.maximum(hi, pts.max(axis=0))
    if not np.isfinite(lo).all():
        return 0, 0, 0, 0
    x0, y0 = np.floor(lo).astype(int) - pad
    x1, y1 = np.ceil(hi).astype(int) + 1 + pad
    if base_size is not None:
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, int(base_size[0])), min(y1, int(base_size[1]))
    return int(x0), int(y0), int(max(x1 - x0, 0)), int(max(y1 - y0, 0))


# --------------------------------------------------------------------------------------------
# Field component images (paper Fig. 5)


def diverging_colormap(values: NDArray, limit: float) -> NDArray[np.uint8]:
    """Blue (-limit) - white (0) - red (+limit) BGR colours for ``values`` (NaN -> grey)."""
    t = np.clip(np.nan_to_num(values / max(limit, 1e-9)), -1.0, 1.0)
    pos = np.clip(t, 0, 1)
    neg = np.clip(-t, 0, 1)
    # BGR: red = (0, 0, 255), blue = (255, 0, 0); fade from white.
    b = 255 * (1 - pos)
    g = 255 * (1 - pos) * (1 - neg)
    r = 255 * (1 - neg)
    out = np.clip(np.stack([b, g, r], axis=-1), 0, 255).astype(np.uint8)
    out[~np.isfinite(values)] = (128, 128, 128)
    return out


def _legend(height: int, limit: float, title: str, width: int = 90) -> NDArray[np.uint8]:
    """A vertical colour bar ``(height, width, 3)`` from +limit (top) to -limit with ticks."""
    panel = np.full((height, width, 3), 255, np.uint8)
    top, bottom = 28, max(height - 12, 40)
    bar_h = max(bottom - top, 2)
    vals = np.linspace(limit, -limit, bar_h)[:, None] * np.ones((1, 18))
    panel[top : top + bar_h, 8:26] = diverging_colormap(vals, limit)
    cv2.rectangle(panel, (8, top), (25, top + bar_h - 1), (0, 0, 0), 1)
    cv2.putText(panel, title, (4, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for frac, v in ((0.0, limit), (0.5, 0.0), (1.0, -limit)):
        y = int(round(top + frac * (bar_h - 1)))
        cv2.line(panel, (26, y), (31, y), (0, 0, 0), 1)
        cv2.putText(
            panel,
            f"{v:+.2f}" if v else "0",
            (33, y + 4),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.4,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    return panel


def field_component_images(
    field: DisplacementField,
    width: int,
    height: int,
    origin: tuple[float, float] = (0.0, 0.0),
    *,
    limit_px: float | None = None,
    legend: bool = True,
    show_nodes: bool = True,
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """The interpolated field's horizontal and vertical components as images (paper Fig. 5).

    Args:
        field: the displacement field.
        width, height, origin: the base crop to draw (e.g. the frame's footprint box).
        limit_px: colour scale +-limit px for both images (None = per component, the largest
            magnitude among the measured vectors, at least 0.5 px; larger values saturate).
        legend: append a colour bar with the scale in px on the right.
        show_nodes: mark the grid nodes (filled dot: measured; ring: filled from neighbours).

    Returns:
        ``(u_img, v_img)`` BGR uint8 ``(height, width [+ legend], 3)``; grey outside the field.
    """
    d = field.dense(width, height, origin)
    # Scale to the measured vectors: filled cells at the edge of a footprint can carry
    # extrapolated values that would wash out the colours of the rest.
    vec = field.vectors[field.valid] if field.valid.any() else field.vectors.reshape(-1, 2)
    images = []
    for c, title in ((0, "dx px"), (1, "dy px")):
        limit = limit_px if limit_px is not None else float(max(np.abs(vec[:, c]).max(), 0.5))
        img = diverging_colormap(d[..., c], limit)
        if show_nodes:
            nodes = field.node_xy.reshape(-1, 2) - np.asarray(origin)
            for (x, y), ok in zip(nodes, field.valid.ravel(), strict=True):
                if 0 <= x < width and 0 <= y < height:
                    p = (int(round(x)), int(round(y)))
                    cv2.circle(img, p, 3, (0, 0, 0), -1 if ok else 1, cv2.LINE_AA)
        if legend:
            img = np.concatenate([img, _legend(height, limit, title)], axis=1)
        images.append(img)
    return images[0], images[1]


# --------------------------------------------------------------------------------------------
# Overlay (paper Fig. 6)


def _bgr(image: NDArray) -> NDArray[np.uint8]:
    image = np.asarray(image)
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def overlay(
    frame_registered: NDArray,
    reference: NDArray,
    alpha: float = 0.5,
    *,
    mask: NDArray | None = None,
) -> NDArray[np.uint8]:
    """Frame k semi-transparently over the reference (paper Fig. 6).

    Args:
        frame_registered: ``(H, W[, 3])`` uint8 registered frame (base px crop).
        reference: same size, the reference (mid base image) over the same crop.
        alpha: opacity of the frame, 0..1.
        mask: ``(H, W)`` where the frame has data (None = everywhere); elsewhere the reference
            shows alone.

    Returns:
        ``(H, W, 3)`` BGR uint8.
    """
    if not 0 <= alpha <= 1:
        raise ValueError(f"alpha must be in [0, 1], got {alpha}")
    a, b = _bgr(frame_registered), _bgr(reference)
    if a.shape != b.shape:
        raise ValueError(f"frame {a.shape} and reference {b.shape} differ in size")
    out = cv2.addWeighted(a, alpha, b, 1 - alpha, 0.0)
    if mask is not None:
        out[~np.asarray(mask, bool)] = b[~np.asarray(mask, bool)]
    return out


# --------------------------------------------------------------------------------------------
# Video


def write_video(
    frames: Iterable[NDArray | str | os.PathLike],
    out_mp4: str | os.PathLike,
    fps: float = 5.0,
    *,
    quality: int = 7,
) -> Path:
    """Write frames (BGR arrays or image paths, read one at a time) to an H.264 mp4 atomically.

    Frames are padded to even width and height (yuv420p needs it); all must have the first
    frame's size. Never holds more than one frame in memory.

    Args:
        frames: arrays ``(H, W[, 3])`` uint8 (BGR) or paths of images.
        out_mp4: output path (``.mp4``).
        fps: frames per second (paper: 5).
        quality: imageio-ffmpeg quality 0..10.

    Returns:
        The output path.
    """
    import imageio.v2 as imageio

    out = Path(out_mp4)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.stem}.", suffix=".tmp.mp4")
    os.close(fd)
    writer = None
    size = None
    n = 0
    try:
        for item in frames:
            img = read_image(item) if isinstance(item, (str, os.PathLike)) else _bgr(item)
            if img.dtype != np.uint8:
                raise ValueError(f"video frames must be uint8, got {img.dtype}")
            h, w = img.shape[:2]
            if size is None:
                size = (w, h)
                writer = imageio.get_writer(
                    tmp,
                    format="FFMPEG",
                    mode="I",
                    fps=fps,
                    codec="libx264",
                    pixelformat="yuv420p",
                    macro_block_size=1,
                    quality=quality,
                )
            elif (w, h) != size:
                raise ValueError(f"video frame {n} is {w}x{h}, the first was {size[0]}x{size[1]}")
            pad_w, pad_h = w % 2, h % 2
            if pad_w or pad_h:
                img = cv2.copyMakeBorder(img, 0, pad_h, 0, pad_w, cv2.BORDER_CONSTANT, value=0)
            writer.append_data(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
            n += 1
        if writer is None:
            raise ValueError(f"no frames to write to {out}")
        writer.close()
        writer = None
        os.replace(tmp, out)
    finally:
        if writer is not None:
            writer.close()
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


# --------------------------------------------------------------------------------------------
# A whole result


def write_registered_sequence(
    result: Any,
    frames: Any,
    out_dir: str | os.PathLike | None = None,
    *,
    stage: str = "local",
    fps: float = 5.0,
    overlays: bool = True,
    fields: bool = True,
    step: int = 8,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Render every frame of a result into base pixels, cropped to the sequence's footprint.

    Writes into ``out_dir`` (default ``result.out_dir / "registered"``):
    ``frames/KKKKKK.png`` (registered frame; black where the frame has no data or failed),
    ``overlay/KKKKKK.jpg`` (frame over the mid base image, alpha 0.5, paper Fig. 6),
    ``field/KKKKKK_dx.png`` and ``_dy.png`` (the field's components over the frame's footprint,
    paper Fig. 5) and ``registered.mp4`` (``fps`` frames/s).

    Args:
        result: a registration result (``registration.load``).
        frames: a frame source with ``get(k)`` -> BGR raw frame.
        stage: "global" or "local".

    Returns:
        ``{"dir", "video", "box": [x0, y0, w, h], "n_frames", "n_failed"}`` (paths as str).
    """
    out = Path(out_dir) if out_dir is not None else Path(result.out_dir) / "registered"
    n = int(result.n_frames)
    ok = [k for k in range(n) if result.records[k].get("status") == "ok"]
    fns = [(lambda q, k=k: result.frame_to_base(k, q, "global")) for k in ok]
    x0, y0, w, h = footprint(fns, tuple(result.frame_size), tuple(result.base_size), pad=2)
    if w == 0 or h == 0:
        raise ValueError("no registered frame maps into the base map; nothing to render")
    mid = None
    mid_path = Path(getattr(result, "mid_base_path", ""))
    if overlays and mid_path.is_file():
        mid = read_image(mid_path)[y0 : y0 + h, x0 : x0 + w]
    frame_paths: list[Path] = []
    for k in range(n):
        path = out / "frames" / f"{k:06d}.png"
        if k in ok:
            image, mask = render_registered(
                frames.get(k),
                lambda b, k=k: result.base_to_frame(k, b, stage),
                (w, h),
                (x0, y0),
                step=step,
                return_mask=True,
            )
            if mid is not None:
                write_image_atomic(out / "overlay" / f"{k:06d}.jpg", overlay(image, mid, mask=mask))
            fld = result.field(k) if fields and hasattr(result, "field") else None
            if fld is not None:
                fb = footprint(
                    [lambda q, k=k: result.frame_to_base(k, q, "global")],
                    tuple(result.frame_size),
                    tuple(result.base_size),
                )
                u, v = field_component_images(fld, fb[2], fb[3], (fb[0], fb[1]))
                write_image_atomic(out / "field" / f"{k:06d}_dx.png", u)
                write_image_atomic(out / "field" / f"{k:06d}_dy.png", v)
        else:
            image = np.zeros((h, w, 3), np.uint8)
        write_image_atomic(path, image)
        frame_paths.append(path)
        if progress:
            progress(k + 1, n)
    video = write_video(frame_paths, out / "registered.mp4", fps=fps)
    return {
        "dir": str(out),
        "video": str(video),
        "box": [x0, y0, w, h],
        "n_frames": n,
        "n_failed": n - len(ok),
        "stage": stage,
    }


__all__ = [
    "diverging_colormap",
    "field_component_images",
    "footprint",
    "overlay",
    "render_registered",
    "write_registered_sequence",
    "write_video",
]
