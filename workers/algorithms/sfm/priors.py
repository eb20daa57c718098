"""Checking each frame's metadata attitude against what its matched pairs say, before it seeds a model.

Drone makers write the gimbal heading in two ways: the image top faces the yaw (the physical reading of
``datum.rotation_from_attitude``) or faces yaw + 180 degrees (the Phantom 3 frames of our test data), and a
flight may mix them, or carry a wrong angle on a frame. A frame's prior is tested against every verified
pair it is in: the pair's relative rotation from its essential matrix (and, where the GPS baseline is long
enough to give one, the direction of that baseline in the camera) must agree with the rotations the
priors give, under either convention. Each frame takes the convention its pairs agree with; a frame that
agrees with too few of its pairs under both is left out of the seed, and joins the model later by PnP on
its tracks, as a frame without metadata would.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from workers.algorithms.geometry import vector_from_rotation
from workers.algorithms.sfm.datum import Attitude, GpsFix, rotation_from_attitude

CONVENTIONS = ("yaw", "yaw+180")  # the camera's heading: the metadata yaw, or the opposite one
MAX_ROTATION_DEG = 10.0  # pair rotation from the priors vs from the essential matrix
MAX_BASELINE_DEG = 25.0  # baseline direction from GPS vs from the essential matrix
MIN_AGREEMENT = 0.5  # share of a frame's pairs that must agree with its prior


@dataclass(frozen=True)
class PriorCheck:
    """The verdict on every frame's attitude prior.

    rotations : frame -> (3, 3) world -> camera rotation of the frames whose prior is kept, in their convention.
    conventions : frame -> "yaw" or "yaw+180", for the kept frames.
    rejected : frame -> why its prior was not used (in words).
    """

    rotations: dict[int, np.ndarray]
    conventions: dict[int, str]
    rejected: dict[int, str]


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of the rotation ``R`` (3, 3), degrees."""
    return float(np.degrees(np.linalg.norm(vector_from_rotation(R))))


def candidate_rotations(attitude: Attitude) -> tuple[np.ndarray, np.ndarray]:
    """World -> camera rotation of an attitude read in each of ``CONVENTIONS``: as written, and with the heading
    turned by 180 degrees (for a nadir frame: the image top facing the other way)."""
    return rotation_from_attitude(attitude), rotation_from_attitude(replace(attitude, yaw=attitude.yaw + 180.0))


def check_attitude_priors(
    relative: Mapping[tuple[int, int], tuple[np.ndarray, np.ndarray]],
    attitude: Mapping[int, Attitude],
    gps: Mapping[int, GpsFix],
) -> PriorCheck:
    """Which frames' attitude priors fit their pairs, and in which convention.

    Parameters
    ----------
    relative : (i, j) -> (R (3, 3), t (3,)) of verified pairs: ``X_j = R X_i + t`` from the essential matrix,
        ``|t| = 1`` (``tracks.relative_pose``).
    attitude : frame -> its metadata attitude (frames without one are not judged).
    gps : frame -> its GPS fix; the baseline direction is compared only where both frames have one and the
        baseline is over four times their horizontal accuracy.

    Returns
    -------
    PriorCheck. A frame is kept when at least ``MIN_AGREEMENT`` of its pairs with other judged frames agree
    (rotation within ``MAX_ROTATION_DEG``, baseline within ``MAX_BASELINE_DEG``) with its and its neighbour's
    chosen conventions. A frame in no such pair keeps its prior unchecked: it has no verified match to seed
    anything, and the check after the adjustment (``reconstruction._recheck_frames``) leaves it out if it
    never gains observations. Without a usable GPS baseline, "both frames turned" cannot be told from
    "neither" by rotations alone; the flight then starts in the convention most pairs share, and the seed's
    triangulation test falls back to an incremental start if that was wrong.
    """
    frames = sorted(attitude)
    candidates = {f: candidate_rotations(attitude[f]) for f in frames}
    pairs = [(i, j) for (i, j) in relative if i in candidates and j in candidates]
    agree = {
        (i, j): _agreement(relative[(i, j)], candidates[i], candidates[j], gps.get(i), gps.get(j)) for (i, j) in pairs
    }
    choice = _choose_conventions(frames, agree)
    kept: dict[int, np.ndarray] = {}
    conventions: dict[int, str] = {}
    rejected: dict[int, str] = {}
    for f in frames:
        mine = [(i, j) for (i, j) in pairs if f in (i, j)]
        good = sum(bool(agree[(i, j)][choice[i], choice[j]]) for (i, j) in mine)
        if mine and good < MIN_AGREEMENT * len(mine):
            rejected[f] = (
                f"its attitude (yaw {attitude[f].yaw:.1f}, pitch {attitude[f].pitch:.1f}) disagrees with "
                f"{len(mine) - good} of its {len(mine)} matched pairs in either heading convention"
            )
            continue
        kept[f], conventions[f] = candidates[f][choice[f]], CONVENTIONS[choice[f]]
    return PriorCheck(kept, conventions, rejected)


def _agreement(
    pair: tuple[np.ndarray, np.ndarray],
    cand_i: tuple[np.ndarray, np.ndarray],
    cand_j: tuple[np.ndarray, np.ndarray],
    gps_i: GpsFix | None,
    gps_j: GpsFix | None,
) -> np.ndarray:
    """(2, 2) bool: whether the pair agrees with frame i in convention a and frame j in convention b."""
    R_ij, t_ij = pair
    baseline = None
    if gps_i is not None and gps_j is not None:
        d = np.asarray(gps_i.position) - np.asarray(gps_j.position)
        if np.linalg.norm(d[:2]) > 4.0 * max(gps_i.sigma_h, gps_j.sigma_h):
            baseline = d / np.linalg.norm(d)
    out = np.zeros((2, 2), bool)
    for a in range(2):
        for b in range(2):
            Ri, Rj = cand_i[a], cand_j[b]
            ok = rotation_angle_deg(Rj @ Ri.T @ R_ij.T) <= MAX_ROTATION_DEG
            if ok and baseline is not None:  # camera i's centre seen from camera j: t ~ R_j (C_i - C_j)
                cos = float(np.clip((Rj @ baseline) @ (t_ij / np.linalg.norm(t_ij)), -1.0, 1.0))
                ok = np.degrees(np.arccos(cos)) <= MAX_BASELINE_DEG
            out[a, b] = ok
    return out


def _choose_conventions(frames: list[int], agree: Mapping[tuple[int, int], np.ndarray]) -> dict[int, int]:
    """Each frame's convention (index into ``CONVENTIONS``): start from the one that fits the most pairs if all
    frames shared it, then let each frame take the convention its neighbours agree with most (iterated
    conditional modes; a handful of sweeps settle a flight)."""
    shared = [sum(bool(m[c, c]) for m in agree.values()) for c in range(2)]
    choice = dict.fromkeys(frames, int(np.argmax(shared)))
    for _ in range(10):
        changed = False
        for f in frames:
            score = [0, 0]
            for (i, j), m in agree.items():
                if i == f:
                    score = [score[c] + int(m[c, choice[j]]) for c in range(2)]
                elif j == f:
                    score = [score[c] + int(m[choice[i], c]) for c in range(2)]
            best = int(np.argmax(score)) if score[0] != score[1] else choice[f]
            if best != choice[f]:
                choice[f], changed = best, True
        if not changed:
            break
    return choice
