"""Maps computed tile by tile equal the map of the whole image where the margin covers the function's reach."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from workers.algorithms.cracks import map_in_tiles


def blur(image: np.ndarray) -> np.ndarray:
    return cv2.GaussianBlur(image, (0, 0), 5.0, borderType=cv2.BORDER_REFLECT)


def pyramid(image: np.ndarray) -> np.ndarray:
    """Halve by 2 x 2 averaging and come back: the answer depends on where the 2 x 2 grid starts."""
    h, w = image.shape
    half = cv2.resize(image, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    return cv2.resize(half, (w, h), interpolation=cv2.INTER_NEAREST)


def test_tiles_with_enough_margin_match_the_whole_image() -> None:
    image = np.random.default_rng(0).random((530, 700)).astype(np.float32)
    tiled = map_in_tiles(image, blur, tile_px=128, margin_px=40)
    assert np.max(np.abs(tiled - blur(image))) < 1e-5
    too_little = map_in_tiles(image, blur, tile_px=128, margin_px=4)
    assert np.max(np.abs(too_little - blur(image))) > 1e-3  # the margin is what makes it exact


def test_windows_keep_the_pyramid_grid() -> None:
    image = np.random.default_rng(1).random((512, 512)).astype(np.float32)
    assert np.array_equal(map_in_tiles(image, pyramid, tile_px=100, margin_px=20, align=8), pyramid(image))


def test_small_images_go_whole_and_bad_functions_are_refused() -> None:
    image = np.zeros((64, 64), np.float32)
    calls = []
    map_in_tiles(image, lambda w: calls.append(w.shape) or w, tile_px=64, margin_px=0)
    assert calls == [(64, 64)]
    with pytest.raises(ValueError, match="answered shape"):
        map_in_tiles(np.zeros((300, 300), np.float32), lambda w: w[1:], tile_px=64, margin_px=8)
