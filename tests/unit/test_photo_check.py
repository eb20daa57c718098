"""The upload-time photo check (``workers.photo_check``, through ``inspect_image``): figures of a reduced copy,
and a flight's photos read against each other, on synthetic flights with planted faults and the real Brighton
strip (none flagged)."""

from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from PIL import Image

from tests.conftest import shared_data
from tests.scenes import make_flight
from workers.image_meta import BlockMeans, inspect_image
from workers.photo_check import HashIndex, PhotoFacts, hamming, judge, laplacian_variance, preview_jpeg


def _facts(paths: list[Path], gps: bool = True) -> list[PhotoFacts]:
    out = []
    for key, path in enumerate(paths):
        meta = inspect_image(path)
        out.append(
            PhotoFacts(key, path.name, meta["width"], meta["height"], gps and bool(meta["gps"]), meta["quality"])
        )
    return out


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    return make_flight(tmp_path_factory.mktemp("check") / "frames", n_frames=6, frame_size=(480, 360), seed=3)


def test_a_sound_flight_has_no_issues(flight) -> None:  # type: ignore[no-untyped-def]
    assert all(found == [] for found in judge(_facts(flight.paths)).values())


def test_a_blurred_a_dark_and_a_bright_photo_are_flagged_with_why(flight, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    paths = []
    for i, src in enumerate(flight.paths):
        img = cv2.imread(str(src))
        if i == 1:
            img = cv2.GaussianBlur(img, (0, 0), 3.0)
        elif i == 3:
            img = (img * 0.12).astype(np.uint8)  # under-exposed by about 3 stops
        elif i == 4:
            img = cv2.convertScaleAbs(img, alpha=2.5, beta=90)
        cv2.imwrite(str(tmp_path / src.name), img, [cv2.IMWRITE_JPEG_QUALITY, 92])
        paths.append(tmp_path / src.name)
    found = judge(_facts(paths))
    codes = {key: [i["code"] for i in issues] for key, issues in found.items()}
    assert codes == {0: [], 1: ["blurred"], 2: [], 3: ["under_exposed"], 4: ["over_exposed"], 5: []}
    assert "under a third of the flight's median" in found[1][0]["message"]
    assert "nearly black" in found[3][0]["message"] and "clipped white" in found[4][0]["message"]


def test_a_resized_copy_is_a_duplicate_and_another_size(flight, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    copy = tmp_path / "copy.jpg"
    Image.open(flight.paths[2]).resize((240, 180), Image.Resampling.LANCZOS).save(copy, quality=70)
    facts = _facts([*flight.paths, copy])
    found = judge(facts)[len(flight.paths)]
    assert [i["code"] for i in found] == ["duplicate", "no_gps", "size_mismatch"]  # the copy lost its EXIF too
    assert flight.paths[2].name in found[0]["message"] and "240 x 180 px, while 6 of 7" in found[2]["message"]
    assert hamming(facts[2].quality["phash"], facts[-1].quality["phash"]) <= 2  # type: ignore[index]
    distinct = [hamming(a.quality["phash"], b.quality["phash"]) for a in facts[:6] for b in facts[:6] if a.key < b.key]  # type: ignore[index]
    assert min(distinct) >= 16  # overlapping frames of one flight are far apart


def test_no_gps_is_flagged_only_where_other_photos_have_it(flight) -> None:  # type: ignore[no-untyped-def]
    facts = _facts(flight.paths)
    facts[0] = PhotoFacts(0, "a.jpg", facts[0].width, facts[0].height, False, facts[0].quality)
    assert [i["code"] for i in judge(facts)[0]] == ["no_gps"]
    none = [PhotoFacts(f.key, f.name, f.width, f.height, False, f.quality) for f in facts]
    assert all(found == [] for found in judge(none).values())  # a flight without GPS: nothing to single out


def test_photos_from_before_the_check_say_so(flight) -> None:  # type: ignore[no-untyped-def]
    facts = _facts(flight.paths[:2]) + [PhotoFacts(9, "old.jpg", 480, 360, True, None)]
    assert [i["code"] for i in judge(facts)[9]] == ["not_checked"]


@pytest.mark.realdata
def test_the_brighton_strip_is_clean() -> None:
    paths = sorted(shared_data("drone_brighton_strip1").glob("*.JPG"))
    assert all(found == [] for found in judge(_facts(paths)).values())


def test_laplacian_variance_falls_with_blur() -> None:
    rng = np.random.default_rng(0)
    sharp = (rng.random((200, 200)) > 0.5).astype(np.uint8) * 255
    assert laplacian_variance(sharp) > 10 * laplacian_variance(cv2.GaussianBlur(sharp, (0, 0), 2.0))
    assert laplacian_variance(np.full((50, 50), 128, np.uint8)) == 0.0


def test_tiff_blocks_average_into_the_reduced_copy(tmp_path: Path) -> None:
    """Blocks of any size and offset sum into the right cells: the same means as averaging the whole image."""
    rng = np.random.default_rng(1)
    image = rng.integers(0, 4096, (3, 1100, 1300)).astype(np.uint16)  # 12-bit samples in 16-bit words
    cells = BlockMeans((367, 434), 3)
    for r in range(0, 1100, 70):
        for c in range(0, 1300, 130):
            cells.add(image[:, r : r + 70, c : c + 130], r, c)
    luma = 0.299 * image[0] + 0.587 * image[1] + 0.114 * image[2]
    padded = np.full((367 * 3, 434 * 3), np.nan)
    padded[:1100, :1300] = luma
    expected = np.nanmean(padded.reshape(367, 3, 434, 3), axis=(1, 3)) * 255 / 4095
    assert np.abs(cells.gray().astype(float) - expected).max() <= 1.0
    path = tmp_path / "tiled.tif"
    profile = {"driver": "GTiff", "width": 1300, "height": 1100, "count": 3, "dtype": "uint16", "tiled": True}
    with rasterio.open(path, "w", **profile, blockxsize=256, blockysize=256) as dst:
        dst.write(image)
    quality = inspect_image(path)["quality"]
    assert quality["analysed_px"] == [434, 367] and abs(quality["mean_brightness"] - expected.mean()) < 1.0


def test_previews_fit_the_size_asked(flight, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    with Image.open(io.BytesIO(preview_jpeg(flight.paths[0], 128))) as img:
        assert img.format == "JPEG" and max(img.size) == 128
    path = tmp_path / "frame.tif"
    with rasterio.open(path, "w", driver="GTiff", width=900, height=300, count=1, dtype="uint16") as dst:
        dst.write(np.full((1, 300, 900), 1000, np.uint16))
    with Image.open(io.BytesIO(preview_jpeg(path, 256))) as img:
        assert img.size == (256, 85) and abs(np.asarray(img).mean() - 1000 * 255 / 1023) < 2
    Image.fromarray(np.zeros((40, 60, 3), np.uint8)).save(tmp_path / "small.png")
    with Image.open(io.BytesIO(preview_jpeg(tmp_path / "small.png", 256))) as img:
        assert img.size == (60, 40)  # never enlarged


def test_the_hash_index_finds_what_comparing_every_pair_finds() -> None:
    """Near copies (0-8 bits flipped) among random hashes: the banded index names the same first twin as a
    comparison with every earlier hash."""
    rng = np.random.default_rng(3)
    index, seen = HashIndex(), []
    for k in range(2000):
        if seen and k % 3 == 0:
            flipped = sum(1 << int(b) for b in rng.choice(64, size=int(rng.integers(0, 9)), replace=False))
            value = int(seen[int(rng.integers(len(seen)))][0], 16) ^ flipped
        else:
            value = int(rng.integers(0, 2**63)) * 2 + int(rng.integers(0, 2))
        phash = f"{value:016x}"
        brute = next((name for other, name in seen if hamming(other, phash) <= 5), None)
        assert index.near(phash) == brute, k
        index.add(phash, f"p{k}")
        seen.append((phash, f"p{k}"))
