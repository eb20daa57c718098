"""Crack widths of rendered hairline plates (``tests/crack_scenes.py``: exact sub-pixel cover of each photo
pixel's footprint, 0.5 px PSF, grain, uneven light), cracks of 1-4 photo pixels.

Photo pixels are counted across each crack, from the true camera: an oblique view's pixel reaches twice as
far along the view as across it at 30 degrees, so the same crack spans fewer pixels when it runs across
the view. Every crack at least 2 photo pixels wide across is measured, not flagged; every one under 1.6
px is flagged, with an interval that holds its true width.

- At the issue's sampling (``fine``: 0.15-0.2 mm per photo pixel, 35 % contrast, cracks of 0.15-0.8 mm):
  every crack of 2 px and more within 0.05 mm of its true width.
- At 0.4-0.5 mm per photo pixel (``coarse``, cracks of 0.5-2 mm, 30 % contrast) a crack's width error has
  a part proportional to its width: the coating's own brightness varies by 2-3 % at the scale of a
  millimetre (its grain), under the crack as well as beside it, and the crack's darkness is measured
  against it. A 2 mm crack may be 0.06 mm off; the stated uncertainty (0.08 photo px plus 3 % of the width,
  one sigma) says so, and every error is within 3 of them and within 0.05 mm plus 3 % of the width.

The width estimator was tuned on other seeds (7, 11, 13, 31 at 45 degrees; 23 at 30 and 60 degrees; the
4000 x 3000 plate of seed 101 at 45 degrees); seed 41 at 30 degrees showed the share of the width.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.crack_scenes import CrackSurveyScene, make_crack_survey, photo_px_across, rows_along, run_survey

WIDTHS_PX = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0)  # crack widths in nominal photo pixels, in turn
SCENES = {  # name: (elevation, seed, plate mm, frame px, contrast, crack lengths mm)
    "fine30": (30.0, 43, (100.0, 75.0), (1000, 750), 0.35, (18.0, 40.0)),
    "fine60": (60.0, 43, (100.0, 75.0), (1000, 750), 0.35, (18.0, 40.0)),
    "coarse30": (30.0, 41, (200.0, 150.0), (800, 600), 0.3, (50.0, 80.0)),
}


@pytest.fixture(scope="module", params=sorted(SCENES))
def plate(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> CrackSurveyScene:
    elevation, seed, (width, height), frame, contrast, lengths = SCENES[request.param]
    return make_crack_survey(
        tmp_path_factory.mktemp(request.param),
        [(elevation, 15.0)],
        seed=seed,
        width_mm=width,
        height_mm=height,
        frame_size=frame,
        widths_px=WIDTHS_PX,
        contrast=contrast,
        blur_px=0.5,
        lengths_mm=lengths,
    )


def test_widths_of_cracks_two_photo_pixels_wide_and_more(plate: CrackSurveyScene, tmp_path: Path) -> None:
    report = run_survey(plate, tmp_path, plate.options(round(plate.photo_mm_per_px, 4)))
    p = plate.photo_mm_per_px
    fine = p < 0.25
    errors: list[float] = []
    for s, (stage, truth) in enumerate(zip(report["stages"], plate.stages, strict=True)):
        for crack, row in zip(truth, rows_along(stage, truth, max(1.0, 2 * p)), strict=True):
            across_px = crack.width_mm / photo_px_across(plate, crack, s)
            if row is None:  # recall is test_hairline_cracks': here every crack of 2 px and more must be found
                assert across_px < 1.9, (crack.width_mm, across_px)
                continue
            if across_px < 1.6:
                assert row["below_photo_resolution"], (crack.width_mm, across_px, row["width_mm"])
                low, high = row["width_mm"] - row["width_uncertainty_mm"], row["width_mm"] + row["width_uncertainty_mm"]
                assert low <= crack.width_mm <= high, (crack.width_mm, row["width_mm"], row["width_uncertainty_mm"])
                continue
            if across_px < 1.9:
                continue
            assert not row["below_photo_resolution"], (crack.width_mm, across_px, row["width_mm"])
            error = row["width_mm"] - crack.width_mm
            bound = 0.05 if fine else 0.05 + 0.03 * crack.width_mm
            assert abs(error) < 3 * row["width_uncertainty_mm"] and abs(error) < bound, (crack.width_mm, error)
            errors.append(error)
    print(f"p {p:.3f} mm/px: width errors of {len(errors)} cracks >= 2 photo px across: {np.round(errors, 3).tolist()}")
    assert len(errors) >= 4
    assert abs(float(np.mean(errors))) < 0.03 and float(np.sqrt(np.mean(np.square(errors)))) < 0.04, errors
