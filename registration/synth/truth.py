"""The simulator's ground truth: ``truth.json`` and its loader, with the registration-result
interface.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points
from registration.mapping import STAGES
from registration.synth.basemap import base_map_info
from registration.synth.camera import SequenceGeometry, SimLens, apply_homography

TRUTH_FORMAT = "aerialreg-synth-truth"
# 2: lens_k2, base_map, files (version 1 files read as lens_k2 = 0, base at heading 0, scale 1).
TRUTH_VERSION = 2
READABLE_TRUTH_VERSIONS = (1, 2)


# ------------------------------------------------------------------------------------------
# Truth


class SimTruth:
    """Exact ground truth of a simulated sequence, with the registration-result interface.

    ``frame_to_base(k, xy, stage)`` and ``base_to_frame(k, xy, stage)`` map ``(N, 2)`` raw
    pixels of frame ``k`` to base pixels and back (``stage`` is validated and ignored); NaN for
    points outside the frame or the base. Truth is defined for the terrain surface (roofs and
    vehicles are painted on the ground in the scene, so they follow the same mapping).
    """

    def __init__(
        self,
        geometry: SequenceGeometry,
        root: Path | None = None,
        config: dict | None = None,
        record: dict | None = None,
    ):
        self.geometry = geometry
        self.root = root
        self.config = config or {}
        self.record = record or {}

    @property
    def n_frames(self) -> int:
        return self.geometry.n_frames

    @property
    def gamma(self) -> float:
        return self.geometry.gamma

    @property
    def lens(self) -> SimLens:
        """The true lens (Harris γ plus ``lens_k2``)."""
        return self.geometry.lens

    @property
    def base_map(self) -> dict:
        """How the base relates to the native base (heading, scale, ``base_from_native``,
        ``native_from_scene``, ``valid_polygon``); heading 0 and scale 1 for older files."""
        g = self.geometry
        return self.record.get("base_map") or base_map_info(
            g.base_size, g.base_from_scene, 0.0, 1.0, np.eye(3)
        )

    @property
    def frame_size(self) -> tuple[int, int]:
        return (self.geometry.width, self.geometry.height)

    @property
    def base_size(self) -> tuple[int, int]:
        return tuple(self.geometry.base_size)

    @property
    def base_path(self) -> Path | None:
        return None if self.root is None else self.root / "base.png"

    @property
    def frames_dir(self) -> Path | None:
        return None if self.root is None else self.root / "frames"

    def frame_paths(self) -> list[Path]:
        return [self.frames_dir / f"{k:06d}.png" for k in range(self.n_frames)]

    def verify_files(self) -> list[str]:
        """Files that do not match the SHA-256 recorded in ``truth.json`` (missing or changed),
        as relative paths; empty when all match (or nothing was recorded)."""
        bad = []
        for rel, digest in self.record.get("files", {}).items():
            p = self.root / rel
            try:
                with open(p, "rb") as fh:
                    ok = hashlib.file_digest(fh, "sha256").hexdigest() == digest
            except OSError:
                ok = False
            if not ok:
                bad.append(rel)
        return bad

    def _check(self, k: int, stage: str) -> int:
        if stage not in STAGES:
            raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
        k = int(k)
        if not 0 <= k < self.n_frames:
            raise IndexError(f"frame index {k} out of range 0..{self.n_frames - 1}")
        return k

    def frame_to_base(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]:
        """``(N, 2)`` raw pixels of frame ``k`` -> ``(N, 2)`` base pixels (NaN outside)."""
        k = self._check(k, stage)
        return self.geometry.base_from_raw(k, as_points(xy))

    def base_to_frame(
        self, k: int, xy: ArrayLike, stage: str = "local", *, clip: bool = True
    ) -> NDArray[np.float64]:
        """``(N, 2)`` base pixels -> ``(N, 2)`` raw pixels of frame ``k`` (NaN outside the base,
        and outside the frame unless ``clip`` is False)."""
        k = self._check(k, stage)
        return self.geometry.raw_from_base(k, as_points(xy), clip=clip)

    def vehicles(self) -> dict[str, NDArray] | None:
        """The moving vehicles' true trajectories (``vehicles.csv``,
        :mod:`registration.synth.vehicles`) with their centres in this truth's base pixels
        (``x_base``, ``y_base``), their direction of travel there (``ux``, ``uy``, unit) and
        ``base_px_per_m``; None when the sequence has no vehicle truth (a user scene, no
        vehicles, or a file of an older simulator)."""
        from registration.synth.vehicles import VEHICLES_NAME, read_vehicles

        if self.root is None or not (self.root / VEHICLES_NAME).is_file():
            return None
        v = read_vehicles(self.root / VEHICLES_NAME)
        h = np.asarray(self.geometry.base_from_scene, np.float64)
        centre = np.column_stack([v["x_scene"], v["y_scene"]])
        base = apply_homography(h, centre)
        ahead = apply_homography(h, centre + np.column_stack([v["dx"], v["dy"]]))
        step = ahead - base
        norm = np.linalg.norm(step, axis=1)
        v["x_base"], v["y_base"] = base[:, 0], base[:, 1]
        with np.errstate(invalid="ignore", divide="ignore"):
            v["ux"], v["uy"] = step[:, 0] / norm, step[:, 1] / norm
        # Base px per scene px (the base is a similarity of the scene) over metres per scene px.
        v["base_px_per_m"] = np.sqrt(abs(np.linalg.det(h[:2, :2]))) / self.geometry.scene_gsd
        return v

    def camera_altitude_m(self) -> float:
        return float(-self.geometry.pose.origin[2])


def load_truth(directory: str | os.PathLike) -> SimTruth:
    """Load the ground truth of a sequence written by :func:`simulate` (reads ``truth.json``)."""
    root = Path(directory)
    path = root / "truth.json"
    if not path.is_file():
        raise FileNotFoundError(f"no simulator truth in {root}: {path} is missing")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON ({exc.msg} at line {exc.lineno})") from None
    if data.get("format") != TRUTH_FORMAT:
        raise ValueError(f"{path} is not a simulator truth file (format={data.get('format')!r})")
    if data.get("version") not in READABLE_TRUTH_VERSIONS:
        raise ValueError(
            f"{path} has truth version {data.get('version')}, this code reads "
            f"{', '.join(map(str, READABLE_TRUTH_VERSIONS))}"
        )
    return SimTruth(
        SequenceGeometry.from_dict(data["geometry"]), root, data.get("config"), record=data
    )


# ------------------------------------------------------------------------------------------
# I/O


def read_rgb(path: str | os.PathLike) -> NDArray[np.uint8]:
    """Read an image file as ``(H, W, 3)`` uint8 RGB."""
    from registration.io import read_image

    # Size limits and truncated files as for every other image (registration.io).
    return np.ascontiguousarray(read_image(path)[..., ::-1])
