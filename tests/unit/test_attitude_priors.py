"""Attitude priors checked frame by frame: survey strips flown back and forth (opposite headings), DJI
attitude metadata in either heading convention or mixed, a wrong angle on one frame, and frames the
adjustment would have kept on a handful of observations. Truth: ``tests.sfm_scenes.make_strip_scene``."""

from __future__ import annotations

import numpy as np
import pytest

import workers.algorithms.sfm.reconstruction as reconstruction
from tests.sfm_scenes import SfmScene, make_strip_scene
from workers.algorithms.geometry import vector_from_rotation
from workers.algorithms.sfm import Attitude, GpsFix, reconstruct
from workers.algorithms.sfm.priors import PriorCheck, candidate_rotations, check_attitude_priors
from workers.algorithms.sfm.tracks import relative_pose, verify_pairs


def _metadata(scene: SfmScene, flipped: set[int], off: dict[int, float], gps_m: float, seed: int = 8):
    """GPS fixes with ``gps_m`` noise, and DJI attitude with 2 degrees of noise per angle; ``flipped`` frames in
    the other convention (the image top faces yaw + 180), ``off`` frames with that many degrees of wrong yaw."""
    rng = np.random.default_rng(seed)
    n = len(scene.centres)
    gps = {
        f: GpsFix(tuple(scene.centres[f] + rng.normal(0, gps_m, 3)), max(gps_m, 0.05), max(gps_m, 0.05))
        for f in range(n)
    }
    attitude = {}
    for f in range(n):  # a flipped frame's metadata heading is the camera's turned by 180 degrees
        yaw, pitch, roll = scene.attitude[f] + rng.normal(0, 2.0, 3)
        attitude[f] = Attitude(yaw + (180.0 if f in flipped else 0.0) + off.get(f, 0.0), pitch, roll)
    return gps, attitude


def _errors(scene: SfmScene, rec) -> tuple[float, float]:
    """Worst camera centre error (m) and worst rotation error (degrees) over every frame."""
    n = len(scene.centres)
    assert sorted(rec.poses) == list(range(n)), rec.report["frames"]["not_registered"]
    centre = max(float(np.linalg.norm(rec.poses[f][1] - scene.centres[f])) for f in range(n))
    angle = max(
        np.degrees(np.linalg.norm(vector_from_rotation(rec.poses[f][0] @ scene.rotations[f].T))) for f in range(n)
    )
    return centre, float(angle)


def _relative(scene: SfmScene) -> dict:
    normalised = [scene.camera.pixel_to_normalised(f) for f in scene.features]
    verified, essential = verify_pairs(normalised, scene.matches, scene.camera.fx, 2.0, 20)
    return {
        p: relative_pose(essential[p], normalised[p[0]][fi], normalised[p[1]][fj])[:2]
        for p, (fi, fj) in verified.items()
    }


@pytest.fixture(scope="module")
def three_strips() -> SfmScene:
    return make_strip_scene(strips=3, seed=2, turn_last_deg=60.0)


def test_each_frame_gets_the_convention_its_pairs_agree_with(three_strips: SfmScene) -> None:
    middle = set(range(6, 12))  # the middle strip's metadata in the other convention
    gps, attitude = _metadata(three_strips, flipped=middle, off={14: 40.0}, gps_m=0.5)
    check = check_attitude_priors(_relative(three_strips), attitude, gps)
    assert set(check.rejected) == {14}, check.rejected  # the frame with a wrong yaw, and only it
    assert "disagrees with" in check.rejected[14]
    assert {f for f, c in check.conventions.items() if c == "yaw+180"} == middle
    for f, R in check.rotations.items():  # a kept prior is within its noise of the truth
        assert np.degrees(np.linalg.norm(vector_from_rotation(R @ three_strips.rotations[f].T))) < 8.0


def test_a_prior_with_no_pair_to_judge_it_is_kept_unchecked(three_strips: SfmScene) -> None:
    gps, attitude = _metadata(three_strips, flipped=set(), off={}, gps_m=0.5)
    check = check_attitude_priors({}, attitude, gps)
    assert check.rejected == {} and set(check.conventions.values()) == {"yaw"}


