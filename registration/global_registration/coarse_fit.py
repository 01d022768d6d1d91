"""Fitting the coarse model to SIFT matches (paper 4.3.1): RANSAC per model (similarity, affine,
projective), the consensus between them, and the simplest model the inliers support.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from registration.coords import rescale
from registration.geometry import (
    Affine,
    Projective,
    RansacConfig,
    Similarity,
    hull_coverage,
    quantized,
    ransac,
    simplest_supported,
)
from registration.global_registration import heading
from registration.global_registration.coarse_records import (
    _MODELS,
    CoarseConfig,
    CoarseFeatures,
    CoarseResult,
)
from registration.global_registration.heading import SimilarityPrior
from registration.matching import sift

# ------------------------------------------------------------------------------------------
# Fitting


def _ransac_config(config: CoarseConfig, **changes) -> RansacConfig:
    return dataclasses.replace(config.ransac, **changes)


# Share of the frame the inliers must span for a model's extra terms to be considered, as in
# the fine step (registration.global_registration.fine.FINE_MIN_COVERAGE says why and what it gave).
COARSE_MIN_COVERAGE = {"affine": 0.3, "projective": 0.5}


def _select_model(src, dst, kinds: Sequence[str], current: Projective, probes) -> tuple:
    """The model among ``kinds`` that predicts held-out parts of the pairs best
    (:func:`registration.geometry.model_choice.simplest_supported`, spatial cross-validation): an affine's or
    a projective's extra terms are kept only where the points span enough of the frame
    (:data:`COARSE_MIN_COVERAGE`), since undetermined ones extrapolate badly at the frame's
    corners. Returns ``(Projective, kind)``."""
    fits = []
    for kind in ("similarity", "affine", "projective"):
        if kind in kinds:
            m = current if kind == "projective" else _MODELS[kind].estimate(src, dst)
            if m:
                fits.append((kind, m))
    if not fits:
        return current, "projective"
    kind, model = simplest_supported(
        fits, src, dst, probes=probes, min_coverage=COARSE_MIN_COVERAGE
    )
    return (model if kind == "projective" else model.as_projective()), kind


def projective_or_simpler(
    src: NDArray, dst: NDArray, fitted: Projective, config: CoarseConfig, probes, scale: float
) -> tuple[Projective, str]:
    """``(model, kind)``: the projective ``fitted`` to the inlier pairs ``src -> dst`` (px at
    ``scale``) when they span at least :data:`COARSE_MIN_COVERAGE`'s share for it of ``probes``
    (full-scale corrected px over the frame; None = no check), else the model
    :func:`_select_model` chooses among ``config.models`` (a projective on matches in one part
    of the frame can put its far side hundreds of pixels off)."""
    if probes is None or len(config.models) < 2:
        return fitted, "projective"
    probes = rescale(probes, scale)
    if hull_coverage(src, probes) >= COARSE_MIN_COVERAGE["projective"]:
        return fitted, "projective"
    return _select_model(src, dst, config.models, fitted, probes)


@dataclass
class _Attempt:
    """One prior's outcome, in coarse pixels: every ratio match plus the guided ones (``gated``
    marks those the gate let through), the inliers of the kept model among them, and ``score``:
    how many gated candidates the kept model fits (its support)."""

    model: Projective | None
    kind: str
    frame_xy: NDArray
    base_xy: NDArray
    gated: NDArray
    inliers: NDArray
    reason: str
    score: int = 0


def _attempt(
    prior: SimilarityPrior,
    frame: CoarseFeatures,
    base: CoarseFeatures,
    matches: sift.Matches,
    config: CoarseConfig,
    rng: np.random.Generator,
    anchored: bool,
    domain: NDArray,
) -> _Attempt:
    """Gate (and guide) the matches with a coarse-pixel prior, RANSAC, refine (module doc).

    Consensus searches (:func:`_consensus`) on two sets of pairs when ``guided``: the gated
    ratio matches (the paper; right matches are then often the majority, and a strongly tilted
    frame's perspective survives), and those plus the guided matches, pre-filtered by a
    similarity through the anchor (more right matches when the ratio test keeps few, as across
    years and sensors); each from a projective and from an affine RANSAC. The search whose
    model fits the most gated candidates wins, the simplest model among those within
    ``_NEAR_BEST`` of it. ``domain``: centres of a 10 x 10 grid of cells over the frame in
    coarse corrected pixels (for the model choice).
    """
    hcfg = config.heading
    fk, bk = frame.keypoints, base.keypoints
    all_p, all_q = fk.xy[matches.idx_a], bk.xy[matches.idx_b]
    gated = heading.gate_by_prior(all_p, all_q, prior, hcfg)
    n_ratio = len(all_p)
    if config.guided and len(fk):
        radius = heading.gate_radius_px(prior, fk.xy, hcfg)
        g = heading.guided_matches(
            fk, bk, prior.apply(fk.xy), radius, prior.heading_deg, prior.scale, hcfg
        )
        new = ~np.isin(g.idx_a, matches.idx_a[gated])
        all_p = np.vstack([all_p, fk.xy[g.idx_a[new]]])
        all_q = np.vstack([all_q, bk.xy[g.idx_b[new]]])
        gated = np.concatenate([gated, np.ones(int(new.sum()), bool)])
    out = _Attempt(None, "", all_p, all_q, gated, np.zeros(len(all_p), bool), "")
    sources = [np.flatnonzero(gated[:n_ratio])]
    if config.guided:
        sources.append(_similarity_prefilter(all_p, all_q, np.flatnonzero(gated), prior, config,
                                             rng, anchored))  # fmt: skip
    found_all = []
    firsts = [Projective] + ([Affine] if "affine" in config.models and config.guided else [])
    for idx in sources:
        if len(idx) < Projective.min_samples:
            continue
        for first in firsts:
            found = _consensus(all_p[idx], all_q[idx], fk, bk, prior, config, rng, domain, first)
            if found is None:
                continue
            # One yardstick for every search: the gated candidates the final model fits (the
            # refinement's own matches would favour a search that confirms itself).
            support = _support(found[0], all_p[gated], all_q[gated], config)
            found_all.append((support, found))
    best, best_support = None, -1
    if found_all:
        top = max(f[0] for f in found_all)
        # The simplest model among the nearly best wins (ties: the first found).
        near = [f for f in found_all if f[0] >= _NEAR_BEST * top]
        best_support, best = min(near, key=lambda f: _COMPLEXITY[f[1][1]])
    if best is None:
        n = int(gated.sum())
        out.reason = (
            f"only {n} matches agree with the heading {prior.heading_deg:.0f}° and scale "
            f"{prior.scale * frame.scale / base.scale:.2f} estimated {_from(prior)}"
            if n < Projective.min_samples
            else f"RANSAC found no consensus among the {n} gated matches"
        )
        return out
    model, kind, fit_p, fit_q = best
    out.model, out.kind, out.score = model, kind, best_support
    out.inliers = gated & (np.hypot(*(model.apply(all_p) - all_q).T) < config.ransac.threshold_px)
    return out


def _support(model, p, q, config: CoarseConfig) -> int:
    return int(np.count_nonzero(np.hypot(*(model.apply(p) - q).T) < config.ransac.threshold_px))


def _similarity_prefilter(p, q, idx, prior, config, rng, anchored) -> NDArray:
    """The pairs ``idx`` consistent with a similarity through the anchor (one pair plus the seed
    per sample): most wrong guided matches go before the projective RANSAC."""
    if len(idx) < Similarity.min_samples + 1:
        return idx
    extent = float(np.ptp(p[idx], axis=0).max())
    thr = (
        config.ransac.threshold_px
        + prior.anchor_error_px
        + config.prefilter_slope * prior.scale * extent
    )
    fixed = (prior.anchor_frame[None], prior.anchor_base[None]) if anchored else None
    cfg = _ransac_config(config, sample_size=2, threshold_px=thr, refine="lstsq", min_inliers=4)
    sim = ransac(p[idx], q[idx], Similarity, cfg, rng, fixed=fixed)
    if sim and sim.n_inliers >= Projective.min_samples:
        return idx[sim.inliers]
    return idx


# Searches whose support is within this share of the best count as equally good; the simplest
# model among them is kept (a richer one fits a few more pairs of a partial overlap and
# extrapolates worse).
_NEAR_BEST = 0.9
_COMPLEXITY = {"similarity": 0, "affine": 1, "projective": 2}


def _consensus(p, q, fk, bk, prior, config, rng, domain, first=Projective):
    """RANSAC on the pairs (the ``first`` model: projective, or affine then refitted as a
    projective), the model the points support (:func:`_select_model`), then ``refine_rounds``
    of guided re-matching within ``refine_radius_px`` of that model and a projective RANSAC on
    those matches; a round that fits fewer of the original pairs is undone. Returns ``(model,
    kind, fitted frame px, fitted base px)`` or None."""
    fit = ransac(p, q, first, _ransac_config(config, sample_size=first.min_samples), rng)
    if not fit:
        return None
    start = fit.model if first is Projective else fit.model.as_projective()
    if first is not Projective:
        refit = Projective.estimate(p[fit.inliers], q[fit.inliers], initial=start, optimizer="lm")
        start = refit if refit else start
    model, kind = _select_model(p[fit.inliers], q[fit.inliers], config.models, start, domain)
    best = (model, kind, p[fit.inliers], q[fit.inliers])
    support = _support(model, p, q, config)
    for _ in range(config.refine_rounds):
        g = heading.guided_matches(
            fk, bk, best[0].apply(fk.xy), config.refine_radius_px, prior.heading_deg,
            prior.scale, config.heading, ratio=0.95,
        )  # fmt: skip
        if len(g) < Projective.min_samples:
            break
        gp, gq = fk.xy[g.idx_a], bk.xy[g.idx_b]
        refit = ransac(gp, gq, Projective, config.ransac, rng)
        if not refit:
            break
        m, k = _select_model(gp[refit.inliers], gq[refit.inliers], config.models, refit.model,
                             domain)  # fmt: skip
        s = _support(m, p, q, config)
        if s < support:
            break
        best, support = (m, k, gp[refit.inliers], gq[refit.inliers]), s
    return best


def _from(prior: SimilarityPrior) -> str:
    return {"two seeds": "from the two seeds", "seed": "around the seed"}.get(
        prior.source, "without a seed"
    )


def fit_coarse(
    frame_feats: CoarseFeatures,
    refs: list[tuple[CoarseFeatures, Callable | None]],
    config: CoarseConfig,
    gate: Callable | None,
    rng: np.random.Generator,
    n_keypoints_base: int,
    known: list[sift.Matches | None] | None = None,
    probes: NDArray | None = None,
) -> CoarseResult:
    """Match the frame against each reference separately, gate, RANSAC at the coarse scale
    (the intra-sensor coarse step, paper 4.4).

    ``refs`` holds (features, to_base) pairs: ``to_base`` maps the reference's full-scale pixels
    to base pixels (None = already base pixels). Matching each reference on its own keeps the
    ratio test from rejecting a point because it appears in two references. ``known`` gives
    matches already computed, per reference (None = match here). ``gate`` is called with
    full-scale ``(frame_xy, base_xy)`` and returns a bool mask (None = no gate). With
    ``probes`` (``(N, 2)`` full-scale corrected px spread over the frame, e.g. cell centres),
    inliers spanning less than half of the frame get a simpler model
    (:func:`projective_or_simpler`): on a real roundabout at 320x240, a projective on 8 matches
    in one part of the frame put its far side up to 760 px off.
    """
    s = frame_feats.scale
    frame_xy, base_xy = [], []
    for i, (feats, to_base) in enumerate(refs):
        m = known[i] if known is not None else None
        if m is None:
            m = sift.match_ratio(frame_feats.keypoints, feats.keypoints, config.ratio)
        if len(m.idx_a) == 0:
            continue
        f_full = rescale(frame_feats.keypoints.xy[m.idx_a], 1.0 / s)
        b_full = rescale(feats.keypoints.xy[m.idx_b], 1.0 / feats.scale)
        if to_base is not None:
            b_full = to_base(b_full)
        frame_xy.append(f_full)
        base_xy.append(b_full)
    frame_xy = np.concatenate(frame_xy) if frame_xy else np.zeros((0, 2))
    base_xy = np.concatenate(base_xy) if base_xy else np.zeros((0, 2))
    ok = np.isfinite(base_xy).all(axis=1)
    gated = ok if gate is None else ok & gate(frame_xy, base_xy)
    inliers = np.zeros(len(frame_xy), bool)
    result = CoarseResult(
        success=False,
        reason="",
        base_from_corrected=None,
        frame_xy=frame_xy,
        base_xy=base_xy,
        gated=gated,
        inliers=inliers,
        n_keypoints_frame=len(frame_feats.keypoints.xy),
        n_keypoints_base=n_keypoints_base,
        gate="prediction from the previous frame" if gate is not None else "none",
    )
    n_gated = int(gated.sum())
    if n_gated < Projective.min_samples:
        reason = f"coarse step: only {n_gated} matches passed the location gate (need 4)"
        return replace(result, reason=reason)
    idx = np.flatnonzero(gated)
    fit = ransac(
        rescale(frame_xy[idx], s), rescale(base_xy[idx], s), Projective, config.ransac, rng
    )
    if not fit:
        return replace(result, reason=f"coarse step: RANSAC failed: {fit.reason}")
    inliers[idx[fit.inliers]] = True
    src, dst = rescale(frame_xy[inliers], s), rescale(base_xy[inliers], s)
    model, kind = projective_or_simpler(src, dst, fit.model, config, probes, s)
    return replace(
        result,
        model_kind=kind,
        base_from_corrected=quantized(model.rescaled(1.0 / s, 1.0 / s)),
        success=True,
    )
