"""SIFT scale space: blur levels, octave geometry, and a blob found at its own scale."""

from __future__ import annotations

import inspect
import math

import cv2
import numpy as np
import pytest

from gpu_kernels.filters import gaussian_blur, gaussian_pyramid
from gpu_kernels.scale_space import level_sigmas, scale_space
from tests.gpu.conftest import host
from tests.gpu.kernel_cases import textured_image


def test_levels_have_the_blur_they_claim(xp) -> None:
    img = textured_image(96, 128, seed=2).astype(np.float32) / 255
    octave = next(scale_space(xp.asarray(img), first_octave=0, levels=3, sigma0=1.6, assumed_blur=0.0))
    sigmas = level_sigmas(3, 1.6)
    g = host(octave.gaussians)
    for s in (1, 3, 5):  # incremental blurs compose to the total, up to kernel truncation
        direct = host(gaussian_blur(xp.asarray(img), sigmas[s]))
        assert np.abs(g[s] - direct)[12:-12, 12:-12].max() < 2e-3
    assert np.allclose(host(octave.dog), g[1:] - g[:-1])


@pytest.mark.parametrize(("first", "shape0"), [(-1, (192, 256)), (0, (96, 128)), (1, (48, 64))])
def test_octave_geometry(xp, first: int, shape0: tuple[int, int]) -> None:
    octaves = list(scale_space(xp.asarray(textured_image(96, 128)), first_octave=first, levels=4))
    assert octaves[0].index == first and octaves[0].gaussians.shape == (7, *shape0)
    assert octaves[0].dog.shape == (6, *shape0)
    for a, b in zip(octaves, octaves[1:], strict=False):
        assert b.index == a.index + 1 and b.gaussians.shape[1] == math.ceil(a.gaussians.shape[1] / 2)
    assert min(octaves[-1].gaussians.shape[1:]) >= 8
    assert inspect.isgenerator(scale_space(xp.asarray(textured_image(32, 32))))  # one octave at a time


@pytest.mark.parametrize("blob_sigma", [3.0, 6.0])
def test_a_blob_is_strongest_at_its_own_scale(xp, blob_sigma: float) -> None:
    """For a Gaussian blob of std b, the scale-normalised Laplacian peaks at sigma = b (Lindeberg)."""
    size = 160
    yy, xx = np.mgrid[0:size, 0:size]
    blob = np.exp(-((xx - 80) ** 2 + (yy - 80) ** 2) / (2 * blob_sigma**2)).astype(np.float32)
    best, best_sigma = 0.0, 0.0
    for octave in scale_space(xp.asarray(blob), first_octave=-1, levels=3, sigma0=1.6, assumed_blur=0.0):
        c = int(round(80 / octave.spacing + (0.5 / octave.spacing - 0.5)))
        dog = host(octave.dog)[:, c, c]
        sigmas = level_sigmas(3, 1.6)
        for s, value in enumerate(dog):
            sigma = octave.spacing * math.sqrt(sigmas[s] * sigmas[s + 1])  # DoG(s) ~ scale between s and s+1
            if abs(value) > best:
                best, best_sigma = abs(value), sigma
    assert abs(math.log2(best_sigma / blob_sigma)) <= 1 / 3 + 0.05  # within one level (1/3 octave)


def test_gaussian_pyramid_halves_and_blurs(xp) -> None:
    img = textured_image(64, 96).astype(np.float32)
    levels = gaussian_pyramid(xp.asarray(img), 4)
    assert [lv.shape for lv in levels] == [(64, 96), (32, 48), (16, 24), (8, 12)]
    reference = cv2.GaussianBlur(img, (0, 0), 1.0, borderType=cv2.BORDER_REFLECT_101)[::2, ::2]
    # OpenCV's kernel is truncated at a slightly different radius: 0.03 grey levels apart here.
    assert np.abs(host(levels[1]) - reference).max() < 0.1


def test_bad_parameters() -> None:
    with pytest.raises(ValueError):
        next(scale_space(np.zeros((32, 32), np.float32), first_octave=2))
