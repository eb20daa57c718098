"""Seams and multiband blending: a moving object stays whole on one side of the seam, windows never show,
and a single frame comes back as it was."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from tests.scenes import make_texture
from workers.algorithms.mosaic import compose_block, compose_block_multiband, output_box, seam_labels
from workers.workspace import JobWorkspace

W, H = 600, 400  # output grid, px


def _two_frames(moving_object: bool) -> tuple[dict, dict, dict, dict, dict]:
    """Two 400 x 300 frames of one texture, offset by (150, 60); with ``moving_object`` frame 1 also shows a
    red car (40 x 24 px) in the overlap that frame 0 does not see."""
    texture = make_texture(H, W, seed=4)
    images = {0: texture[:300, :400].copy(), 1: texture[60:360, 150:550].copy()}
    if moving_object:
        images[1][100:124, 120:160] = (30, 30, 220)  # BGR red, at output (270..310, 160..184)
    sizes = {0: (400, 300), 1: (400, 300)}
    # output px (GDAL corners) -> frame px (OpenCV centres)
    to_frame = {0: np.array([[1.0, 0, -0.5], [0, 1.0, -0.5], [0, 0, 1]])}
    to_frame[1] = np.array([[1.0, 0, -150.5], [0, 1.0, -60.5], [0, 0, 1]])
    boxes = {k: output_box(M, sizes[k], W, H) for k, M in to_frame.items()}
    gains = {k: np.ones(3) for k in images}
    return images, sizes, to_frame, boxes, gains


def _multiband(images, sizes, to_frame, boxes, gains, window, bands=4):
    labels, scale = seam_labels(images.__getitem__, sizes, to_frame, gains, W, H)
    return compose_block_multiband(images.__getitem__, sizes, to_frame, boxes, gains, window, labels, scale, bands)


def test_a_moving_object_stays_whole_on_one_side_of_the_seam() -> None:
    images, sizes, to_frame, boxes, gains = _two_frames(moving_object=True)
    car = (slice(160, 184), slice(270, 310))  # output rows, columns
    with_car = images[1][100:124, 120:160][..., ::-1].astype(int)  # RGB, as the mosaic is
    without = images[0][160:184, 270:310][..., ::-1].astype(int)
    rgb, mask, _ = _multiband(images, sizes, to_frame, boxes, gains, (0, 0, W, H))
    got = rgb[car].astype(int)
    whole = min(np.abs(got - with_car).mean(), np.abs(got - without).mean())
    # all car or no car, not a ghost of both: the cut runs around it (its fine bands are the car's); its
    # coarsest bands, wider than the car, still carry some of the ground beside it (11 levels of 255 here)
    assert mask[car].all() and whole < 15.0, whole
    feathered, _, _ = compose_block(images.__getitem__, sizes, to_frame, boxes, gains, (0, 0, W, H), 60.0)
    ghost = feathered[car].astype(int)
    assert min(np.abs(ghost - with_car).mean(), np.abs(ghost - without).mean()) > 40  # feathering: half of each


@pytest.mark.parametrize("step", [12, 40, 200])
def test_the_cut_goes_around_a_difference_of_any_strength(step: int) -> None:
    """A patch one frame shows brighter by ``step`` levels, on the shortest way across the overlap (its
    diagonal), is left whole to one frame: OpenCV's GraphCutSeamFinder, COST_COLOR or COST_COLOR_GRAD, cut it in
    two at each of these strengths."""
    images, sizes, to_frame, boxes, gains = _two_frames(moving_object=False)
    patch = (slice(100, 130), slice(105, 155))  # frame 1 px: output (255..305, 160..190), mid-overlap
    images[1][patch] = np.clip(images[1][patch].astype(int) + step, 0, 255).astype(np.uint8)
    labels, scale = seam_labels(images.__getitem__, sizes, to_frame, gains, W, H)
    ys, xs = np.mgrid[160:190, 255:305]  # the patch's output px -> label cells
    owners = labels[np.floor((ys + 0.5) * scale).astype(int), np.floor((xs + 0.5) * scale).astype(int)]
    assert len(np.unique(owners)) == 1, np.unique(owners, return_counts=True)


@pytest.mark.parametrize("samples", [1, 3])
def test_the_cut_goes_around_fine_detail_the_frames_disagree_on(samples: int, monkeypatch) -> None:
    """Fine stripes that one frame shows shifted by half a period (parallax or a misregistration of fine
    detail), on the cut's way across a noisy overlap: at one sample a render px the stripes' phase can agree
    at every sample (here it does, by construction: a period of two render px, zero at their centres) and the
    cut ran through them, a step in the mosaic; the mean over 3 x 3 samples a px sees them and goes around."""
    from workers.algorithms.mosaic import multiband

    monkeypatch.setattr(multiband, "SEAM_SUPERSAMPLE", samples)
    width, height = 1800, 1200  # frames 1200 x 900: a render px is about 3.3 px of theirs
    texture = make_texture(height, width, seed=4)
    images = {0: texture[:900, :1200].copy(), 1: texture[180:1080, 450:1650].copy()}
    noise = np.random.default_rng(1).normal(0, 8, images[1].shape)  # the frames disagree a little everywhere
    images[1] = np.clip(images[1] + noise, 0, 255).astype(np.uint8)
    sizes = {0: (1200, 900), 1: (1200, 900)}
    to_frame = {0: np.array([[1.0, 0, -0.5], [0, 1.0, -0.5], [0, 0, 1]])}
    to_frame[1] = np.array([[1.0, 0, -450.5], [0, 1.0, -180.5], [0, 0, 1]])
    r = multiband.seam_scale(sizes, to_frame, width, height)
    x0, x1, y0, y1 = 845, 995, 495, 585  # output px, on the way the cut takes without the stripes
    stripes = np.cos(np.pi * r * (np.arange(x0, x1) + 0.5))  # zero at the render's px centres ((i + 0.5) / r)
    images[0][y0:y1, x0:x1] = np.round(128 + 60 * stripes).astype(np.uint8)[None, :, None]
    images[1][y0 - 180 : y1 - 180, x0 - 450 : x1 - 450] = np.round(128 - 60 * stripes).astype(np.uint8)[None, :, None]
    labels, scale = seam_labels(images.__getitem__, sizes, to_frame, {0: np.ones(3), 1: np.ones(3)}, width, height)
    ys, xs = np.mgrid[y0:y1, x0:x1]
    owners = labels[np.floor((ys + 0.5) * scale).astype(int), np.floor((xs + 0.5) * scale).astype(int)]
    assert len(np.unique(owners)) == (2 if samples == 1 else 1), np.unique(owners, return_counts=True)


def test_windows_never_show() -> None:
    """Composed window by window or in one piece, the same pixels: each window's margin holds its bands."""
    images, sizes, to_frame, boxes, gains = _two_frames(moving_object=False)
    whole, whole_mask, whole_index = _multiband(images, sizes, to_frame, boxes, gains, (0, 0, W, H))
    for x in range(0, W, 128):
        for y in range(0, H, 128):
            w, h = min(128, W - x), min(128, H - y)
            part, part_mask, part_index = _multiband(images, sizes, to_frame, boxes, gains, (x, y, w, h))
            assert np.array_equal(part_mask, whole_mask[y : y + h, x : x + w])
            assert np.abs(part.astype(int) - whole[y : y + h, x : x + w].astype(int)).max() <= 1
            assert np.array_equal(part_index, whole_index[y : y + h, x : x + w])  # the same seam owners
    assert set(np.unique(whole_index[whole_mask]).tolist()) == {0, 1} and (whole_index[~whole_mask] == -1).all()


