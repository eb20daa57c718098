"""The fast paths of matching give what the plain ones give: a frame's FLANN index built once and shared by
its pairs, and the batched NCC refinement of tie points against one ``cv2.matchTemplate`` per point."""

from __future__ import annotations

import cv2
import numpy as np

from tests.scenes import make_texture
from workers.algorithms.mosaic import (
    FlannIndex,
    OverlapGuide,
    apply_homography,
    match_index,
    match_ratio,
    refine_tie_points,
    refit_homography,
)
from workers.algorithms.mosaic.features import in_predicted_overlap

PLANTED = np.array([[0.97, -0.08, 30.0], [0.07, 1.01, -20.0], [1e-5, -2e-5, 1.0]])


def _refine_per_point(gray_i, gray_j, points_i, points_j, H_ij, h=7, s=3, min_ncc=0.8):
    """The reference: a warp, a ``cv2.matchTemplate`` and a ``cv2.minMaxLoc`` per point."""
    out_i, out_j = np.asarray(points_i, float).copy(), np.asarray(points_j, float).copy()
    refined = np.zeros(len(out_i), bool)
    side = 2 * (h + s) + 1
    height, width = gray_i.shape
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP

    def vertex(left, centre, right):
        den = left - 2.0 * centre + right
        return 0.0 if den >= 0 else float(np.clip(0.5 * (left - right) / den, -0.5, 0.5))

    for k, (cx, cy) in enumerate(np.rint(out_i).astype(int)):
        if not (h <= cx < width - h and h <= cy < height - h):
            continue
        template = gray_i[cy - h : cy + h + 1, cx - h : cx + h + 1]
        if template.std() < 2.0:
            continue
        origin = np.array([[1.0, 0.0, cx - h - s], [0.0, 1.0, cy - h - s], [0.0, 0.0, 1.0]])
        search = cv2.warpPerspective(gray_j, H_ij @ origin, (side, side), flags=flags)
        score = cv2.matchTemplate(search, template, cv2.TM_CCOEFF_NORMED)
        _, best, _, (px, py) = cv2.minMaxLoc(score)
        if best < min_ncc or not (0 < px < 2 * s and 0 < py < 2 * s):
            continue
        dx = px - s + vertex(score[py, px - 1], score[py, px], score[py, px + 1])
        dy = py - s + vertex(score[py - 1, px], score[py, px], score[py + 1, px])
        out_i[k] = (cx, cy)
        out_j[k] = apply_homography(H_ij, np.array([[cx + dx, cy + dy]]))[0]
        refined[k] = True
    return out_i, out_j, refined


def test_batched_refinement_gives_the_per_point_matchtemplate_result() -> None:
    rng = np.random.default_rng(21)
    gray_i = cv2.cvtColor(make_texture(480, 640, seed=12), cv2.COLOR_BGR2GRAY)
    gray_i[300:420, 40:200] = 128  # a flat patch: its points are left as given by both
    gray_j = cv2.warpPerspective(gray_i, PLANTED, (700, 500), flags=cv2.INTER_LINEAR)
    points_i = np.vstack([rng.uniform([5, 5], [635, 475], (600, 2)), [[1.2, 3.0], [638.6, 200.0], [100.0, 350.0]]])
    points_j = apply_homography(PLANTED, points_i) + rng.uniform(-1.5, 1.5, (len(points_i), 2))
    fast = refine_tie_points(gray_i, gray_j, points_i, points_j, PLANTED)
    slow = _refine_per_point(gray_i, gray_j, points_i, points_j, PLANTED)
    both = fast[2] & slow[2]
    assert slow[2].sum() > 300 and not fast[2][-3:].any()  # off the edge, off the edge, flat
    assert (fast[2] != slow[2]).sum() <= 3  # a peak exactly at min_ncc or a tie may fall either way
    assert np.array_equal(fast[0][both], slow[0][both])
    assert np.abs(fast[1][both] - slow[1][both]).max() < 0.02  # float32 scores there, float64 here
    assert np.array_equal(fast[1][~fast[2]], points_j[~fast[2]])
    error = np.linalg.norm(fast[1][fast[2]] - apply_homography(PLANTED, fast[0][fast[2]]), axis=1)
    assert np.sqrt(np.mean(error**2)) < 0.1


def test_refinement_of_no_points_is_empty() -> None:
    gray = cv2.cvtColor(make_texture(100, 100, seed=1), cv2.COLOR_BGR2GRAY)
    out_i, out_j, refined = refine_tie_points(gray, gray, np.zeros((0, 2)), np.zeros((0, 2)), np.eye(3))
    assert out_i.shape == out_j.shape == (0, 2) and refined.shape == (0,)


