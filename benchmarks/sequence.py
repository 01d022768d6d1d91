"""The simulated sequence a suite measures on (not a suite itself): rendered with the bench's
``--size``, ``--frames``, ``--seed``, ``--scene``/``--base`` and ``--profile``, loaded back with its
exact truth, and a seed click at the reference frame's centre from that truth."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

from numpy.typing import NDArray


@dataclass
class SimulatedSequence:
    """A rendered sequence: its folder, truth, frames, base map and the seed click
    ``(fx, fy, bx, by)`` at the reference frame's centre (raw frame px, base px)."""

    folder: Path
    truth: object
    frames: object
    base: NDArray
    seed: tuple[float, float, float, float]


def simulated_sequence(
    args, out: Path, label: str, reference_frame: int = 0, *, video: bool = False, **sim
) -> SimulatedSequence:
    """Render ``args.frames`` frames of ``args.size_wh`` into ``out`` (the named simulator profile
    when ``args.profile`` is set, else the default flight) and load them; ``label`` prefixes the
    progress line on stderr. ``video``: also write the frames as ``out/sequence.mp4`` (H.264).
    ``sim``: further :class:`registration.synth.SimConfig` values."""
    from registration.io import open_frames, read_image
    from registration.synth import SimConfig, load_truth, simulate
    from registration.synth.profiles import profile_config

    w, h = args.size_wh
    fields = dict(frame_size=(w, h), n_frames=args.frames, seed=args.seed, video=video, **sim)
    profile = getattr(args, "profile", None)
    config = profile_config(profile, **fields) if profile else SimConfig(**fields)
    t0 = time.perf_counter()
    simulate(out, config, scene=args.scene, base=args.base)
    what = f", profile {profile}" if profile else ""
    sys.stderr.write(
        f"{label}: simulated {args.frames} frames {w}x{h}{what} in "
        f"{time.perf_counter() - t0:.1f} s\n"
    )
    truth = load_truth(out)
    bx, by = truth.frame_to_base(reference_frame, [[w / 2, h / 2]])[0]
    return SimulatedSequence(
        folder=out,
        truth=truth,
        frames=open_frames(out / "frames"),
        base=read_image(out / "base.png"),
        seed=(w / 2, h / 2, float(bx), float(by)),
    )
