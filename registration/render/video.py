"""Videos of a registered sequence: the frames rendered into base px over the sequence's footprint,
written as mp4.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.io import atomic_path, read_image, write_image_atomic
from registration.render.figures import _bgr, field_component_images, overlay
from registration.render.frames import footprint, render_registered

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
    writer = None
    size = None
    n = 0
    with atomic_path(out, keep_suffix=True) as tmp:
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
                    raise ValueError(
                        f"video frame {n} is {w}x{h}, the first was {size[0]}x{size[1]}"
                    )
                pad_w, pad_h = w % 2, h % 2
                if pad_w or pad_h:
                    img = cv2.copyMakeBorder(img, 0, pad_h, 0, pad_w, cv2.BORDER_CONSTANT, value=0)
                writer.append_data(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
                n += 1
            if writer is None:
                raise ValueError(f"no frames to write to {out}")
        finally:
            if writer is not None:
                writer.close()
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
    ok = [k for k in range(n) if result.is_ok(k)]
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
