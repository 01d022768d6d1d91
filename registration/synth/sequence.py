"""Render a helicopter sequence with exact ground truth, write it, and load the truth back.

Output layout of :func:`simulate` (``OUT``)::

    OUT/frames/000000.png ...   raw frames (lens-distorted, rolling shutter, noise, JPEG-like
                                compression), RGB PNG
    OUT/base.png                the base map (second sensor), the target of registration; at
                                any heading and resolution (black = no data outside the map)
    OUT/truth.json              everything the truth needs: camera, lens, pose track, terrain,
                                mapping between scene and base, the config, the SHA-256 of every
                                frame and the base; :func:`load_truth` recomputes the truth
                                exactly from it
    OUT/sequence.mp4            the frames as H.264 video (cropped to even size), for viewing
    OUT/vehicles.csv            the moving vehicles' true trajectories, per frame (procedural
                                city with vehicles; :mod:`registration.synth.vehicles`)

Nothing in ``OUT`` is overwritten without ``force``; everything is rendered into a staging folder
and swapped in, ``truth.json`` last (:mod:`registration.synth.output`).

The pieces: :mod:`~registration.synth.config` (settings and limits),
:mod:`~registration.synth.plan` (pose, terrain, scene extent), :mod:`~registration.synth.camera`
(lens, rolling shutter, ground intersection), :mod:`~registration.synth.render` (frames),
:mod:`~registration.synth.basemap` (base heading/scale, :func:`rebase`).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.io import atomic_path
from registration.synth import city as citymod
from registration.synth.basemap import base_map_info, warp_base
from registration.synth.camera import SequenceGeometry
from registration.synth.config import SimConfig
from registration.synth.output import Staging, check_target, write_bytes, write_png
from registration.synth.plan import (
    plan_procedural,
    plan_scene,
)
from registration.synth.render import FrameRenderer
from registration.synth.truth import TRUTH_FORMAT, TRUTH_VERSION, read_rgb
from registration.synth.vehicles import VEHICLES_NAME, vehicle_rows, vehicles_csv

Progress = Callable[[int, int], None]


def _as_rgb(image, name: str) -> NDArray[np.uint8]:
    if isinstance(image, (str, os.PathLike)):
        return read_rgb(image)
    arr = np.asarray(image)
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, axis=2)
    if arr.ndim != 3 or arr.shape[2] not in (3, 4) or arr.dtype != np.uint8:
        raise ValueError(
            f"{name} must be an (H, W, 3) uint8 RGB image or a path, got {arr.shape} {arr.dtype}"
        )
    return np.ascontiguousarray(arr[..., :3])


@contextmanager
def _video_writer(path: Path, fps: float) -> Iterator[Callable[[NDArray[np.uint8]], None]]:
    """H.264 video of the frames, cropped to even size, written through
    :func:`registration.io.atomic_path`: yields the function that appends a frame."""
    import imageio.v2 as imageio

    with atomic_path(path, keep_suffix=True) as tmp:
        writer = imageio.get_writer(
            str(tmp),
            format="FFMPEG",
            fps=fps,
            codec="libx264",
            quality=7,
            macro_block_size=1,
            output_params=["-preset", "veryfast"],
            pixelformat="yuv420p",
            ffmpeg_log_level="error",
        )
        try:
            yield lambda rgb: writer.append_data(
                np.ascontiguousarray(rgb[: rgb.shape[0] // 2 * 2, : rgb.shape[1] // 2 * 2])
            )
        finally:
            writer.close()


# ------------------------------------------------------------------------------------------
# The simulator


def _paint_city(cfg: SimConfig, geom: SequenceGeometry):
    """``(layout, scene, native base)`` of the procedural city planned in ``geom``: the frames'
    sensor and the base's (another sun, other parked cars and traffic, another sensor)."""
    layout = citymod.make_layout(*geom.scene_size, gsd=cfg.gsd_m, seed=cfg.seed)
    scene_img = citymod.render_city(layout, citymod.Look(parked_seed=cfg.seed * 2 + 1))
    base_img = citymod.second_sensor(
        citymod.render_city(
            layout,
            citymod.Look(
                sun_azimuth_deg=cfg.base_sun_deg[0],
                sun_elevation_deg=cfg.base_sun_deg[1],
                parked_seed=cfg.seed * 2 + 2,
                parked_fraction=0.55,
                traffic_seed=cfg.seed + 1000,
                traffic_per_km=cfg.traffic_per_km * 0.8,
            ),
        ),
        cfg.seed,
    )
    return layout, scene_img, base_img


