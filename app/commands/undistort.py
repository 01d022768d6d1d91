"""``aerialreg undistort``: correct one image's radial distortion with the Harris model (paper 3)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from app.cli import UsageError, emit_json
from registration.distortion import (
    CANVASES,
    IMAGE_INTERPOLATIONS,
    HarrisModel,
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
        "camera: 0.7; 0 = no change; must be below ~1.0, the limit for the frame is printed "
        "when exceeded)",
    )
    p.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="OUT",
        help="output image file; its extension picks the format (.png, .jpg, .tif, ...)",
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


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as stored (grey, colour BGR or BGRA; 8 or 16 bit).

    Raises:
        FileNotFoundError: no such file.
        ValueError: a directory, an empty, truncated or corrupt file, data OpenCV cannot decode,
            an image outside the size limits (one line each).
    """
    from registration.io import MAX_FRAME_PIXELS, decode_image_file

    # Checks size limits before decoding and refuses truncated files (registration.io).
    return decode_image_file(path, max_pixels=MAX_FRAME_PIXELS)


def run(args: argparse.Namespace) -> int:
    out = Path(args.output)
    if out.is_dir():
        raise UsageError(f"output {out} is a directory; give an image file name such as out.png")
    if not out.parent.exists() and str(out.parent) not in ("", "."):
        raise UsageError(f"output folder {out.parent} does not exist")
    if not out.suffix or not cv2.haveImageWriter(str(out)):
        raise UsageError(f"cannot write images of type {out.suffix or '(none)'!r}: {out}")
    image = read_image(args.image)
    h, w = image.shape[:2]
    model = check_valid(HarrisModel(args.gamma, w, h))
    corrected, info = undistort_image(
        image, model, canvas=args.canvas, interpolation=args.interpolation
    )
    if not cv2.imwrite(str(out), corrected):
        raise UsageError(f"could not write {out}")
    if args.json:
        emit_json(
            {
                "output": str(out),
                "gamma": float(args.gamma),
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
