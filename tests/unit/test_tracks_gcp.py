"""Tracks from pairwise matches, pair verification, GCP file parsers and the datum fits."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.sfm_scenes import make_sfm_scene
from workers.algorithms.geometry import lonlat_to_utm, rotation_from_vector
from workers.algorithms.sfm import (
    LocalFrame,
    build_tracks,
    line_similarity,
    parse_gcp_list,
    parse_opensfm_gcps,
    refine_similarity,
    scale_observations,
    similarity_3d,
    verify_pairs,
)

FRAME = LocalFrame(32632, 500_000.0, 5_000_000.0)  # UTM 32N, near lon 9, lat 45


def idx(*values: int) -> np.ndarray:
    return np.array(values, dtype=np.int64)


def test_tracks_join_chains_of_matches_and_drop_conflicts() -> None:
    matches = {
        (0, 1): (idx(0, 1, 5), idx(3, 4, 7)),
        (1, 2): (idx(3, 4), idx(9, 8)),
        (0, 2): (idx(0, 6), idx(9, 2)),  # 0:6 - 2:2 is a lone pair; 0:0 closes the loop 0:0-1:3-2:9
        (2, 3): (idx(8, 2), idx(1, 1)),  # 3:1 joins 2:8 and 2:2 -> two features of frame 2: conflict
    }
    tracks = build_tracks(matches)
    found = {
        tuple(
            sorted(
                zip(tracks.frame[tracks.track == t].tolist(), tracks.feature[tracks.track == t].tolist(), strict=True)
            )
        )
        for t in range(tracks.n_tracks)
    }
    assert found == {((0, 0), (1, 3), (2, 9)), ((0, 5), (1, 7))}
    assert sorted(tracks.lengths().tolist()) == [2, 3]
    assert build_tracks(matches, min_length=3).n_tracks == 1
    track_ids, features = tracks.in_frame(2)
    assert features.tolist() == [9] and tracks.lengths()[track_ids[0]] == 3


def test_tracks_of_nothing_and_misuse() -> None:
    assert build_tracks({}).n_tracks == 0
    with pytest.raises(ValueError):
        build_tracks({(0, 0): (idx(1), idx(2))})
    with pytest.raises(ValueError):
        build_tracks({(0, 1): (idx(1, 2), idx(2))})
    with pytest.raises(ValueError):
        build_tracks({(0, 1): (idx(1), idx(2))}, min_length=1)


def test_verification_removes_planted_wrong_matches() -> None:
    scene = make_sfm_scene(n_ring=8, n_nadir=4, n_points=800, seed=3)
    normalised = [scene.camera.pixel_to_normalised(f) for f in scene.features]
    verified, essential = verify_pairs(normalised, scene.matches, scene.camera.fx, 2.0, 20)
    kept_wrong = kept_right = total_wrong = total_right = 0
    for pair, (fi, fj) in scene.matches.items():
        wrong = scene.wrong[pair]
        total_wrong, total_right = total_wrong + wrong.sum(), total_right + (~wrong).sum()
        if pair in verified:
            kept = set(zip(verified[pair][0].tolist(), verified[pair][1].tolist(), strict=True))
            flags = np.array([(a, b) in kept for a, b in zip(fi.tolist(), fj.tolist(), strict=True)])
            kept_wrong += (flags & wrong).sum()
            kept_right += (flags & ~wrong).sum()
            assert essential[pair].shape == (3, 3)
    assert total_wrong > 500
    assert kept_wrong / total_wrong < 0.03, "verification should drop nearly all wrong matches"
    assert kept_right / total_right > 0.97


GCP_LIST = """WGS84 UTM 32N
500010.0 5000020.0 101.5 1200.5 800.25 a.jpg p1
500010.0 5000020.0 101.5 330 410 b.jpg p1   # same point, second image
500100 5000000 99 20 30 a.jpg p2 extra fields ignored

