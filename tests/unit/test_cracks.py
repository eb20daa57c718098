"""Crack detection: synthetic coatings with drawn cracks of known position and width, and CrackForest
images the model never saw (041-060) scored with a 2-pixel tolerance."""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
import pytest
from scipy import ndimage as ndi

from tests.conftest import shared_data
from tests.unit.test_crack_geometry import band_mask
from workers.algorithms.cracks import (
    FEATURE_VERSION,
    NET_LAYERS,
    CrackModel,
    CrackNet,
    ToleranceCounts,
    avg_pool2,
    conv2d,
    crack_probability,
    darkening,
    detect_cracks,
    hysteresis_threshold,
    load_crack_model,
    pixel_features,
    remove_short_components,
    to_gray,
    tolerance_counts,
    upsample2,
)

H, W = 320, 480
EIGHT = np.ones((3, 3))


def textured_surface(rng: np.random.Generator, shading: float = 0.35) -> np.ndarray:
    """(H, W) float64 grey surface: grain at three scales under a linear light falloff in a random direction
    (light at a low angle) and a broad hot spot."""
    grain = sum(
        a * np.sqrt(s) * cv2.GaussianBlur(rng.standard_normal((H, W)).astype(np.float32), (0, 0), s)
        for s, a in ((1, 15.0), (3, 12.0), (10, 15.0))
    )
    yy, xx = np.mgrid[0:H, 0:W]
    a = rng.uniform(0, 2 * np.pi)
    ramp = 1 + shading * ((xx - W / 2) * np.cos(a) + (yy - H / 2) * np.sin(a)) / (W / 2)
    spot = 0.2 * np.exp(-((xx - rng.uniform(0, W)) ** 2 + (yy - rng.uniform(0, H)) ** 2) / (2 * 120.0**2))
    return (140 + grain) * (ramp + spot)


def random_crack(rng: np.random.Generator, length: float, step: float = 4.0) -> np.ndarray:
    """(N, 2) (x, y) centreline of a gently wandering crack of about ``length`` px."""
    angle = rng.uniform(0, 2 * np.pi)
    points = [np.array([rng.uniform(60, W - 60), rng.uniform(60, H - 60)])]
    for _ in range(int(length / step)):
        angle += rng.normal(0, 0.12)
        points.append(points[-1] + step * np.array([np.cos(angle), np.sin(angle)]))
    return np.array(points)


def cracked_scene(
    seed: int, widths: tuple[int, ...] = (1, 2, 3, 4, 5, 6)
) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """A shaded textured coating with one crack per width, 80-200 px long, at least 15 px apart.

    Returns
    -------
    image : (H, W) uint8.
    lines : per crack, (N, 2) float64 (x, y) centreline.
    bands : per crack, (H, W) bool pixels of the crack.
    """
    rng = np.random.default_rng(seed)
    lines: list[np.ndarray] = []
    bands: list[np.ndarray] = []
    taken = np.zeros((H, W), bool)
    for width in widths:
        while True:
            line = random_crack(rng, rng.uniform(80, 200))
            if line.min() < 8 or line[:, 0].max() > W - 8 or line[:, 1].max() > H - 8:
                continue
            band = band_mask(line, width, (H, W))
            if not (band & taken).any():
                break
        lines.append(line)
        bands.append(band)
        taken |= cv2.dilate(band.astype(np.uint8), np.ones((31, 31), np.uint8)) > 0
    cracks = cv2.GaussianBlur(np.any(bands, axis=0).astype(np.float32), (0, 0), 0.7)
    image = textured_surface(rng) * (1 - 0.55 * cracks) + rng.normal(0, 4, (H, W))
    return np.clip(image, 0, 255).astype(np.uint8), lines, bands


def dense(line: np.ndarray, step: float = 1.0) -> np.ndarray:
    """(M, 2) points every ``step`` px along a polyline (N, 2)."""
    along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))]
    s = np.arange(0.0, along[-1], step)
    return np.column_stack([np.interp(s, along, line[:, 0]), np.interp(s, along, line[:, 1])])


@lru_cache(maxsize=4)
def detected_scene(seed: int) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray], np.ndarray]:
    """``cracked_scene(seed)`` and its detected mask, computed once for the tests that share it."""
    image, lines, bands = cracked_scene(seed)
    return image, lines, bands, detect_cracks(image)


