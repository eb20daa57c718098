"""Strip tie points, coarse to fine, against the synthetic strip's known homographies.

Frames are the real camera's shape at reduced size (8000 x 400 px, long across track); the truth of a pair is
``inv(H_j) @ H_i`` (frame i px -> frame j px).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpu_kernels.backend import cuda_available
from tests.strip_scenes import SyntheticStrip, make_strip
from workers.algorithms.mosaic.alignment import apply_homography
from workers.algorithms.strips import (
    CoarseOptions,
    FramePyramid,
    PairTies,
    along_strip,
    build_pyramid,
    build_tracks,
    carry_ties,
    coarsest_level,
    distant_pairs,
    feasible_levels,
    filter_ties,
    fine_tie_points,
    open_windows,
    read_pyramid,
    register_coarse,
)
from workers.algorithms.strips.overlap import frame_outline, overlap_polygon

SIZE = (8000, 400)  # (width, height) px: long across track, as the real 75000 x 1800 frame
N_POINTS = 300

pytestmark = pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")


@pytest.fixture(scope="module")
def strip(tmp_path_factory: pytest.TempPathFactory) -> SyntheticStrip:
    return make_strip(tmp_path_factory.mktemp("strip"), 5, frame_size=SIZE, overlap=0.65, seed=3)


@pytest.fixture(scope="module")
def pyramids(strip: SyntheticStrip) -> list[FramePyramid]:
    top = coarsest_level(strip.frame_size)
    return [read_pyramid(path, 0, top + 1) for path in strip.paths]


def _truth(strip: SyntheticStrip, i: int, j: int) -> np.ndarray:
    return np.linalg.inv(strip.homographies[j]) @ strip.homographies[i]


def _corner_error(H: np.ndarray, truth: np.ndarray, corners: np.ndarray) -> float:
    return float(np.linalg.norm(apply_homography(H, corners) - apply_homography(truth, corners), axis=1).max())


def _rms(ties: PairTies, truth: np.ndarray) -> float:
    return float(np.sqrt((np.linalg.norm(apply_homography(truth, ties.points_a) - ties.points_b, axis=1) ** 2).mean()))


@pytest.mark.parametrize("pair", [(0, 1), (1, 2), (2, 3), (3, 4)])
def test_coarse_homography_maps_frame_corners_within_a_few_px(
    strip: SyntheticStrip, pyramids: list[FramePyramid], pair: tuple[int, int]
) -> None:
    i, j = pair
    result = register_coarse(pyramids[i], pyramids[j], min_spread=0.5)
    truth = _truth(strip, i, j)
    assert result.homography is not None and result.satisfied, result.reason
    assert result.level == coarsest_level(SIZE) == 3  # 1000 x 50 px: enough for a 65 % overlap
    assert result.spread >= 0.5 and min(result.extent_px) >= 0.5 * max(result.overlap_px)
    # The whole frame (extrapolated 130 px beyond the overlap) within a few px, the overlap within ~1.
    assert _corner_error(result.homography, truth, frame_outline(SIZE)) < 5.0
    assert _corner_error(result.homography, truth, overlap_polygon(truth, SIZE, SIZE)) < 1.5
    assert np.linalg.norm(apply_homography(truth, result.points_a) - result.points_b, axis=1).max() < 8.0


def test_a_prior_confines_the_matches_to_its_neighbourhood(strip: SyntheticStrip, pyramids: list[FramePyramid]) -> None:
    truth = _truth(strip, 0, 1)
    near = truth @ np.array([[1.0, 0, 20], [0, 1, -12], [0, 0, 1]])  # GPS-like: 20 px off
    guided = register_coarse(pyramids[0], pyramids[1], prior=near)
    assert guided.satisfied and guided.homography is not None
    assert _corner_error(guided.homography, truth, frame_outline(SIZE)) < 5.0
    far = truth @ np.array([[1.0, 0, 900], [0, 1, 0], [0, 0, 1]])  # nothing true within 64 px of it
    misled = register_coarse(pyramids[0], pyramids[1], prior=far)
    assert not misled.satisfied
    assert misled.homography is None or _corner_error(misled.homography, truth, frame_outline(SIZE)) > 100


def test_a_small_overlap_forces_a_finer_level(tmp_path: Path) -> None:
    # 15 % of 400 rows: 7 rows at level 3, too few for a 15 x 15 NCC window; level 1 has 30.
    small = make_strip(tmp_path, 2, frame_size=SIZE, overlap=0.15, seed=8)
    top = coarsest_level(SIZE)
    pyrs = [read_pyramid(path, 0, top + 1) for path in small.paths]
    result = register_coarse(pyrs[0], pyrs[1], min_spread=0.5)
    assert result.satisfied and result.homography is not None, result.reason
    assert result.level is not None and result.level < top
    assert [a.level for a in result.attempts][0] == top  # it started coarse and went finer
    assert all(a.inliers == 0 or a.spread < 0.5 for a in result.attempts[:-1])
    assert _corner_error(result.homography, _truth(small, 0, 1), overlap_polygon(_truth(small, 0, 1), SIZE, SIZE)) < 2


def test_texture_poor_pair_reports_the_closest_spread(strip: SyntheticStrip, pyramids: list[FramePyramid]) -> None:
    # Frame a flat (no corners, no NCC) beyond 30 % of its width at every level: no setting can spread the
    # inliers over half of the overlap.
    def flattened(pyramid: FramePyramid) -> FramePyramid:
        base = pyramid.image(pyramid.base_level).copy()
        base[:, int(0.3 * base.shape[1]) :] = 128
        return build_pyramid(base, pyramid.full_size, pyramid.base_level, len(pyramid.images))

    result = register_coarse(flattened(pyramids[0]), pyramids[1], min_spread=0.5)
    assert not result.satisfied
    assert "closest" in result.reason
    assert len(result.attempts) == 2 * len(pyramids[0].images)  # every level, both settings
    assert 0.15 < result.spread < 0.5
    assert result.spread == max(a.spread for a in result.attempts)
    assert result.points_a[:, 0].max() < 0.31 * SIZE[0]


@pytest.fixture(scope="module")
def coarse(strip: SyntheticStrip, pyramids: list[FramePyramid]) -> dict[tuple[int, int], np.ndarray]:
    found = {}
    for i in range(len(strip.paths) - 1):
        result = register_coarse(pyramids[i], pyramids[i + 1])
        assert result.homography is not None
        found[i, i + 1] = result.homography
    return found


@pytest.fixture(scope="module")
def fine(strip: SyntheticStrip, coarse: dict[tuple[int, int], np.ndarray]) -> dict[tuple[int, int], PairTies]:
    frames = [open_windows(path) for path in strip.paths]
    return {(i, j): fine_tie_points(frames[i], frames[j], H, N_POINTS, frames=(i, j)) for (i, j), H in coarse.items()}


def test_fine_tie_points_are_within_a_third_of_a_px_of_the_truth(
    strip: SyntheticStrip, fine: dict[tuple[int, int], PairTies]
) -> None:
    for (i, j), ties in fine.items():
        assert 0.75 * N_POINTS <= ties.counts["blocks"] <= 1.25 * N_POINTS
        assert len(ties.points_a) >= 0.8 * ties.counts["blocks"], ties.counts
        assert _rms(ties, _truth(strip, i, j)) < 0.3
        assert np.array_equal(ties.points_a, np.rint(ties.points_a))  # pixel centres of a
        assert ties.score.min() >= 0.8
        # one point per block: they cover the overlap's length and both of its rows of blocks
        assert np.ptp(ties.points_a[:, 0]) > 0.9 * SIZE[0]


def test_fine_search_reads_only_small_windows(strip: SyntheticStrip, coarse: dict[tuple[int, int], np.ndarray]) -> None:
    class Counting:
        def __init__(self, path: Path) -> None:
            self.frame, self.pixels, self.shape = open_windows(path), 0, open_windows(path).shape

        def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
            window = self.frame[key]
            self.pixels += window.shape[0] * window.shape[1]
            return window

    a, b = Counting(strip.paths[0]), Counting(strip.paths[1])
    ties = fine_tie_points(a, b, coarse[0, 1], 100)
    assert len(ties.points_a) > 60
    assert a.pixels <= 100 * 1.3 * 48**2 and b.pixels <= 100 * 1.3 * 31**2  # probes and search windows
    assert a.pixels + b.pixels < 0.15 * SIZE[0] * SIZE[1]  # 8 % of the frame per 100 points


def test_the_filter_drops_planted_outliers(strip: SyntheticStrip, fine: dict[tuple[int, int], PairTies]) -> None:
    ties = fine[0, 1]
    rng = np.random.default_rng(7)
    planted = rng.choice(len(ties.points_a), 40, replace=False)
    points_b = ties.points_b.copy()
    angle = rng.uniform(0, 2 * np.pi, 40)
    points_b[planted] += rng.uniform(3, 25, 40)[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    result = filter_ties(ties.points_a, points_b, epipolar_px=1.0, residual_px=1.0)
    clean = np.setdiff1d(np.arange(len(points_b)), planted)
    # F alone cannot see a displacement along the epipolar line; the homography check drops the rest
    assert (~result.epipolar[planted]).mean() >= 0.75
    assert not result.keep[planted].any()
    assert result.keep[clean].mean() >= 0.98
    assert result.H is not None
    assert _corner_error(result.H, _truth(strip, 0, 1), overlap_polygon(_truth(strip, 0, 1), SIZE, SIZE)) < 0.5


def test_too_few_points_are_an_empty_result() -> None:
    result = filter_ties(np.zeros((5, 2)), np.zeros((5, 2)))
    assert result.F is None and not result.keep.any()
    frame = np.full((400, 8000), 128, np.uint8)  # no texture: no corner passes the threshold
    empty = fine_tie_points(frame, frame, np.eye(3), 50)
    assert len(empty.points_a) == 0 and empty.counts["corners"] == 0


def test_tracks_join_observations_of_three_frames(
    strip: SyntheticStrip, coarse: dict[tuple[int, int], np.ndarray], fine: dict[tuple[int, int], PairTies]
) -> None:
    frames = [open_windows(path) for path in strip.paths]
    pairs = list(fine.values())
    carried = 0
    for i in range(len(frames) - 2):
        H = coarse[i + 1, i + 2] @ coarse[i, i + 1]
        ties = carry_ties(frames[i], frames[i + 2], fine[i, i + 1].points_a, H, frames=(i, i + 2))
        assert len(ties.points_a) > 50 and _rms(ties, _truth(strip, i, i + 2)) < 0.3
        carried += len(ties.points_a)
        pairs.append(ties)
    tracks = build_tracks(pairs)
    lengths = tracks.lengths()
    assert tracks.conflicts == 0
    assert (lengths == 3).sum() >= 0.95 * carried  # every carried point ties i, i + 1 and i + 2
    for t in np.flatnonzero(lengths == 3):
        rows = np.flatnonzero(tracks.track == t)
        f, xy = tracks.frame[rows], tracks.xy[rows]
        assert f[2] - f[0] == 2 and f[1] - f[0] == 1
        for k in (1, 2):
            moved = apply_homography(_truth(strip, int(f[0]), int(f[k])), xy[:1])
            assert np.linalg.norm(moved - xy[k : k + 1]) < 1.0


def _pair(frames: tuple[int, int], a: list[tuple[float, float]], b: list[tuple[float, float]]) -> PairTies:
    return PairTies(frames, np.array(a, float), np.array(b, float), np.ones(len(a), np.float32), {})


def test_build_tracks_unites_chains_and_drops_conflicts() -> None:
    pairs = [
        _pair((0, 1), [(10, 10), (50, 50)], [(110, 10), (150, 50)]),
        _pair((1, 2), [(110.1, 10), (300, 300)], [(210, 10), (400, 300)]),  # 0.1 px: the same point of 1
        _pair((0, 2), [(50, 50)], [(900, 900)]),  # ties (50, 50) of 0 to a second, far point of 2
        _pair((1, 2), [(150, 50)], [(250, 50)]),
    ]
    tracks = build_tracks(pairs, merge_px=0.25)
    assert tracks.conflicts == 1  # the (50, 50) track sees frame 2 at (250, 50) and at (900, 900)
    lengths = sorted(tracks.lengths().tolist())
    assert lengths == [2, 3]
    three = np.flatnonzero(tracks.track == np.argmax(tracks.lengths()))
    assert tracks.frame[three].tolist() == [0, 1, 2]
    assert np.allclose(tracks.xy[three], [(10, 10), (110.05, 10), (210, 10)])
    assert build_tracks([]).n_tracks == 0


@pytest.mark.gpu
@pytest.mark.skipif(not cuda_available(), reason="needs CuPy and a CUDA device")
def test_fine_tie_points_on_the_gpu_match_the_cpu(
    strip: SyntheticStrip, coarse: dict[tuple[int, int], np.ndarray], fine: dict[tuple[int, int], PairTies]
) -> None:
    frames = [open_windows(path) for path in strip.paths[:2]]
    gpu = fine_tie_points(frames[0], frames[1], coarse[0, 1], N_POINTS, frames=(0, 1), device="cuda")
    cpu = fine[0, 1]
    assert gpu.counts == cpu.counts
    assert np.array_equal(gpu.points_a, cpu.points_a)
    assert np.abs(gpu.points_b - cpu.points_b).max() < 1e-3


def test_pairs_too_far_apart_on_the_strip_are_predicted_from_one_pair() -> None:
    """A straight strip of 1000 x 100 px frames, 50 m of GPS a frame and 45 px (55 % overlap) between neighbours,
    turned 0.3 degrees in the frames: gap 2 overlaps (90 px < 100), gap 3 does not (135 px) and is distant past the
    margin (1.25 x 100 px); a crossing line's pairs are not placed; a degenerate reference places none. Two apart,
    they meet over 10 px."""
    n, size = 10, (1000, 100)
    positions = np.array([[0.0, 50.0 * k] for k in range(n)] + [[400.0, 0.0], [800.0, 0.0]])  # 10, 11: across it
    angle = np.radians(0.3)
    step = 45 * np.array([np.sin(angle), -np.cos(angle)])  # where a's centre lies in b, from b's centre
    H = np.array([[1.0, 0.0, step[0]], [0.0, 1.0, step[1]], [0.0, 0.0, 1.0]])
    pairs = [(i, j) for i in range(n) for j in range(i + 1, min(n, i + 7))] + [(0, 10), (5, 11), (10, 11)]
    placed = along_strip(pairs, positions, size, (4, 5), H)
    assert set(placed) == {(i, j) for i, j in pairs if j < n}  # the crossing line's pairs are not placed
    assert placed[(4, 6)][0] == pytest.approx(90.0) and placed[(4, 6)][2] == pytest.approx(10.0, abs=0.01)
    assert distant_pairs(placed) == [(i, j) for i, j in pairs if j < n and j - i >= 3]
    assert distant_pairs(placed, margin=1.4) == [(i, j) for i, j in pairs if j < n and j - i >= 4]
    assert along_strip(pairs, positions, size, (4, 5), np.eye(3)) == {}  # no shift: no scale
    assert along_strip(pairs, np.zeros_like(positions), size, (4, 5), H) == {}  # no GPS distance


def test_coarse_levels_start_where_the_predicted_overlap_can_hold_a_match() -> None:
    """Frames two apart at 55 % overlap meet over 180 native px: 5.6 px at level 5 and 11 at level 4 cannot hold a
    15 px NCC window and its search in both frames (18 px), 22 at level 3 can; neighbours (990 px) start at the
    coarsest; an overlap too thin for any level gets the finest."""
    assert feasible_levels([5, 4, 3], 180.0) == [3]
    assert feasible_levels([3, 4, 5], 990.0) == [5, 4, 3]
    assert feasible_levels([5, 4, 3], 10.0) == [3]
    assert feasible_levels([5, 4, 3], 180.0, CoarseOptions(half_window=3)) == [4, 3]  # 10 level px needed
