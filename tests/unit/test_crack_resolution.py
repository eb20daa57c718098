"""A crack survey's cracks do not depend on the output raster it is asked for: detection and measurement
run on a raster set by the photos' own sampling on the specimen (``rectify_specimen``), and ``mm_per_px``
only sets the rectified COGs and overlays (default: the photos' sampling)."""

from __future__ import annotations

from pathlib import Path

import pytest
import rasterio

from tests.crack_scenes import CrackSurveyScene, make_crack_survey, run_survey
from workers.algorithms.cracks import smallest_detectable_width

RATIOS = (0.5, 1.0, 2.0)  # output mm_per_px over the photos' sampling


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> CrackSurveyScene:
    return make_crack_survey(tmp_path_factory.mktemp("resolution"), [(45.0, 10.0)], seed=5, frame_size=(640, 480))


def test_counts_and_lengths_do_not_depend_on_mm_per_px(scene: CrackSurveyScene, tmp_path: Path) -> None:
    options = scene.options(0.0)
    del options["mm_per_px"]  # the default: the photos' own sampling
    default = run_survey(scene, tmp_path / "default", options)
    native = min(s["photo_mm_per_px"] for s in default["stages"])
    assert abs(default["mm_per_px"] / native - 1) < 0.05, (default["mm_per_px"], native)
    assert default["detection_mm_per_px"] <= native  # detection at or finer than the photos' sampling
    for stage in default["stages"]:  # at the contrast the survey measured its cracks at (none: 30 %)
        smallest = smallest_detectable_width(stage["photo_mm_per_px"], default["detectability_contrast"])
        assert stage["smallest_detectable_width_mm"] == pytest.approx(smallest)
        low, high = stage["smallest_detectable_width_range_mm"]
        assert low <= stage["smallest_detectable_width_mm"] <= high
    truth = [len(s) for s in scene.stages]
    assert [s["count"] for s in default["stages"]] == truth
    for ratio in RATIOS:
        mm = round(ratio * native, 4)
        report = run_survey(scene, tmp_path / f"x{ratio}", scene.options(mm))
        assert report["mm_per_px"] == mm and report["detection_mm_per_px"] == default["detection_mm_per_px"]
        for stage, reference in zip(report["stages"], default["stages"], strict=True):
            assert stage["count"] == reference["count"], (ratio, stage["count"], reference["count"])
            assert abs(stage["total_length_mm"] / reference["total_length_mm"] - 1) < 0.03
        with rasterio.open(tmp_path / f"x{ratio}" / report["stages"][0]["rectified"]) as cog:
            assert cog.res == pytest.approx((mm, mm))
            assert cog.width == int(scene.width_mm / mm + 1e-9) + 1