def within(mask: np.ndarray, distance_px: float) -> np.ndarray:
    """(H, W) bool: pixels within ``distance_px`` of ``mask``."""
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE) <= distance_px


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_synthetic_cracks_are_found_where_drawn(seed: int) -> None:
    _, lines, bands, found = detected_scene(seed)
    labels, n = ndi.label(found, EIGHT)
    assert n == len(bands)  # no crack lost or split, nothing from texture or shading
    truth = np.any(bands, axis=0)
    assert (found & within(truth, 2)).sum() >= 0.97 * found.sum()  # detected pixels lie within 2 px of a crack
    near_found = within(found, 2)
    for line, band in zip(lines, bands, strict=True):
        assert len(set(np.unique(labels[band & found])) - {0}) == 1  # each crack is one component
        centre = np.rint(dense(line)).astype(int)
        assert near_found[centre[:, 1], centre[:, 0]].mean() >= 0.85  # found within 2 px along most of it


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_measured_length_of_detected_cracks(seed: int) -> None:
    """End to end: detection then measurement. The detected cracks lose a little at their tips (total
    0.94-0.99 of the drawn length over seeds 1-10). Widths are not asserted: the CrackForest-trained
    detector draws hairline cracks ~4 px wide, as that data set's ground truth does."""
    from workers.algorithms.cracks import measure_cracks

    _, lines, _, found = detected_scene(seed)
    cracks = measure_cracks(found, 0.05)
    true = sum(0.05 * float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum()) for line in lines)
    assert len(cracks) == len(lines)
    assert 0.90 <= sum(c.length_mm for c in cracks) / true <= 1.02


def test_shading_and_texture_alone_give_no_cracks() -> None:
    rng = np.random.default_rng(7)
    for shading in (0.2, 0.5):
        image = np.clip(textured_surface(rng, shading) + rng.normal(0, 4, (H, W)), 0, 255).astype(np.uint8)
        assert detect_cracks(image).sum() < 0.001 * H * W