def test_one_frame_comes_back_unchanged() -> None:
    images, sizes, to_frame, boxes, gains = _two_frames(moving_object=False)
    one = {0: images[0]}
    rgb, mask, _ = _multiband(one, {0: sizes[0]}, {0: to_frame[0]}, {0: boxes[0]}, {0: gains[0]}, (0, 0, 400, 300))
    assert mask.all()
    assert np.abs(rgb[..., ::-1].astype(int) - images[0].astype(int)).max() <= 1


def test_a_multiband_mosaic_shows_the_ground_where_it_lies(tmp_path) -> None:
    from tests.scenes import make_flight
    from tests.unit.test_pipeline_truth import ground_colour_error
    from workers.pipeline import process_directory

    flight = make_flight(tmp_path / "frames", n_frames=6, rotation_deg=10, scale_jitter=0.05, gps=True, seed=4)
    report = process_directory(tmp_path / "frames", tmp_path / "job", {"working_max_px": 1024, "blend": "multiband"})
    assert len(report["frames_used"]) == 6 and report["config"]["blend"] == "multiband"
    assert 0 < report["mosaic"]["seam_visibility"] < 0.8  # the cut lines show less than the ground does (0.69)
    assert ground_colour_error(flight, tmp_path / "job" / "mosaic.tif") < 10.0
    ws = JobWorkspace(tmp_path / "job")
    assert "cutlines.geojson" in ws.outputs()
    cutlines = json.loads((tmp_path / "job" / "cutlines.geojson").read_text())["features"]
    footprints = {f["properties"]["index"]: f for f in ws.load_footprints()["features"]}
    assert sorted(f["properties"]["index"] for f in cutlines) == sorted(footprints)  # every frame owns a part
    for feature in cutlines:  # and what it owns lies inside its own footprint (lon/lat; a few px of slack)
        lon, lat = np.concatenate([np.array(p[0]) for p in feature["geometry"]["coordinates"]]).T
        outline = np.array(footprints[feature["properties"]["index"]]["geometry"]["coordinates"][0])
        slack = 5 * report["gsd_m"] / 111_000
        assert outline[:, 0].min() - slack <= lon.min() and lon.max() <= outline[:, 0].max() + slack
        assert outline[:, 1].min() - slack <= lat.min() and lat.max() <= outline[:, 1].max() + slack
    assert_frame_index_is_true(flight, ws, report)
    feather = process_directory(tmp_path / "frames", tmp_path / "feather", {"working_max_px": 1024})
    assert "cutlines.geojson" not in JobWorkspace(tmp_path / "feather").outputs()  # feathering cuts no seams
    assert feather["mosaic"]["seam_visibility"] is None  # nor measures them, unless asked (a second)
    assert_frame_index_is_true(flight, JobWorkspace(tmp_path / "feather"), feather)
    measured = process_directory(
        tmp_path / "frames", tmp_path / "measured", {"working_max_px": 1024, "measure_seams": True}
    )
    # measured on the same seams: a feathered mosaic's ground is the same, its seams show about as little
    assert 0 < measured["mosaic"]["seam_visibility"] < 1.3


