"""Hairline cracks of a brittle coating, 0.5-3 photo pixels wide, 30 % darker than the coating, under
uneven light, on grain, through a blurred lens (``tests/crack_scenes.py``, exact sub-pixel cover): every
crack at least one photo pixel wide is found, whatever the output raster, and little else is. At lower
contrast the report's smallest detectable width holds: every crack at least that wide is found."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from tests.crack_scenes import CrackSurveyScene, make_crack_survey, rows_along, run_survey, score_stage

WIDTHS_PX = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0)  # crack widths in photo pixels, in turn
CONTRAST = 0.3


@pytest.fixture(scope="module")
def hairlines(tmp_path_factory: pytest.TempPathFactory) -> CrackSurveyScene:
    return make_crack_survey(
        tmp_path_factory.mktemp("hairlines"),
        [(45.0, 15.0)],
        seed=11,
        frame_size=(800, 600),
        widths_px=WIDTHS_PX,
        contrast=CONTRAST,
        blur_px=0.5,
    )


def test_every_crack_one_photo_pixel_wide_is_found(hairlines: CrackSurveyScene, tmp_path: Path) -> None:
    report = run_survey(hairlines, tmp_path, hairlines.options(round(2 * hairlines.photo_mm_per_px, 4)))
    tolerance = max(1.0, 2 * hairlines.photo_mm_per_px)
    recall: dict[float, list[float]] = defaultdict(list)
    false_mm = true_mm = 0.0
    for stage, truth in zip(report["stages"], hairlines.stages, strict=True):
        score = score_stage(stage, truth, tolerance)
        for crack, found in zip(truth, score.found, strict=True):
            recall[round(crack.width_mm / hairlines.photo_mm_per_px, 2)].append(found)
        false_mm += score.false_mm
        true_mm += score.true_mm
        # the report says how fine this setup sees: about one photo pixel at the cracks' contrast, which it
        # measured on the widest of them
        assert abs(report["crack_contrast"] - CONTRAST) < 0.03
        assert stage["smallest_detectable_width_mm"] < 1.5 * stage["photo_mm_per_px"]
        assert abs(stage["photo_mm_per_px"] / hairlines.photo_mm_per_px - 1) < 0.1
    print({w: round(float(np.mean([f > 0.8 for f in r])), 2) for w, r in sorted(recall.items())}, false_mm / true_mm)
    for width_px, shares in recall.items():
        if width_px >= 1.0:
            assert min(shares) > 0.8, (width_px, shares)  # every one, along most of its length
    assert false_mm < 0.02 * true_mm, (false_mm, true_mm)


def test_widths_are_flagged_below_photo_resolution_and_honest_above(
    hairlines: CrackSurveyScene, tmp_path: Path
) -> None:
    """A found crack under 2 photo px is flagged (its width is only bounded: within the reported range); one of
    3 px is not, and its width is within 0.05 mm and its stated uncertainty (x 3)."""
    report = run_survey(hairlines, tmp_path, hairlines.options(round(hairlines.photo_mm_per_px, 4)))
    p = hairlines.photo_mm_per_px
    checked = 0
    for stage, truth in zip(report["stages"], hairlines.stages, strict=True):
        for crack, row in zip(truth, rows_along(stage, truth, max(1.0, 2 * p)), strict=True):
            if row is None:
                continue
            checked += 1
            if crack.width_mm < 1.6 * p:
                assert row["below_photo_resolution"], (crack.width_mm, row)
                assert row["width_mm"] + row["width_uncertainty_mm"] >= crack.width_mm
            if crack.width_mm > 2.9 * p:
                assert not row["below_photo_resolution"], (crack.width_mm, row)
                error = abs(row["width_mm"] - crack.width_mm)
                assert error < 0.05 and error < 3 * row["width_uncertainty_mm"], (crack.width_mm, row["width_mm"])
    assert checked >= 6


def test_fainter_cracks_as_wide_as_the_report_says_are_found(tmp_path: Path) -> None:
    """At 20 % contrast and 60 degrees (seed 53, no tuning used it; the claim was measured at 45 degrees), the
    report measures the cracks' contrast on the widest of them and says how narrow a crack of that contrast
    it finds, at worst over the specimen: every crack at least that wide is found."""
    scene = make_crack_survey(
        tmp_path / "photos",
        [(60.0, 15.0)],
        seed=53,
        frame_size=(640, 480),
        widths_px=(1.0, 1.5, 2.0, 2.5, 3.0, 4.0),
        contrast=0.2,
        blur_px=0.5,
    )
    report = run_survey(scene, tmp_path / "survey", scene.options(round(scene.photo_mm_per_px, 4)))
    assert abs(report["crack_contrast"] - 0.2) < 0.03
    checked = 0
    for stage, truth in zip(report["stages"], scene.stages, strict=True):
        low, high = stage["smallest_detectable_width_range_mm"]
        assert 1.5 * stage["photo_mm_per_px"] < high < 3 * stage["photo_mm_per_px"]  # 2 px at 20 %
        score = score_stage(stage, truth, max(1.0, 2 * scene.photo_mm_per_px))
        for crack, found in zip(truth, score.found, strict=True):
            if crack.width_mm >= high:
                checked += 1
                assert found > 0.8, (crack.width_mm, high, found)
    assert checked >= 4
