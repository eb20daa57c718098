"""SIFT against OpenCV's on real frames warped by known homographies, and on a planted blob."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from gpu_kernels.bf_match import match_descriptors
from gpu_kernels.sift import sift
from tests.conftest import shared_data
from tests.gpu.conftest import host
from tests.gpu.kernel_cases import textured_image

WARP = np.array([[0.80, -0.36, 150.0], [0.36, 0.80, -60.0], [1.5e-4, -1.0e-4, 1.0]])  # ~24 deg, x0.88, tilt


def project(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    q = np.column_stack([xy, np.ones(len(xy))]) @ H.T
    return q[:, :2] / q[:, 2:]


def scores(xy1: np.ndarray, d1: np.ndarray, xy2: np.ndarray, d2: np.ndarray, shape: tuple[int, int]) -> tuple:
    """Repeatability (share of image-1 points landing inside image 2 that have a detection within 2 px)
    and matching precision (share of ratio-test matches within 3 px of the truth), with their counts."""
    h, w = shape
    p = project(WARP, xy1)
    inside = (p[:, 0] > 8) & (p[:, 0] < w - 8) & (p[:, 1] > 8) & (p[:, 1] < h - 8)
    dist, _ = cKDTree(xy2).query(p[inside])
    matches = match_descriptors(d1, d2, ratio=0.8, mutual=True)
    a, b = host(matches.index_a), host(matches.index_b)
    correct = np.linalg.norm(project(WARP, xy1[a]) - xy2[b], axis=1) < 3.0
    return (dist < 2.0).mean(), correct.mean(), int(correct.sum())


def frame(path) -> np.ndarray:
    grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    return cv2.resize(grey, (640, round(640 * grey.shape[0] / grey.shape[1])), interpolation=cv2.INTER_AREA)


@pytest.mark.realdata
@pytest.mark.parametrize("source", ["drone_brighton_strip1/DJI_0026.JPG", "stitching/budapest1.jpg"])
def test_repeatability_and_precision_reach_ninety_percent_of_opencv(xp, source: str) -> None:
    folder, name = source.split("/")
    img1 = frame(shared_data(folder) / name)
    img2 = cv2.warpPerspective(img1, WARP, (img1.shape[1], img1.shape[0]), flags=cv2.INTER_LINEAR)
    ours1, ours2 = sift(xp.asarray(img1)), sift(xp.asarray(img2))
    ours = scores(host(ours1.xy), ours1.descriptors, host(ours2.xy), ours2.descriptors, img1.shape)
    detector = cv2.SIFT_create()
    (k1, c1), (k2, c2) = detector.detectAndCompute(img1, None), detector.detectAndCompute(img2, None)
    xy1, xy2 = np.array([k.pt for k in k1]), np.array([k.pt for k in k2])
    theirs = scores(
        xy1,
        xp.asarray(c1 / np.linalg.norm(c1, axis=1, keepdims=True)),
        xy2,
        xp.asarray(c2 / np.linalg.norm(c2, axis=1, keepdims=True)),
        img1.shape,
    )
    assert ours[0] >= 0.9 * theirs[0], f"repeatability {ours[0]:.3f} vs OpenCV {theirs[0]:.3f}"
    assert ours[1] >= 0.9 * theirs[1], f"precision {ours[1]:.3f} vs OpenCV {theirs[1]:.3f}"
    assert ours[2] >= 0.9 * theirs[2], f"correct matches {ours[2]} vs OpenCV {theirs[2]}"


@pytest.mark.parametrize(("brightness", "sign"), [(1.0, -1), (-1.0, 1)])
def test_a_planted_blob_is_found_at_its_place_and_scale(xp, brightness: float, sign: int) -> None:
    yy, xx = np.mgrid[0:160, 0:160]
    blob = 0.5 + 0.4 * brightness * np.exp(-((xx - 70.3) ** 2 + (yy - 85.6) ** 2) / (2 * 5.0**2))
    found = sift(xp.asarray(blob.astype(np.float32)))
    xy, sigma, signs = host(found.xy), host(found.sigma), host(found.sign)
    k = int(np.argmin(np.linalg.norm(xy - [70.3, 85.6], axis=1)))
    assert np.linalg.norm(xy[k] - [70.3, 85.6]) < 0.5
    assert abs(np.log2(sigma[k] / 5.0)) < 0.35 and signs[k] == sign  # bright blob: DoG minimum


def test_descriptor_layouts_and_rotation(xp) -> None:
    img = textured_image(200, 200, seed=6)
    small = sift(xp.asarray(img), layout=(2, 8))
    assert host(small.descriptors).shape[1] == 32
    norms = np.linalg.norm(host(small.descriptors), axis=1)
    assert np.allclose(norms, 1.0, atol=1e-4)
    turned = np.ascontiguousarray(np.rot90(img))  # exact 90 degree rotation: the same points, turned
    a, b = sift(xp.asarray(img)), sift(xp.asarray(turned))
    matches = match_descriptors(a.descriptors, b.descriptors, ratio=0.8)
    ia, ib = host(matches.index_a), host(matches.index_b)
    xy_a, xy_b = host(a.xy)[ia], host(b.xy)[ib]
    expected = np.column_stack([xy_a[:, 1], 199 - xy_a[:, 0]])  # rot90: (x, y) -> (y, W - 1 - x)
    assert len(ia) > 50 and (np.linalg.norm(expected - xy_b, axis=1) < 1.0).mean() > 0.95


def test_tiled_detection_equals_untiled(xp) -> None:
    from gpu_kernels.sift import sift_tiled, tile_margin

    img = xp.asarray(textured_image(300, 520, seed=8))
    whole = sift(img, octaves=3)
    tiled = sift_tiled(img, tile=128, octaves=3)
    assert tile_margin(3) < 300 and len(whole.xy) > 300

    def rows(kp) -> np.ndarray:
        table = np.column_stack([host(kp.xy), host(kp.sigma), host(kp.angle), host(kp.descriptors)])
        return table[np.lexsort(table[:, :4].T[::-1])]

    assert np.array_equal(rows(whole), rows(tiled))