def assert_frame_index_is_true(flight, ws: JobWorkspace, report: dict) -> None:
    """``frame_index.tif``: a uint16 COG on the mosaic's grid, 0 exactly where the mosaic has no data, and every
    other value a frame (index + 1) that does see the pixel's ground (by the flight's true homographies)."""
    import rasterio

    assert "frame_index.tif" in ws.outputs()
    with rasterio.open(ws.frame_index_path()) as src, rasterio.open(ws.mosaic_path()) as mosaic:
        assert src.dtypes == ("uint16",) and src.nodata == 0 and src.overviews(1)
        assert src.transform == mosaic.transform and src.crs == mosaic.crs
        index, covered = src.read(1), mosaic.dataset_mask() > 0
        names = {int(k.removeprefix("FRAME_")): v for k, v in src.tags().items() if k.startswith("FRAME_")}
    assert np.array_equal(index > 0, covered)
    frames = {f.index: f.name for f in ws.load_frames()}
    assert set(np.unique(index[index > 0]).tolist()) == {k + 1 for k in frames}  # every frame gives pixels
    assert names == {k + 1: name for k, name in frames.items()}
    rows, cols = np.nonzero(index)
    pick = np.random.default_rng(0).choice(len(rows), 3000)
    east, north = rasterio.transform.xy(src.transform, rows[pick], cols[pick])
    tex = np.column_stack([east, north, np.ones(len(pick))]) @ np.linalg.inv(flight.texture_to_utm).T
    w, h = flight.frame_size
    inside = []
    for (tx, ty, _), value in zip(tex, index[rows[pick], cols[pick]], strict=True):
        n = int(frames[int(value) - 1].removeprefix("frame_").removesuffix(".jpg"))
        fx, fy, fw = np.linalg.inv(flight.homographies[n]) @ [tx, ty, 1.0]
        inside.append(-2 <= fx / fw <= w + 1 and -2 <= fy / fw <= h + 1)  # a px or two of slack at the edge
    assert np.mean(inside) == 1.0, np.mean(inside)


def test_seam_visibility_sees_a_step_and_not_a_smooth_join() -> None:
    from workers.algorithms.mosaic import seam_points, seam_visibility

    noise = np.random.default_rng(6).normal(128, 40, (200, 300, 3))
    texture = np.clip(cv2.GaussianBlur(noise, (0, 0), 1.5), 0, 255)  # stationary: no line is special
    labels = np.zeros((100, 150), np.int32)
    labels[:, 75:] = 1  # the seam at output x = 150 (labels at half resolution)
    points, normals = seam_points(labels, 0.5)
    assert len(points) and np.allclose(points[:, 0], 150.0) and np.all(normals == [1.0, 0.0])

    def reader(image: np.ndarray):
        def read(x: int, y: int, w: int, h: int):
            window = image[max(y, 0) : y + h, max(x, 0) : x + w]
            return window, np.ones(window.shape[:2], bool)

        return read

    stepped = texture.copy()
    stepped[:, 150:] = np.clip(stepped[:, 150:] * 1.4 + 25, 0, 255)  # right frame far brighter
    assert seam_visibility(reader(texture.astype(np.uint8)), points, normals) < 1.3
    assert seam_visibility(reader(stepped.astype(np.uint8)), points, normals) > 1.5