def _plan_user_scene(cfg: SimConfig, scene, base, base_from_scene):
    """``(geometry, scene, native base)`` for a user scene (and base, related by
    ``base_from_scene``; identity needs sizes within 3 %)."""
    scene_img = _as_rgb(scene, "scene")
    base_img = citymod.second_sensor(scene_img, cfg.seed) if base is None else _as_rgb(base, "base")
    sh, sw = scene_img.shape[:2]
    bh, bw = base_img.shape[:2]
    if base_from_scene is None:
        if abs(sw - bw) > 0.03 * sw or abs(sh - bh) > 0.03 * sh:
            raise ValueError(
                f"scene is {sw}x{sh} px but base is {bw}x{bh} px; give base_from_scene "
                "(--base-from-scene, 9 numbers) to relate them"
            )
        h = np.eye(3)
    else:
        h = np.asarray(base_from_scene, np.float64)
        if h.size != 9:
            raise ValueError(f"base_from_scene must have 9 numbers (3x3), got {h.size}")
        h = h.reshape(3, 3)
        if not np.isfinite(h).all() or abs(np.linalg.det(h)) < 1e-12:
            raise ValueError(
                f"base_from_scene must be a finite invertible 3x3 matrix, got {h.ravel().tolist()}"
            )
        h = h / h[2, 2] if abs(h[2, 2]) > 1e-12 else h
    return plan_scene(cfg, (sw, sh), (bw, bh), h), scene_img, base_img


def simulate(
    out_dir: str | os.PathLike,
    config: SimConfig | None = None,
    *,
    scene: str | os.PathLike | NDArray | None = None,
    base: str | os.PathLike | NDArray | None = None,
    base_from_scene: ArrayLike | None = None,
    progress: Progress | None = None,
    force: bool = False,
) -> Path:
    """Render a helicopter sequence with exact ground truth into ``out_dir``.

    Args:
        out_dir: output folder (created); layout in the module docstring. Must be missing or
            empty unless ``force``.
        config: :class:`SimConfig` (defaults: 1280x960, 25 frames, γ 0.7, 40 ms readout).
        scene: image (path or RGB array) to render frames from instead of the procedural city.
        base: base map of the same area (path or RGB array); None with a scene = the scene as
            another sensor would see it. Ignored without ``scene``.
        base_from_scene: ``(3, 3)`` homography scene px -> base px (identity by default, which
            requires scene and base of the same size within 3 %).
        progress: called as ``progress(done, total)``; total = frames + 2 (scene, frames,
            video).
        force: replace the simulator's entries of a non-empty ``out_dir`` (``frames/``,
            ``base.png``, ``truth.json``, ``sequence.mp4``; other files are left alone).

    Returns:
        ``Path(out_dir)``.

    Raises:
        ValueError: one line naming the bad value (sizes, γ, footprint outside the base ...).
        FileExistsError: ``out_dir`` is not empty and ``force`` is False (one line).
    """
    cfg = config or SimConfig()
    cfg.validate()
    out = Path(out_dir)
    check_target(out, force)
    total = cfg.n_frames + 2  # scene, frames, video
    geom, layout, scene_img, base_img, scene_desc = _plan_and_paint(
        cfg, scene, base, base_from_scene, progress, total
    )
    native_size = tuple(int(v) for v in geom.base_size)
    native_from_scene = np.asarray(geom.base_from_scene, np.float64)
    base_img, base_from_native, canvas = warp_base(base_img, cfg.base_heading_deg, cfg.base_scale)
    geom = dataclasses.replace(
        geom, base_from_scene=base_from_native @ native_from_scene, base_size=canvas
    )
    base_map = base_map_info(
        native_size, native_from_scene, cfg.base_heading_deg, cfg.base_scale, base_from_native
    )
    truth = _truth_record(cfg, geom, scene_desc, base_map)
    with Staging(out, force) as stage:
        files = {"base.png": write_png(stage.dir / "base.png", base_img)}
        del base_img
        if progress:
            progress(1, total)
        renderer = FrameRenderer(geom, scene_img, cfg, layout)
        _write_frames(stage.dir, renderer, cfg, files, progress, total)
        if layout is not None and cfg.vehicles:
            rows = [row for k in range(cfg.n_frames) for row in vehicle_rows(layout, cfg, geom, k)]
            files[VEHICLES_NAME] = write_bytes(stage.dir / VEHICLES_NAME, vehicles_csv(rows))
        truth["files"] = files
        stage.commit(truth)
    if progress:
        progress(total, total)
    return out


