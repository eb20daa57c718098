"""Stage ``align_frames``: every frame into one plane (spanning tree, then global least squares)."""

from __future__ import annotations

from typing import Any

import numpy as np

from workers.algorithms.geometry import similarity_scale
from workers.algorithms.mosaic import (
    TiePoints,
    apply_homography,
    chain_homographies,
    corner_sigmas,
    fit_plane_to_map,
    is_plausible,
    level_plane,
    refine_homographies,
    spanning_tree,
    tie_residuals_px,
)
from workers.config import MosaicConfig
from workers.pipeline import PipelineError
from workers.records import Alignment, DroppedPair, Frame, PairRecord, PairResidual, RejectedFrame
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

MAX_ROUNDS = 5  # adjustments, each after dropping the worst inconsistent pair
MAX_PAIR_RMS_FACTOR = 1.5  # a pair is inconsistent above this multiple of the RANSAC threshold
CONFLICT_FACTOR = 2.0  # a pair is strained when its adjusted tie RMS exceeds this multiple of its own fit


def run(ws: JobWorkspace, cfg: MosaicConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Read ``pairs.json`` and the tie points; write ``alignment.json`` (frame -> plane homographies)."""
    frames = {f.index: f for f in ws.load_frames()}
    pairs = [p for p in ws.load_pairs() if p.accepted]
    dropped: list[DroppedPair] = []
    inlier_px = _inlier_px(cfg, frames)
    for round_ in range(MAX_ROUNDS):
        progress(round_ / MAX_ROUNDS, f"adjustment round {round_ + 1}")
        root, refined, ties = _adjust(ws, cfg, frames, pairs)
        bad = _inconsistent_pairs(refined, ties, MAX_PAIR_RMS_FACTOR * inlier_px)
        reason = "inconsistent with the other pairs after adjustment"
        if not bad:
            bad = _conflicting_pair(pairs, refined, ties, 0.5 * inlier_px)
            reason = "weakest overlap pulling a neighbouring pair away from its own fit"
        if not bad or round_ == MAX_ROUNDS - 1:  # the last adjustment is always over the pairs kept
            break
        # A pair whose tie points stay far apart once every other pair has had its say is a false
        # overlap (repeated texture, moving objects): drop it and adjust again without it.
        dropped += [DroppedPair(p.i, p.j, reason) for p in pairs if p.pair in bad]
        pairs = [p for p in pairs if p.pair not in bad]
    sizes = {k: (frames[k].width, frames[k].height) for k in refined}
    rejected = _rejections(frames, refined, sizes)
    used = {k: H for k, H in refined.items() if k not in {r.index for r in rejected}}
    residuals = tie_residuals_px(used, ties)
    all_res = np.concatenate(list(residuals.values())) if residuals else np.zeros(0)
    rms = float(np.sqrt(np.mean(all_res**2))) if len(all_res) else None
    ws.save_alignment(
        Alignment(
            reference=root,
            homographies=dict(sorted(used.items())),
            rejected=rejected,
            tie_point_rms_px=rms,
            tie_points=len(all_res),
            dropped_pairs=dropped,
            pair_residuals=[
                PairResidual(i, j, float(np.sqrt(np.mean(r**2))), float(r.max()))
                for (i, j), r in sorted(residuals.items())
            ],
            corner_sigma_px=_corner_sigmas(cfg, frames, used, ties),
        )
    )
    progress(1.0, f"{len(used)} frames aligned")
    return {"reference": root, "frames_aligned": len(used), "frames_rejected": len(rejected), "tie_point_rms_px": rms}


def _inlier_px(cfg: MosaicConfig, frames: dict[int, Frame]) -> float:
    """The homography inlier threshold on the frames' working copies (``MosaicConfig.threshold_scale``)."""
    return cfg.inlier_px(max(max(f.width, f.height) for f in frames.values()))


def _adjust(
    ws: JobWorkspace,
    cfg: MosaicConfig,
    frames: dict[int, Frame],
    pairs: list[PairRecord],
) -> tuple[int, dict[int, np.ndarray], dict[tuple[int, int], TiePoints]]:
    """Spanning tree over ``pairs``, chained initial homographies, then the global adjustment."""
    root, parent = spanning_tree(max(frames) + 1, {p.pair: float(p.inliers) for p in pairs})
    if not parent:
        raise PipelineError(
            "no two frames overlap: no pair had enough matching points "
            f"(at least {cfg.min_inliers} homography inliers); check the photos overlap"
        )
    initial = chain_homographies(root, parent, {p.pair: p.model for p in pairs if p.model is not None})
    ties = {p.pair: TiePoints(*ws.load_matches(p.pair)) for p in pairs if p.i in initial and p.j in initial}
    return root, adjust_plane(cfg, frames, initial, root, ties), ties


def adjust_plane(
    cfg: MosaicConfig,
    frames: dict[int, Frame],
    initial: dict[int, np.ndarray],
    root: int,
    ties: dict[tuple[int, int], TiePoints],
) -> dict[int, np.ndarray]:
    """Frame -> plane homographies of the frames in ``initial`` (the chained start, ``root`` the identity):
    adjusted by the tie points, levelled, then adjusted with the frames' GPS fixes if they have enough."""
    sizes = {k: (frames[k].width, frames[k].height) for k in initial}
    inlier_px = _inlier_px(cfg, frames)

    def adjust(
        start: dict[int, np.ndarray],
        positions: dict[int, tuple[np.ndarray, float]],
        fixed: int | None = root,
        shape_weight: float = 0.0,
    ) -> dict[int, np.ndarray]:
        return refine_homographies(
            start,
            ties,
            fixed,
            sizes,
            loss_scale_px=inlier_px,
            perspective_damping=cfg.perspective_damping,
            positions=positions,
            shape_weight=shape_weight,
        )

    # Tie points alone first, then the plane levelled (the root frame's tilt taken out of it).
    levelled = level_plane(adjust(initial, {}), sizes)
    refined = levelled
    # With GPS, the fixes join the adjustment: their similarity to the plane is fitted to the tie-point
    # solution, then every frame is pulled towards its fix by the fix's accuracy against the tie points'
    # own (their measured sigma), and again with the similarity refitted to that. Each round starts from the
    # levelled tie-point solution: the perspective damping holds to where it starts, and restarting from
    # a solution the fixes have bent would let the bend grow.
    #
    # A strip's frames also have square pixels (``strip_square_pixels``), a prior of both rounds. In the first no
    # frame is held: the fixes place the plane and the prior shapes it. Held, the root frame would keep the tilt
    # levelling guessed from a tie-point solution whose frames' widths were free (at 50 % forward overlap: the
    # plane 8000 px out of true at a 305-frame strip's ends; every other frame followed it against its fix,
    # corners 822 px off). That solution levelled, the second holds its root again: free, the fixes' noise along
    # a straight strip stretched the plane against the prior (55 %, 60 frames: corners 4.4 px off, 1.2 held; with
    # misses counted in the photos' pixels, 50 %, 305 frames: 4.1 px free, 3.9 held, median of four draws).
    tie_sigma = _tie_sigma_px(levelled, ties)
    square = cfg.strip_square_pixels if cfg.mode == "strip" else 0.0
    start = levelled
    for round_ in range(GPS_ROUNDS):
        positions = gps_positions(frames, refined, cfg.gps_sigma_m, cfg.min_gps_frames)
        if not positions:
            break
        weighed = {k: (xy, sigma / tie_sigma) for k, (xy, sigma) in positions.items()}
        if not square:
            refined = adjust(levelled, weighed)
        elif round_ == 0:
            refined = start = level_plane(adjust(levelled, weighed, None, tie_sigma / square), sizes)
        else:
            refined = adjust(start, weighed, root, tie_sigma / square)
    return refined


def _corner_sigmas(
    cfg: MosaicConfig, frames: dict[int, Frame], homs: dict[int, np.ndarray], ties: dict[tuple[int, int], TiePoints]
) -> dict[int, float]:
    """A strip's frames' corner precision (:func:`corner_sigmas`) under the weights :func:`adjust_plane` gave
    its last round; empty in the other modes (no square-pixel prior, so along a straight line of fixes the
    datum's shape would be unfixed) or without enough GPS."""
    square = cfg.strip_square_pixels if cfg.mode == "strip" else 0.0
    if not square or len(homs) < 2:
        return {}
    tie_sigma = _tie_sigma_px(homs, ties)
    positions = gps_positions(frames, homs, cfg.gps_sigma_m, cfg.min_gps_frames)
    weighed = {k: (xy, sigma / tie_sigma) for k, (xy, sigma) in positions.items()}
    sizes = {k: (frames[k].width, frames[k].height) for k in homs}
    return corner_sigmas(homs, ties, sizes, weighed, tie_sigma / square, _inlier_px(cfg, frames))


GPS_ROUNDS = 2  # adjustments with GPS inside, each after refitting the GPS similarity to the plane
MIN_TIE_SIGMA_PX = 0.01  # floor of the tie points' measured sigma: a noiseless synthetic pair would mute GPS


def _tie_sigma_px(homs: dict[int, np.ndarray], ties: dict[tuple[int, int], TiePoints]) -> float:
    """The tie points' sigma per coordinate (px), robustly from their misses: the median of a 2-D normal
    miss is 1.1774 sigma. The adjustment counts a tie residual as if its sigma were 1 px, so a fix's sigma
    is divided by this: both then weigh by their accuracy (with 1 px, the 1 m fixes of a strip measured to
    0.02 px bent it by 4 px at its corners)."""
    misses = tie_residuals_px(homs, ties)
    if not misses:
        return 1.0
    return max(float(np.median(np.concatenate(list(misses.values())))) / 1.1774, MIN_TIE_SIGMA_PX)


def gps_positions(
    frames: dict[int, Frame], homs: dict[int, np.ndarray], sigma_m: float, min_frames: int
) -> dict[int, tuple[np.ndarray, float]]:
    """Frame -> (where its GPS fix puts its centre in the plane, px; that fix's accuracy, px) through the
    similarity that best fits the fixes to ``homs``; empty with fewer than ``min_frames`` fixes or too
    little spread between them to fit a similarity (then the adjustment is by tie points alone)."""
    with_gps = [k for k in sorted(homs) if frames[k].gps]
    if len(with_gps) < min_frames:
        return {}
    latlon = np.array([[gps["lat"], gps["lon"]] for k in with_gps if (gps := frames[k].gps)])
    centres = np.concatenate([apply_homography(homs[k], _centre(frames[k])) for k in with_gps])
    fit = fit_plane_to_map(centres, latlon)
    if isinstance(fit, str):
        return {}
    _, plane_to_map, utm = fit
    gsd = similarity_scale(plane_to_map)
    targets = apply_homography(np.linalg.inv(plane_to_map), utm)
    return {k: (targets[n], (frames[k].gps_accuracy_m or sigma_m) / gsd) for n, k in enumerate(with_gps)}


def _inconsistent_pairs(
    homs: dict[int, np.ndarray], ties: dict[tuple[int, int], TiePoints], limit_px: float
) -> set[tuple[int, int]]:
    residuals = tie_residuals_px(homs, ties)
    rms = {pair: float(np.sqrt(np.mean(r**2))) for pair, r in residuals.items()}
    worst = max(rms, key=lambda pair: rms[pair], default=None)
    # One at a time: a single false pair drags its neighbours' residuals up too.
    return {worst} if worst is not None and rms[worst] > limit_px else set()


def _conflicting_pair(
    pairs: list[PairRecord], homs: dict[int, np.ndarray], ties: dict[tuple[int, int], TiePoints], floor_px: float
) -> set[tuple[int, int]]:
    """The weakest pair (fewest inliers) sharing a frame with the pair the adjustment strains most, if any.

    A pair whose tie points fit its own homography but meet more than ``CONFLICT_FACTOR`` times worse (and
    over ``floor_px``) after the adjustment is pulled by a pair that disagrees with it: on real flights, a
    small overlap between frames two apart, where lens distortion and relief weigh most. The weakest pair
    touching its frames is dropped, never one whose loss would disconnect a frame.
    """
    adjusted = tie_residuals_px(homs, ties)
    # frame i as the plane: frame j maps onto it through the inverse of the pair model (i -> j)
    own = {
        p.pair: tie_residuals_px({0: np.eye(3), 1: np.linalg.inv(p.model)}, {(0, 1): ties[p.pair]})
        for p in pairs
        if p.pair in ties and p.model is not None
    }
    strain = {}
    for pair, r in adjusted.items():
        fit = own[pair].get((0, 1)) if pair in own else None
        rms, fit_rms = float(np.sqrt(np.mean(r**2))), float(np.sqrt(np.mean(fit**2))) if fit is not None else 0.0
        if rms > floor_px and rms > CONFLICT_FACTOR * max(fit_rms, 1e-6):
            strain[pair] = rms / max(fit_rms, 1e-6)
    if not strain:
        return set()
    worst = max(strain, key=lambda pair: strain[pair])
    frames_before = len(spanning_tree(max(homs) + 1, {p.pair: 1.0 for p in pairs})[1])
    for p in sorted((p for p in pairs if p.pair != worst and set(p.pair) & set(worst)), key=lambda p: p.inliers):
        rest = {q.pair: 1.0 for q in pairs if q.pair != p.pair}
        if len(spanning_tree(max(homs) + 1, rest)[1]) == frames_before:
            return {p.pair}
    return set()


def _rejections(
    frames: dict[int, Frame], refined: dict[int, np.ndarray], sizes: dict[int, tuple[int, int]]
) -> list[RejectedFrame]:
    out = []
    for k, f in sorted(frames.items()):
        if k not in refined:
            reason = "no overlap with the other frames (not enough matching points with any frame it was compared with)"
            out.append(RejectedFrame(k, f.name, reason))
        elif not is_plausible(refined[k], *sizes[k]):
            out.append(RejectedFrame(k, f.name, "alignment folds or stretches the frame"))
    return out


def _centre(frame: Frame) -> np.ndarray:
    """(1, 2) pixel (x, y) of the working copy's centre (pixel centres at integers)."""
    return np.array([[(frame.width - 1) / 2, (frame.height - 1) / 2]])
