"""Crack widths of rendered hairline plates (``tests/crack_scenes.py``: exact sub-pixel cover of each photo
pixel's footprint, 30 % contrast, 0.5 px PSF, grain, uneven light) at 30 and 60 degrees, cracks of 1-4 photo
pixels: every crack of 2 photo px and more is measured, not flagged, to within its stated uncertainty, and
0.05 mm on average. The width estimator was tuned on other seeds (7, 11, 13, 31), at 45 degrees."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.crack_scenes import CrackSurveyScene, make_crack_survey, rows_along, run_survey

WIDTHS_PX = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0)  # crack widths in photo pixels, in turn


@pytest.fixture(scope="module", params=[30.0, 60.0], ids=["30deg", "60deg"])
def plate(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> CrackSurveyScene:
    return make_crack_survey(
        tmp_path_factory.mktemp(f"widths{request.param:.0f}"),
        [(request.param, 15.0)],
        seed=23,
        frame_size=(800, 600),
        widths_px=WIDTHS_PX,
        contrast=0.3,
        blur_px=0.5,
    )


def test_widths_of_cracks_two_photo_pixels_wide_and_more(plate: CrackSurveyScene, tmp_path: Path) -> None:
    report = run_survey(plate, tmp_path, plate.options(round(plate.photo_mm_per_px, 4)))
    p = plate.photo_mm_per_px
    errors: list[float] = []
    for stage, truth in zip(report["stages"], plate.stages, strict=True):
        for crack, row in zip(truth, rows_along(stage, truth, max(1.0, 2 * p)), strict=True):
            if row is None:  # recall is test_hairline_cracks': here every crack of 2 px and more must be found
                assert crack.width_mm < 1.9 * p, crack.width_mm
                continue
            if crack.width_mm < 1.6 * p:
                assert row["below_photo_resolution"], (crack.width_mm, row["mean_width_mm"])
                continue
            if crack.width_mm < 1.9 * p:
                continue
            assert not row["below_photo_resolution"], (crack.width_mm, row["mean_width_mm"])
            error = row["width_mm"] - crack.width_mm
            assert abs(error) < 3 * row["width_uncertainty_mm"] and abs(error) < 0.1, (crack.width_mm, error)
            errors.append(error)
    print(f"width errors of {len(errors)} cracks >= 2 photo px: {np.round(errors, 3).tolist()} mm")
    assert len(errors) >= 6
    assert abs(float(np.mean(errors))) < 0.05 and float(np.sqrt(np.mean(np.square(errors)))) < 0.05, errors
