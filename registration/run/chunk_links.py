"""Links between frames measured while a chunk is registered (beyond the paper), so that the
sequence adjustment (:mod:`registration.run.adjust`) need not decode the frames a second time.

As each frame of a chunk is registered, its links to the chunk's frames registered before it
at the adjustment's steps (``SequenceAdjustConfig.link_steps``: ``k - s`` going forward, ``k + s``
going backward from the reference frame) are measured exactly as the adjustment would measure
them (:func:`registration.adjustment.measure_links` through both frames' own models as their
records store them), and stored with the frame's arrays under a key of what they were measured
through (:func:`registration.adjustment.link_key`). The adjustment uses a stored pair where its
key matches and measures the others (pairs across chunk joins, frames whose start model the
analyst's map points moved), so its result is the same to the bit whether links were stored or
not. Decoding every frame again cost the adjustment 0.036 of its 0.18 s of CPU per 1280x960
frame and 0.139 of 0.395 s per 2560x1920 frame (``tools/cpu_by_stage.py``).

A resumed chunk first reads again the frames it already has that its next frames link to, so
that every frame's arrays are those of an uninterrupted run.
"""

from __future__ import annotations

from numpy.typing import NDArray

from registration.adjustment import (
    SequenceAdjustConfig,
    as_polyprojective,
    link_key,
    links_to_arrays,
    measure_links,
)
from registration.adjustment.sequence import probes_for
from registration.geometry import model_from_dict
from registration.matching import textured_probes, to_grey


class ChunkLinks:
    """The links of a chunk's frames as they are registered, in the chunk's order.

    Args:
        config: the run's sequence adjustment (its steps, probes and matcher).
        lens: the run's lens (raw <-> corrected px).
        frame_size: ``(width, height)`` of the raw frames.
    """

    def __init__(self, config: SequenceAdjustConfig, lens, frame_size: tuple[int, int]) -> None:
        self.config, self.lens, self.frame_size = config, lens, frame_size
        self._reach = max(config.link_steps)
        # Registered frames a later frame may link to: k -> (grey, model, probes or None).
        self._seen: dict[int, list] = {}

    def remember(self, k: int, frame: NDArray, model: dict) -> None:
        """Keep frame ``k`` (raw ``(H, W[, C])``, its record's ``model``) for the links of the
        frames registered after it, measuring none."""
        model_ = as_polyprojective(model_from_dict(model), *self.frame_size)
        self._seen[k] = [to_grey(frame), model_, None]
        self._forget_far_from(k)

    def add(self, k: int, frame: NDArray, model: dict) -> dict[str, NDArray]:
        """Frame ``k`` just registered (raw ``frame``, its record's ``model``): the arrays of its
        links to the frames kept (:func:`registration.adjustment.links_to_arrays`); it is kept
        for the frames after it."""
        self.remember(k, frame, model)
        cfg = self.config
        pairs = []
        for s in cfg.link_steps:
            for j in (k - s, k + s):
                if j == k or j not in self._seen:
                    continue
                a, b = min(j, k), max(j, k)
                grey_a, model_a, _ = self._seen[a]
                grey_b, model_b, _ = self._seen[b]
                links = measure_links(
                    grey_a, grey_b, a, b, model_a, model_b, self.lens, cfg.probes,
                    self._probes(a), cfg.link_matcher,
                )  # fmt: skip
                key = link_key(model_a, model_b, self.lens, cfg.probes, cfg.link_matcher)
                pairs.append((links, key))
        return links_to_arrays(pairs)

    def _probes(self, k: int) -> NDArray:
        seen = self._seen[k]
        if seen[2] is None:
            seen[2] = textured_probes(seen[0], probes_for(seen[0], self.config.probes))
        return seen[2]

    def _forget_far_from(self, k: int) -> None:
        # A chunk runs in one direction, so no later frame links to these.
        for j in [j for j in self._seen if abs(j - k) > self._reach]:
            del self._seen[j]


def linked_done_frames(order: list[int], done, steps: tuple[int, ...]) -> list[int]:
    """The frames of a resumed chunk already registered (``done``: k -> its
    :class:`registration.run.chunks.DoneFrame`) that a frame registered after them in ``order``
    links to, in ``order``."""
    todo_after: set[int] = set()
    out = []
    for k in reversed(order):
        if k not in done:
            todo_after.add(k)
        elif done[k].ok and any(k + s in todo_after or k - s in todo_after for s in steps):
            out.append(k)
    return out[::-1]
