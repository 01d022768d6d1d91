"""``aerialreg undistort``: correct one image's radial distortion with the Harris model (paper 3)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import cv2
import numpy as np

from app.cli.common import UsageError, emit_json
from registration.io import atomic_path
from registration.lens import (
    CANVASES,
    IMAGE_INTERPOLATIONS,
    HarrisModel,
    check_harris_gamma,
    check_valid,
    undistort_image,
)

NAME = "undistort"
HELP = "Correct an image's radial lens distortion with the Harris model (paper section 3)."


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "image", metavar="IMAGE", help="raw (distorted) image file, any format OpenCV reads"
    )
    p.add_argument(
        "--gamma",
        type=float,
        required=True,
        metavar="G",
        help="Harris distortion parameter γ (positive corrects barrel distortion; the paper's "
        "camera: 0.7; 0 = no change; valid from -1 to just above 1.0; the exact limit "
        "for the frame is printed when exceeded)",
    )
    p.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="OUT",
        help="output image file; its extension picks the format (.png, .jpg, .tif, ...)",
    )
    p.add_argument(
        "--center",
        metavar="X,Y",
        help="distortion centre in raw pixels (default: the frame centre ((W-1)/2, (H-1)/2)); "
        "as printed by 'aerialreg calibrate --center auto'",
    )
    p.add_argument(
        "--canvas",
        choices=CANVASES,
        default="same",
        help="'same': the raw frame's size and centre, as the paper's Fig. 2 (outer raw content "
        "is cropped); 'full': a larger canvas holding every raw pixel (default: same)",
    )
    p.add_argument(
        "--interpolation",
        choices=IMAGE_INTERPOLATIONS,
        default="linear",
        help="resampling: bilinear ('linear') or bicubic ('cubic') (default: linear)",
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object (output path, gamma, canvas size and origin) on stdout",
    )


# Beyond registration.io's limits (at least 16 px a side, at most 100 megapixels, checked from
# the header before decoding): at most MAX_IMAGE_SIDE a side, since the correction maps hold
# int16 positions.
MAX_IMAGE_SIDE = 32000


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as stored (grey, colour BGR or BGRA; 8 or 16 bit).

    Raises:
        FileNotFoundError: no such file.
        ValueError: a directory, an empty, truncated or corrupt file, data OpenCV cannot decode,
            an image outside the size limits (one line each, :func:`registration.io.
            decode_image_file`).
    """
    from registration import io

    image = io.decode_image_file(path, max_pixels=io.MAX_FRAME_PIXELS)
    h, w = image.shape[:2]
    if max(w, h) > MAX_IMAGE_SIDE:
        raise ValueError(f"{path}: {w}x{h} pixels; images may be at most {MAX_IMAGE_SIDE} a side")
    return image


def parse_center(text: str | None) -> tuple[float, float] | None:
    """``"X,Y"`` (raw pixels) -> ``(x, y)``; None for None; UsageError otherwise."""
    if text is None:
        return None
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise UsageError(
            f"--center must look like 959.5,539.5 (raw pixels), got {text!r}"
        ) from None
    if not (np.isfinite(x) and np.isfinite(y)):
        raise UsageError(f"--center must be finite, got {text!r}")
    return x, y


def same_file(a: Path, b: Path) -> bool:
    """True when ``a`` and ``b`` name the same file (also through links or ``..``)."""
    if a.exists() and b.exists():
        return os.path.samefile(a, b)
    return a.resolve() == b.resolve()


def write_image_atomically(out: Path, image: np.ndarray) -> None:
    """Write ``image`` to ``out`` through a temporary file beside it, so that a failed write
    never leaves a truncated ``out`` (and an existing ``out`` stays intact until replaced)."""
    with atomic_path(out, keep_suffix=True) as tmp:  # cv2.imwrite picks the format by the name
        if not cv2.imwrite(str(tmp), image):
            raise UsageError(f"could not write {out}")


def run(args: argparse.Namespace) -> int:
    out = Path(args.output)
    if out.is_dir():
        raise UsageError(f"output {out} is a directory; give an image file name such as out.png")
    if not out.parent.exists() and str(out.parent) not in ("", "."):
        raise UsageError(f"output folder {out.parent} does not exist")
    if not out.suffix or not cv2.haveImageWriter(str(out)):
        raise UsageError(f"cannot write images of type {out.suffix or '(none)'!r}: {out}")
    if same_file(Path(args.image), out):
        raise UsageError(
            f"output {out} is the input image; write the corrected image to another file"
        )
    center = parse_center(args.center)
    image = read_image(args.image)
    h, w = image.shape[:2]
    check_harris_gamma(args.gamma, w, h, center)
    model = check_valid(HarrisModel(args.gamma, w, h, center))
    corrected, info = undistort_image(
        image, model, canvas=args.canvas, interpolation=args.interpolation
    )
    write_image_atomically(out, corrected)
    if args.json:
        emit_json(
            {
                "output": str(out),
                "gamma": float(args.gamma),
                "center": [float(model.c[0]), float(model.c[1])],
                "image_size": [w, h],
                "canvas": info.to_dict(),
                "interpolation": args.interpolation,
            }
        )
    else:
        sys.stderr.write(
            f"wrote {out}: {info.width}x{info.height} ({args.canvas} canvas, gamma {args.gamma:g}, "
            f"canvas pixel (0,0) = corrected ({info.origin[0]:g}, {info.origin[1]:g}))\n"
        )
    return 0