510000 5000000 98 5 6 c.jpg
"""


def test_odm_gcp_list_with_utm_zone_names_and_groups_by_name_or_coordinates() -> None:
    gcps = parse_gcp_list(GCP_LIST, FRAME)
    assert [g.id for g in gcps] == ["p1", "p2", "510000 5000000 98"]
    p1 = gcps[0]
    assert np.allclose(p1.position, [10.0, 20.0, 101.5], atol=1e-6)
    assert set(p1.observations) == {"a.jpg", "b.jpg"} and np.allclose(p1.observations["a.jpg"], [1200.5, 800.25])
    assert np.allclose(gcps[2].position, [10_000.0, 0.0, 98.0], atol=1e-6)


def test_odm_gcp_list_in_lonlat_and_proj_strings() -> None:
    lon, lat = 9.01, 45.02
    expected = lonlat_to_utm(np.array([[lon, lat]]), 32632)[0] - [FRAME.easting0, FRAME.northing0]
    for crs in ("EPSG:4326", "+proj=longlat +datum=WGS84 +no_defs"):
        (gcp,) = parse_gcp_list(f"{crs}\n{lon} {lat} 12.0 10 20 x.jpg g\n", FRAME)
        assert np.allclose(gcp.position[:2], expected, atol=1e-3) and gcp.position[2] == 12.0


@pytest.mark.parametrize(
    "text, line",
    [
        ("", 1),
        ("NOT A CRS\n1 2 3 4 5 a.jpg\n", 1),
        ("WGS84 UTM 61N\n", 1),
        ("EPSG:32632\n1 2 3 4 5 a.jpg\n1 2 3 4 a.jpg\n", 3),
        ("EPSG:32632\n\n1 2 x 4 5 a.jpg\n", 3),
        ("EPSG:32632\n1 2 3 4 5 a.jpg p\n1 2 3 6 7 a.jpg p\n", 3),  # observed twice in one image
        ("EPSG:32632\n1 2 3 4 5 a.jpg p\n1 2 4 6 7 b.jpg p\n", 3),  # same name, other coordinates
        ("EPSG:32632\n1 2 3 -4 5 a.jpg\n", 2),
        ("EPSG:4326\n9.0 45.0 1 4 5 a.jpg\n9.0 95.0 1 4 5 a.jpg\n", 3),  # latitude 95
        ("EPSG:4326\n500 45.0 1 4 5 a.jpg\n", 2),  # longitude 500
        ("EPSG:32615\n1e300 1e300 1 4 5 a.jpg\n", 2),  # no place in the job's UTM zone
    ],
)
def test_odm_gcp_list_bad_input_names_the_line(text: str, line: int) -> None:
    with pytest.raises(ValueError, match=f"line {line}"):
        parse_gcp_list(text, FRAME)


OPENSFM_JSON = {
    "points": [
        {
            "id": "0",
            "position": {"latitude": 45.02, "longitude": 9.01, "altitude": 14.9},
            "observations": [
                {"shot_id": "a.jpg", "projection": [-0.015689, -0.0625362]},
                {"shot_id": "elsewhere.jpg", "projection": [0.1, 0.1]},
            ],
        },
        {"id": "1", "observations": [{"shot_id": "b.jpg", "projection": [0.5, 0.375]}]},
    ]
}


def test_opensfm_gcps_denormalise_projections_like_opensfm() -> None:
    sizes = {"a.jpg": (3264, 2448), "b.jpg": (1024, 768)}
    gcps = parse_opensfm_gcps(json.dumps(OPENSFM_JSON), sizes, FRAME)
    a = gcps[0].observations["a.jpg"]
    # opensfm.features.denormalized_image_coordinates: x * max(w, h) - 0.5 + w / 2
    assert np.allclose(a, [-0.015689 * 3264 - 0.5 + 1632, -0.0625362 * 3264 - 0.5 + 1224])
    assert set(gcps[0].observations) == {"a.jpg"}  # images outside the job are skipped
    assert gcps[1].position is None
    assert np.allclose(gcps[1].observations["b.jpg"], [1023.5, 767.5])  # the frame's far corner
    expected = lonlat_to_utm(np.array([[9.01, 45.02]]), 32632)[0] - [FRAME.easting0, FRAME.northing0]
    assert np.allclose(gcps[0].position, [*expected, 14.9], atol=1e-6)
    half = scale_observations(gcps, 0.5)
    assert np.allclose(half[1].observations["b.jpg"], [511.5, 383.5])


@pytest.mark.parametrize(
    "text, where",
    [
        ('{"points": [\n  {"id": 1,}\n]}', "line 2"),
        ('{"points": 3}', "points"),
        ('{"points": [{"observations": []}]}', r"points\[0\]"),
        ('{"points": [{"id": "a", "position": {"latitude": "x", "longitude": 1, "altitude": 2}}]}', "latitude"),
        ('{"points": [{"id": "a", "observations": [{"shot_id": "a.jpg", "projection": [1]}]}]}', "observations"),
        ('{"points": [{"id": "a", "observations": 3}]}', r"points\[0\]\.observations: expected a list"),
        ('{"points": [{"id": "a", "observations": {"a.jpg": [1, 2]}}]}', r"points\[0\]\.observations"),
        ('{"points": [{"id": "a", "position": {"latitude": 95, "longitude": 1, "altitude": 2}}]}', "latitude 95"),
        ('{"points": [{"id": "a", "position": {"latitude": 5, "longitude": -500, "altitude": 2}}]}', "longitude -500"),
    ],
)
def test_opensfm_gcps_bad_input(text: str, where: str) -> None:
    with pytest.raises(ValueError, match=where):
        parse_opensfm_gcps(text, {"a.jpg": (100, 100)}, FRAME)


def test_similarity_fits_recover_planted_transforms() -> None:
    rng = np.random.default_rng(7)
    R = rotation_from_vector(np.array([0.3, -0.2, 1.1]))
    src = rng.normal(0, 10, (12, 3))
    dst = 2.5 * src @ R.T + [100.0, -50.0, 7.0]
    s, R_fit, t = similarity_3d(src, dst)
    assert abs(s - 2.5) < 1e-9 and np.allclose(R_fit, R) and np.allclose(t, [100.0, -50.0, 7.0])
    s2, R2, t2 = refine_similarity(
        src,
        dst + rng.normal(0, 0.01, dst.shape),
        np.full(12, 0.01),
        2.4,
        rotation_from_vector(np.array([0.32, -0.18, 1.1])),
        t + 1.0,
    )
    assert abs(s2 - 2.5) < 1e-3 and np.abs(R2 - R).max() < 1e-3


def test_line_similarity_levels_the_cameras_about_a_collinear_strip() -> None:
    scene = make_sfm_scene(n_ring=0, n_nadir=8, n_points=10, seed=1)
    truth_R, truth_C = scene.rotations[:5], np.column_stack([np.arange(5) * 10.0, np.zeros(5), np.full(5, 60.0)])
    planted = rotation_from_vector(np.array([0.4, 0.9, -0.3]))
    model_C = 0.2 * truth_C @ planted.T + [3.0, 1.0, -2.0]  # model = planted similarity of the truth
    model_R = truth_R @ planted.T
    s, R, t = line_similarity(model_C, truth_C, model_R)
    assert abs(s - 5.0) < 1e-9
    assert np.allclose(s * model_C @ R.T + t, truth_C, atol=1e-9)
    assert np.abs(R @ planted - np.eye(3)).max() < 1e-6  # nadir cameras: the turn about the line is found


def test_line_similarity_turns_photos_facing_along_the_line_to_look_down() -> None:
    """Nadir photos whose right-hand side faces along the flight line (x axes along it, a few degrees of yaw and
    tilt each): levelling their x axes hardly turns the model about the line, so their optical axes are taken
    down (levelling alone left such a flight 20-25 degrees off nadir)."""
    rng = np.random.default_rng(3)
    level = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # x east, y south, z down
    truth_R = np.array([level @ rotation_from_vector(rng.normal(0, np.radians(3), 3)) for _ in range(8)])
    truth_C = np.column_stack([np.arange(8) * 10.0, rng.normal(0, 1.0, 8), np.full(8, 60.0)])
    planted = rotation_from_vector(np.array([0.4, 0.9, -0.3]))
    model_C = 0.2 * truth_C @ planted.T + [3.0, 1.0, -2.0]
    model_R = truth_R @ planted.T
    s, R, t = line_similarity(model_C, truth_C, model_R)
    found = model_R @ R.T  # world -> camera after the fit
    off_nadir = np.degrees(np.arccos(-found[:, 2, 2]))
    true_off = np.degrees(np.arccos(-truth_R[:, 2, 2]))
    assert abs(off_nadir.mean() - true_off.mean()) < 3.0, (off_nadir, true_off)
    assert np.degrees(np.arccos(np.clip((np.trace(R @ planted) - 1) / 2, -1, 1))) < 3.0  # the planted turn undone