def test_shared_frame_indices_give_the_matches_built_per_pair() -> None:
    rng = np.random.default_rng(5)
    descs = [rng.random((700, 128)).astype(np.float32) for _ in range(3)]
    descs[1][:400] = descs[0][200:600] + rng.normal(0, 0.01, (400, 128)).astype(np.float32)
    indices = [FlannIndex(d) for d in descs]
    for a, b in [(0, 1), (1, 0), (0, 2), (1, 2)]:
        shared = match_ratio(descs[a], descs[b], 0.8, 25, (indices[a], indices[b]))
        assert np.array_equal(shared, match_ratio(descs[a], descs[b], 0.8, 25))
    assert len(match_ratio(descs[0], descs[1], 0.8, 25, (indices[0], indices[1]))) > 380
    assert len(match_ratio(descs[0], descs[2], 0.8, 25, (indices[0], indices[2]))) == 0  # no overlap


def test_match_index_only_for_the_opencv_path() -> None:
    desc = np.random.default_rng(0).random((50, 128)).astype(np.float32)
    assert isinstance(match_index(desc, "sift", "cpu"), FlannIndex)
    assert match_index(desc, "harris_ncc", "cpu") is None
    assert match_index(desc, "sift", "cuda") is None
    assert match_index(desc[:1], "sift", "cpu") is None  # too few to match: match_ratio returns empty


def test_guided_matching_keeps_every_match_of_the_overlap() -> None:
    rng = np.random.default_rng(9)
    size = (1000, 800)
    points_a = rng.uniform([0, 0], size, (2400, 2)).astype(np.float32)
    shift = np.array([[1.0, 0.0, -550.0], [0.0, 1.0, 30.0], [0.0, 0.0, 1.0]])  # a 45 % side overlap
    mapped = apply_homography(shift, points_a)
    seen = np.all((mapped >= 0) & (mapped < size), axis=1)
    desc_a = rng.random((2400, 128)).astype(np.float32)
    desc_b = rng.random((2400, 128)).astype(np.float32)  # what b sees outside the overlap: other ground
    points_b = rng.uniform([0, 0], size, (2400, 2)).astype(np.float32)
    desc_b[: seen.sum()] = desc_a[seen] + rng.normal(0, 0.01, (seen.sum(), 128)).astype(np.float32)
    points_b[: seen.sum()] = mapped[seen]
    guide = OverlapGuide(points_a, points_b, size, 2.0)
    full = match_ratio(desc_a, desc_b, 0.8, 25)
    guided = match_ratio(desc_a, desc_b, 0.8, 25, guide=guide)
    true_rows = np.flatnonzero(seen)
    assert set(map(tuple, guided.tolist())) <= set(map(tuple, full.tolist()))
    assert np.isin(true_rows, guided[:, 0]).mean() > 0.97  # the overlap's matches are all still found
    rows = np.arange(2400)
    probe = np.flatnonzero(np.isin(rows, true_rows[::8]))
    inside = in_predicted_overlap(guide, probe, np.searchsorted(true_rows, probe), rows)
    assert inside[seen].all() and inside.mean() < 0.6  # the model's overlap, grown by the margin only
    few = in_predicted_overlap(guide, probe[:5], np.searchsorted(true_rows, probe[:5]), rows)
    assert few.all()  # too few probe matches to predict anything: search everywhere


def test_refit_homography_recovers_the_model_from_refined_points() -> None:
    rng = np.random.default_rng(4)
    points_i = rng.uniform(0, 1000, (300, 2))
    points_j = apply_homography(PLANTED, points_i) + rng.normal(0, 0.05, (300, 2))
    points_j[:30] += rng.uniform(5, 20, (30, 2))  # not on the plane
    start = PLANTED @ np.array([[1.0, 0.0, 0.8], [0.0, 1.0, -0.6], [0.0, 0.0, 1.0]])  # a coarse model
    H, close = refit_homography(points_i, points_j, start, 2.0)
    assert not close[:30].any() and close[30:].all()
    corners = np.array([[0.0, 0.0], [1000.0, 0.0], [0.0, 1000.0], [1000.0, 1000.0]])
    assert np.abs(apply_homography(H, corners) - apply_homography(PLANTED, corners)).max() < 0.1


def test_recent_cache_builds_each_value_once_and_keeps_the_most_recent() -> None:
    import threading

    from workers.parallel import RecentCache

    builds: list[int] = []
    gate = threading.Event()

    def build(k: int) -> FlannIndex | None:
        gate.wait(5)
        builds.append(k)
        return match_index(np.random.default_rng(k).random((60, 128)).astype(np.float32), "sift", "cpu")

    cache: RecentCache[FlannIndex | None] = RecentCache(2)
    got: list[FlannIndex | None] = []
    threads = [threading.Thread(target=lambda: got.append(cache.get(0, lambda: build(0)))) for _ in range(4)]
    for t in threads:
        t.start()
    gate.set()
    for t in threads:
        t.join()
    assert builds == [0] and all(g is got[0] for g in got) and isinstance(got[0], FlannIndex)  # once, shared
    cache.get(1, lambda: build(1))
    cache.get(0, lambda: build(0))  # used again: now the most recent
    cache.get(2, lambda: build(2))  # evicts 1, the least recent
    cache.get(0, lambda: build(0))
    cache.get(1, lambda: build(1))
    assert builds == [0, 1, 2, 1]
    assert match_index(np.zeros((5, 32), np.uint8), "harris_ncc", "cpu") is None
