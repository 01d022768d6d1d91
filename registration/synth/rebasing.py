"""A simulated sequence copied with its base map turned and/or resampled (frames reused, truth
kept exact).
"""

from __future__ import annotations

import copy
import json
import os
import shutil
from pathlib import Path

import numpy as np

from registration.synth.basemap import base_map_info, resample, similarity


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def rebase(
    src_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    heading_deg: float,
    scale: float,
    *,
    force: bool = False,
) -> Path:
    """Copy the simulated sequence in ``src_dir`` to ``out_dir`` with a new base map.

    The new base is the native base turned by ``heading_deg`` and scaled by ``scale`` (absolute
    values, as :class:`SimConfig`'s ``base_heading_deg``/``base_scale``), resampled from
    ``src_dir/base.png``: from a source at heading 0 and scale 1 (the usual case) that is one
    resampling of the native base; from another source the base is resampled twice. The frames
    (and ``sequence.mp4``) are hard-linked (copied where the file system cannot link); the
    truth is the source's with ``base_from_scene`` composed with the new similarity, so it stays
    exact. Writing follows :mod:`registration.synth.output` (``force`` to replace a non-empty
    ``out_dir``; truth last).

    Returns:
        ``Path(out_dir)``.
    """
    from registration.synth.output import Staging, sha256_file, write_png
    from registration.synth.truth import load_truth
    from registration.synth.vehicles import VEHICLES_NAME

    src = Path(src_dir)
    out = Path(out_dir)
    load_truth(src)  # validates format and version, one-line errors
    truth = json.loads((src / "truth.json").read_text())
    if out.resolve() == src.resolve():
        raise ValueError(f"rebase needs another output folder than its source {src}")
    geom = truth["geometry"]
    base_from_scene = np.asarray(geom["base_from_scene"], np.float64)
    info = truth.get("base_map") or {
        "native_size": list(geom["base_size"]),
        "native_from_scene": base_from_scene.tolist(),
        "base_from_native": np.eye(3).tolist(),
        "scale": 1.0,
    }
    native_size = tuple(int(v) for v in info["native_size"])
    native_from_scene = np.asarray(info["native_from_scene"], np.float64)
    src_from_native = np.asarray(info["base_from_native"], np.float64)
    new_from_native, canvas = similarity(native_size, heading_deg, scale)

    from registration.synth.truth import read_rgb

    src_base = read_rgb(src / truth.get("base", "base.png"))
    new_from_src = new_from_native @ np.linalg.inv(src_from_native)
    base = resample(src_base, new_from_src, canvas, float(scale) / float(info["scale"]))

    new = copy.deepcopy(truth)
    new["geometry"]["base_from_scene"] = (new_from_native @ native_from_scene).tolist()
    new["geometry"]["base_size"] = list(canvas)
    new["base_map"] = base_map_info(
        native_size, native_from_scene, heading_deg, scale, new_from_native
    )
    if isinstance(new.get("config"), dict):
        new["config"]["base_heading_deg"] = float(heading_deg)
        new["config"]["base_scale"] = float(scale)
    new["rebased_from"] = str(src.resolve())
    with Staging(out, force) as stage:
        files = dict(new.get("files", {}))
        files["base.png"] = write_png(stage.dir / "base.png", base)
        for rel in truth["frames"]:
            _link_or_copy(src / rel, stage.dir / rel)
            if rel not in files:
                files[rel] = sha256_file(stage.dir / rel)
        # The vehicles' truth is in scene pixels: the new base_from_scene maps it.
        for name in ("sequence.mp4", VEHICLES_NAME):
            if (src / name).is_file():
                _link_or_copy(src / name, stage.dir / name)
        new["files"] = files
        stage.commit(new)
    return out
