"""A flight whose frames disagree (exposure, lens fall-off, a car that drives between shots), composed with seams
and multiband blending: the car is either there or not at each place it was seen, never a ghost of both, where
feathering leaves ghosts; the fall-off is found; the frame index says which frame each car came from."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio

from tests.scenes import SeamFlight, make_seam_flight
from workers.pipeline import process_directory
from workers.workspace import JobWorkspace


@pytest.fixture(scope="module")
def seam_flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[SeamFlight, dict[str, Path]]:
    root = tmp_path_factory.mktemp("seam_flight")
    flight = make_seam_flight(root / "frames")
    jobs = {}
    for blend in ("multiband", "feather"):
        options = {"working_max_px": 1024, "blend": blend, "vignetting_correction": True}
        process_directory(root / "frames", root / blend, options)
        jobs[blend] = root / blend
    return flight, jobs


def car_shares(flight: SeamFlight, job: Path) -> tuple[np.ndarray, np.ndarray]:
    """For each place the car was seen: how much of it the mosaic shows over the car's inner half (0: bare
    ground, 1: the car), and the frame index the mosaic gives there (most common value, index + 1)."""
    with rasterio.open(job / "mosaic.tif") as src, rasterio.open(job / "frame_index.tif") as index_src:
        rgb = np.moveaxis(src.read(), 0, 2).astype(np.float64)
        index = index_src.read(1)
        to_pixel = ~src.transform
    texture_to_utm = flight.flight.texture_to_utm
    ground = flight.flight.texture.astype(np.float64)
    shares, owners = [], []
    for car in flight.cars:
        centre = car.mean(axis=0)
        inner = centre + 0.5 * (car - centre)  # the car's inner half: a px of misregistration stays inside
        lo, hi = np.floor(inner.min(axis=0)).astype(int), np.ceil(inner.max(axis=0)).astype(int)
        tx, ty = np.meshgrid(np.arange(lo[0], hi[0]), np.arange(lo[1], hi[1]))
        east, north, _ = texture_to_utm @ np.vstack([tx.ravel(), ty.ravel(), np.ones(tx.size)])
        cols, rows = (np.floor(v).astype(int) for v in to_pixel @ (east, north))
        shown = rgb[rows, cols]
        bare = ground[ty.ravel(), tx.ravel()][:, ::-1]  # texture BGR -> RGB
        red = np.broadcast_to(flight.car_colour()[::-1], bare.shape)
        # shown = a bare + b car, whatever the exposure the mosaic settled on: the car's share is b / (a + b)
        (a, b), *_ = np.linalg.lstsq(np.column_stack([bare.ravel(), red.ravel()]), shown.ravel(), rcond=None)
        shares.append(b / (a + b))
        owners.append(np.bincount(index[rows, cols]).argmax())
    return np.array(shares), np.array(owners)


def test_the_moving_car_leaves_no_ghost(seam_flight) -> None:
    flight, jobs = seam_flight
    shares, owners = car_shares(flight, jobs["multiband"])
    # whole (the car's frame owns the place: its gain-corrected red is about 1) or absent (about 0)
    assert np.all((shares < 0.2) | (shares > 0.8)), shares
    frames = {f.index: f.name for f in JobWorkspace(jobs["multiband"]).load_frames()}
    for i, (share, owner) in enumerate(zip(shares, owners, strict=True)):
        assert (frames[owner - 1] == f"frame_{i:03d}.jpg") == (share > 0.5)  # the car shows where its frame owns
    feathered, _ = car_shares(flight, jobs["feather"])
    assert np.any((feathered > 0.25) & (feathered < 0.75)), feathered  # feathering: half a car, a ghost


def test_exposure_and_fall_off_are_evened_out(seam_flight) -> None:
    flight, jobs = seam_flight
    report = JobWorkspace(jobs["multiband"]).load_stage_report("compose_mosaic")
    found = report["vignetting"]
    assert abs(found["c1"] + found["c2"] - sum(flight.vignette)) < 0.1, found
    # the cut lines show less than the ground 16 px beside them does (0.86 here, 0.88 with one colour sample a
    # render px; on bench/seams.py's 1280 x 960 flight 0.78, where OpenCV's stitcher measures 0.82)
    assert report["seam_visibility"] < 0.95