def test_probability_map_shape_and_inputs() -> None:
    image, _, bands = cracked_scene(4, widths=(3,))
    grey = crack_probability(image)
    colour = crack_probability(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    assert grey.shape == (H, W) and grey.dtype == np.float32
    assert grey.min() >= 0 and grey.max() <= 1
    np.testing.assert_allclose(grey, colour, atol=1e-5)
    assert grey[bands[0]].mean() > 0.5 > grey[~within(bands[0], 4)].mean()
    assert pixel_features(image).shape == (H, W, 44)
    odd = crack_probability(image[:101, :77])  # sides that are not multiples of 4 are padded, then cropped
    assert odd.shape == (101, 77) and np.isfinite(odd).all()
    with pytest.raises(ValueError):
        crack_probability(np.zeros((H, W, 4), np.uint8))


def test_hysteresis_and_short_components() -> None:
    score = np.zeros((40, 120), np.float32)
    score[5, 10:100] = 0.6  # long, weak, touches a strong pixel
    score[5, 50] = 0.95
    score[20, 10:100] = 0.6  # long, weak only
    score[30, 10:30] = 0.95  # strong but 20 px long
    mask = hysteresis_threshold(score, 0.5, 0.9)
    assert mask[5].sum() == 90 and mask[20].sum() == 0 and mask[30].sum() == 20
    kept = remove_short_components(mask, 40)
    assert kept[5].sum() == 90 and kept[30].sum() == 0
    with pytest.raises(ValueError):
        hysteresis_threshold(score, 0.9, 0.5)


def test_tolerance_counts() -> None:
    truth = np.zeros((50, 100), bool)
    truth[25, 10:90] = True
    near, far = np.roll(truth, 2, axis=0), np.roll(truth, 3, axis=0)
    assert tolerance_counts(near, truth).f1 == 1.0
    assert tolerance_counts(far, truth).f1 == 0.0
    half = truth.copy()
    half[:, 50:] = False
    counts = tolerance_counts(half, truth, tolerance_px=0)
    assert counts.precision == 1.0 and abs(counts.recall - 0.5) < 0.02
    assert (counts + counts).f1 == pytest.approx(counts.f1)


def test_model_round_trip_and_version_check() -> None:
    model = load_crack_model()
    arrays = model.to_arrays()
    again = CrackModel.from_arrays(arrays)
    assert again.low == model.low and again.min_length_px == model.min_length_px
    np.testing.assert_array_equal(again.net.layers["up_full"][0], model.net.layers["up_full"][0])
    np.testing.assert_array_equal(again.stage2.w1, model.stage2.w1)
    with pytest.raises(ValueError, match="feature version"):
        CrackModel.from_arrays({**arrays, "feature_version": np.array(FEATURE_VERSION + 1)})
    with pytest.raises(ValueError):
        model.net.predict(np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ValueError):
        model.stage1.predict(np.zeros((4, 4, 3), np.float32))
    size = sum(a.nbytes for a in arrays.values())
    assert size < 200_000  # small enough to commit


def dilated(kernel: np.ndarray, dilation: int) -> np.ndarray:
    """A (k, k) kernel with ``dilation - 1`` zeros between its taps."""
    k = kernel.shape[0]
    out = np.zeros((dilation * (k - 1) + 1,) * 2, kernel.dtype)
    out[::dilation, ::dilation] = kernel
    return out


@pytest.mark.parametrize(("k", "dilation"), [(1, 1), (3, 1), (3, 2), (3, 4)])
def test_conv2d_matches_a_per_channel_correlation(k: int, dilation: int) -> None:
    rng = np.random.default_rng(k + dilation)
    x = rng.standard_normal((13, 17, 3)).astype(np.float32)
    weight = rng.standard_normal((k, k, 3, 2)).astype(np.float32)
    bias = np.array([0.5, -1.0], np.float32)
    expected = np.stack(
        [
            bias[o]
            + sum(
                ndi.correlate(x[..., i].astype(np.float64), dilated(weight[:, :, i, o], dilation), mode="constant")
                for i in range(3)
            )
            for o in range(2)
        ],
        axis=-1,
    )
    np.testing.assert_allclose(conv2d(x, weight, bias, dilation), expected, atol=1e-4)
    with pytest.raises(ValueError):
        conv2d(x[..., :2], weight, bias)


def test_pooling_and_upsampling_follow_torch_conventions() -> None:
    ramp = np.arange(4, dtype=np.float32)[:, None, None] * np.ones((4, 2, 1), np.float32)
    # torch.nn.functional.interpolate(scale_factor=2, mode="bilinear", align_corners=False) of 0, 1, 2, 3
    np.testing.assert_allclose(upsample2(ramp)[:, 0, 0], [0, 0.25, 0.75, 1.25, 1.75, 2.25, 2.75, 3])
    assert upsample2(ramp).shape == (8, 4, 1)
    np.testing.assert_allclose(upsample2(ramp)[:, 1, 0], upsample2(ramp)[:, 0, 0])
    np.testing.assert_allclose(avg_pool2(ramp)[:, 0, 0], [0.5, 2.5])


def random_net(rng: np.random.Generator, n_features: int = 5, widths: tuple[int, int, int] = (4, 6, 3)) -> CrackNet:
    """A :class:`CrackNet` of random weights and the layer shapes that the training script builds."""
    a, b, c = widths
    shapes = {
        "enc0": (n_features, a),
        "enc1": (a, a),
        "half0": (a, b),
        "half1": (b, b),
        "quarter0": (b, b),
        "quarter1": (b, b),
        "quarter2": (b, b),
        "up_half": (2 * b, b),
        "up_full": (a + b, c),
        "head": (c, 1),
    }
    layers = {
        name: (
            rng.normal(0, 0.5, (k, k, *shapes[name])).astype(np.float32),
            rng.normal(0, 0.1, shapes[name][1]).astype(np.float32),
        )
        for name, k, _ in NET_LAYERS
    }
    return CrackNet(
        rng.normal(0, 1, n_features).astype(np.float32), rng.uniform(0.5, 2, n_features).astype(np.float32), layers
    )


def test_network_forward_pass_is_translation_equivariant_and_local() -> None:
    """A crack seen at another place gives the same logits there (away from the borders), and a far change
    leaves a pixel's logit alone: the NumPy convolutions, pooling and upsampling are wired consistently."""
    rng = np.random.default_rng(5)
    net = random_net(rng)
    x = rng.standard_normal((192, 200, 5)).astype(np.float32)
    z = net.logits(x)
    assert z.shape == (192, 200) and np.isfinite(z).all()
    shifted = net.logits(np.roll(x, (8, 12), axis=(0, 1)))  # a shift by whole quarter-resolution pixels
    np.testing.assert_allclose(shifted[88:112, 92:116], z[80:104, 80:104], atol=1e-4)
    far = x.copy()
    far[:, 100:] += 5.0  # the receptive field reaches ~45 px
    np.testing.assert_allclose(net.logits(far)[:, :48], z[:, :48], atol=1e-5)
    assert not np.allclose(net.logits(far)[:, 60:], z[:, 60:], atol=1e-3)


def test_network_matches_its_pytorch_twin(monkeypatch: pytest.MonkeyPatch) -> None:
    """The NumPy forward pass against the training script's PyTorch network (skips without PyTorch)."""
    torch = pytest.importorskip("torch")
    import importlib.util
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "scripts" / "train_crack_model.py"
    spec = importlib.util.spec_from_file_location("train_crack_model", path)
    assert spec is not None and spec.loader is not None
    train = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, train)  # dataclasses look their module up there
    spec.loader.exec_module(train)
    torch.manual_seed(0)
    twin = train.TorchCrackNet(7, (5, 6, 4)).eval()
    with torch.no_grad():
        twin.mean.normal_()
        twin.scale.uniform_(0.5, 2.0)
    x = np.random.default_rng(1).standard_normal((36, 44, 7)).astype(np.float32)
    with torch.no_grad():
        expected = twin(torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))[None])[0].numpy()
    np.testing.assert_allclose(twin.to_numpy().logits(x), expected, atol=1e-4)