def _plan_and_paint(cfg: SimConfig, scene, base, base_from_scene, progress, total: int):
    """``(geometry, layout, scene, native base, scene description)``: the flight planned over
    the procedural city (``layout`` its plan) or the user's ``scene`` (``layout`` None), the
    scene painted or read and the base map at its native heading and scale. ``progress(0,
    total)`` is reported once the flight is planned (a bad flight fails before any bar)."""
    if scene is None:
        if base is not None or base_from_scene is not None:
            raise ValueError("base and base_from_scene need a scene image")
        geom = plan_procedural(cfg)
        if progress:
            progress(0, total)
        layout, scene_img, base_img = _paint_city(cfg, geom)
        scene_desc = "procedural"
    else:
        layout = None
        scene_desc = str(scene) if isinstance(scene, (str, os.PathLike)) else "array"
        geom, scene_img, base_img = _plan_user_scene(cfg, scene, base, base_from_scene)
        if progress:
            progress(0, total)
    return geom, layout, scene_img, base_img, scene_desc


def _truth_record(cfg: SimConfig, geom: SequenceGeometry, scene_desc: str, base_map: dict) -> dict:
    """``truth.json`` but its ``files`` (added once the frames are written): the frames, lens,
    geometry ``geom`` (scene px), ``base_map`` (:func:`base_map_info`) and the config."""
    return {
        "format": TRUTH_FORMAT,
        "version": TRUTH_VERSION,
        "scene": scene_desc,
        "base": "base.png",
        "frames": [f"frames/{k:06d}.png" for k in range(cfg.n_frames)],
        "frame_size": list(cfg.frame_size),
        "gamma": cfg.gamma,
        "lens_k2": cfg.lens_k2,
        "frame_scale": float(-geom.pose.origin[2] / (cfg.gsd_m * geom.focal_px)),
        "geometry": geom.to_dict(),
        "base_map": base_map,
        "config": dataclasses.asdict(cfg),
    }


def _write_frames(
    stage_dir: Path,
    renderer: FrameRenderer,
    cfg: SimConfig,
    files: dict[str, str],
    progress: Progress | None,
    total: int,
) -> None:
    """Render every frame into ``stage_dir/frames/`` (and ``sequence.mp4`` with
    ``cfg.video``), adding each frame's SHA-256 to ``files`` (``{"frames/000000.png": hex}``)
    and reporting ``progress(k + 2, total)`` after frame ``k``."""
    with ExitStack() as stack:
        video = (
            stack.enter_context(_video_writer(stage_dir / "sequence.mp4", cfg.fps))
            if cfg.video
            else None
        )
        for k in range(cfg.n_frames):
            frame = renderer.render(k)
            rel = f"frames/{k:06d}.png"
            files[rel] = write_png(stage_dir / rel, frame)
            if video:
                video(frame)
            if progress:
                progress(k + 2, total)