@pytest.mark.parametrize(
    ("strips", "flipped", "off"),
    [(2, set(), {}), (2, set(range(12)), {}), (3, set(range(6, 12)), {}), (2, set(), {3: 40.0})],
    ids=["two-strips-yaw", "two-strips-yaw+180", "three-strips-mixed", "one-wrong-yaw"],
)
def test_strips_with_opposite_headings_come_out_right(strips: int, flipped: set[int], off: dict[int, float]) -> None:
    scene = make_strip_scene(strips=strips, seed=2, turn_last_deg=60.0)
    gps, attitude = _metadata(scene, flipped, off, gps_m=0.1)
    rec = reconstruct(scene.features, scene.matches, scene.camera, gps=gps, attitude=attitude)
    assert rec.report["initialisation"] == "gps_attitude"
    centre, angle = _errors(scene, rec)
    # the bounds of the single-flight test (test_bundle.test_cameras_from_gps_and_attitude)
    assert centre < 1e-3 * scene.size and angle < 0.2 and rec.report["rms_reprojection_px"] <= 0.6
    per_frame = rec.report["per_frame"]
    for f in off:
        assert per_frame[str(f)]["attitude"].startswith("not used")
    assert all(e["observations"] >= 0.5 * e["tie_points_offered"] for e in per_frame.values())
    assert rec.report["warnings"] == []


def test_a_strip_the_adjustment_would_starve_is_placed_again(three_strips: SfmScene, monkeypatch) -> None:
    """With the priors trusted blindly (as before the check), the middle strip, whose metadata is in the other
    convention, is outvoted: its frames are placed again by PnP, and the report says so."""

    def trusting(relative, attitude, gps) -> PriorCheck:
        return PriorCheck(
            {f: candidate_rotations(a)[0] for f, a in attitude.items()}, dict.fromkeys(attitude, "yaw"), {}
        )

    monkeypatch.setattr(reconstruction, "check_attitude_priors", trusting)
    gps, attitude = _metadata(three_strips, flipped=set(range(6, 12)), off={}, gps_m=0.1)
    rec = reconstruct(three_strips.features, three_strips.matches, three_strips.camera, gps=gps, attitude=attitude)
    centre, angle = _errors(three_strips, rec)
    assert centre < 1e-3 * three_strips.size and angle < 0.2
    per_frame = rec.report["per_frame"]
    again = {name for name, e in per_frame.items() if e["status"] == "placed again"}
    assert again == {str(f) for f in range(6, 12)}
    assert all(per_frame[name]["observations"] >= 0.5 * per_frame[name]["tie_points_offered"] for name in again)
    assert sum("placed again" in w for w in rec.report["warnings"]) == 6


def test_a_frame_that_fits_nowhere_is_left_out_with_the_reason(three_strips: SfmScene) -> None:
    """A frame whose matches are all wrong (another place's photo) keeps no observations: not registered,
    with the reason, and a warning."""
    scene = three_strips
    rng = np.random.default_rng(4)
    matches = dict(scene.matches)
    for (i, j), (fi, fj) in scene.matches.items():
        if 7 in (i, j):  # every match of frame 7 points at a random feature
            k = (fi if i == 7 else fj).copy()
            k[:] = rng.integers(0, len(scene.features[7]), len(k))
            matches[(i, j)] = (k, fj) if i == 7 else (fi, k)
    gps, attitude = _metadata(scene, flipped=set(), off={}, gps_m=0.1)
    rec = reconstruct(scene.features, matches, scene.camera, gps=gps, attitude=attitude)
    assert 7 not in rec.poses and "7" in rec.report["frames"]["not_registered"]
    assert any(w.startswith("1 of 18 frames") and w.endswith("left out: 7") for w in rec.report["warnings"])
    assert len(rec.poses) == len(scene.centres) - 1