# Measured with the committed model on all 20 held-out images: precision 0.830, recall 0.715, F1 0.768; on the
# 19 whose labels pass the audit below (all but 042): precision 0.873, recall 0.761, F1 0.813. Cross-validated on
# 001-040: 0.889. Asserted with margins of about 0.02 and 0.01.
HELD_OUT_F1 = 0.745
HELD_OUT_F1_AUDITED = 0.80
MIN_LABEL_DARKENING = 0.02  # a label must mark pixels at least 2% darker than the road around them


def label_darkening(image: np.ndarray, truth: np.ndarray) -> float:
    """Median of how much darker the labelled pixels are than the unlabelled ones around them (8 px)."""
    return float(np.median(darkening(to_gray(image), truth, background_px=8.0)[truth]))


def load_cfd(index: int) -> tuple[np.ndarray, np.ndarray]:
    data = shared_data("crack_cfd")
    image = cv2.imread(str(data / "image" / f"{index:03d}.jpg"), cv2.IMREAD_COLOR)
    truth = cv2.imread(str(data / "mask_png" / f"{index:03d}.png"), cv2.IMREAD_GRAYSCALE)
    assert image is not None and truth is not None, index
    return image, truth > 0


@pytest.mark.realdata
def test_crackforest_labels_mark_dark_lines_but_one() -> None:
    """A label audit that needs no detector: every CrackForest mask lies on pixels 4-19% darker than the road
    next to them, except 042's, which is no darker at all (its vertical crack is not in the photo)."""
    darkness = {index: label_darkening(*load_cfd(index)) for index in range(1, 61)}
    assert [i for i, d in darkness.items() if d < MIN_LABEL_DARKENING] == [42], darkness
    assert min(d for i, d in darkness.items() if i != 42) > 0.04


@pytest.mark.realdata
def test_crackforest_held_out_images() -> None:
    """Images 041-060, never used for training or tuning; pooled 2-px-tolerant precision/recall/F1, on all of
    them and on those whose labels pass the audit."""
    total = audited = ToleranceCounts(0, 0, 0, 0)
    for index in range(41, 61):
        image, truth = load_cfd(index)
        counts = tolerance_counts(detect_cracks(image), truth, tolerance_px=2.0)
        total = total + counts
        if label_darkening(image, truth) >= MIN_LABEL_DARKENING:
            audited = audited + counts
    assert total.f1 >= HELD_OUT_F1, (total.precision, total.recall, total.f1)
    assert audited.f1 >= HELD_OUT_F1_AUDITED, (audited.precision, audited.recall, audited.f1)
