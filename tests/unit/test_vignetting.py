"""The lens' radial fall-off, estimated from the overlaps of frames that carry it, and undone in the mosaic."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from tests.scenes import make_flight, make_texture
from workers.algorithms.mosaic.vignetting import falloff, fit_vignetting, radius2
from workers.pipeline import process_directory
from workers.workspace import JobWorkspace

TRUE = (-0.35, -0.05)  # c1, c2: corners at exp(-0.4), about 67 % of the centre's brightness


def _vignetted(frame: np.ndarray, vignette: tuple[float, float]) -> np.ndarray:
    h, w = frame.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.clip(frame * falloff(radius2(xs, ys, w, h), vignette)[..., None], 0, 255)


def test_fall_off_is_found_from_overlaps_alone() -> None:
    """Frames cut from one texture at known offsets, each darkened by the same fall-off and its own gain."""
    texture = make_texture(300, 700, seed=5).astype(np.float32)
    size = (300, 200)
    images, masks, radii = [], [], []
    for n, (x0, y0) in enumerate([(0, 0), (120, 40), (240, 10), (360, 80), (400, 0)]):
        grid = np.zeros((300, 700, 3), np.float32)
        frame = _vignetted(texture[y0 : y0 + size[1], x0 : x0 + size[0]], TRUE) * (1.0 + 0.05 * (n - 2))
        grid[y0 : y0 + size[1], x0 : x0 + size[0]] = frame
        mask = np.zeros((300, 700), bool)
        mask[y0 : y0 + size[1], x0 : x0 + size[0]] = True
        ys, xs = np.mgrid[0:300, 0:700].astype(np.float32)
        images.append(grid)
        masks.append(mask)
        radii.append(radius2(xs - x0, ys - y0, *size))
    c1, c2 = fit_vignetting(images, masks, radii)
    corner = c1 + c2  # log V at rho = 1
    assert abs(corner - sum(TRUE)) < 0.04, (c1, c2)
    assert fit_vignetting(images[:1], masks[:1], radii[:1]) == (0.0, 0.0)  # one frame: nothing to compare


def test_a_vignetted_flight_is_evened_out(tmp_path: Path) -> None:
    flight = make_flight(tmp_path / "frames", n_frames=8, rotation_deg=10, scale_jitter=0.05, gps=True, seed=4)
    for path in flight.paths:  # the same lens on every frame (EXIF kept: only the pixels change)
        from PIL import Image

        with Image.open(path) as im:
            exif = im.info.get("exif", b"")
            pixels = np.asarray(im.convert("RGB")).astype(np.float32)
        Image.fromarray(_vignetted(pixels, TRUE).astype(np.uint8)).save(path, quality=95, exif=exif)
    runs = {}
    for on in (False, True):
        job = tmp_path / f"job-{on}"
        report = process_directory(tmp_path / "frames", job, {"working_max_px": 1024, "vignetting_correction": on})
        assert len(report["frames_used"]) == 8
        runs[on] = ground_colour_error_gain_free(flight, job / "mosaic.tif")
    found = JobWorkspace(tmp_path / "job-True").load_stage_report("compose_mosaic")["vignetting"]
    assert abs(found["c1"] + found["c2"] - sum(TRUE)) < 0.1, found
    assert runs[True] < 0.7 * runs[False], runs


def ground_colour_error_gain_free(flight, path: Path) -> float:
    """``test_pipeline_truth.ground_colour_error`` after the one overall gain that best matches the texture:
    the fall-off darkens every frame on average, and only its unevenness is the mosaic's fault."""
    import rasterio

    with rasterio.open(path) as src:
        rgb = np.moveaxis(src.read(), 0, 2).astype(np.float32)
        mask = src.dataset_mask() > 0
        rows, cols = np.mgrid[0 : src.height, 0 : src.width]
        east, north = rasterio.transform.xy(src.transform, rows.ravel(), cols.ravel())
    tex = np.column_stack([east, north, np.ones(len(east))]) @ np.linalg.inv(flight.texture_to_utm).T
    mx, my = (tex[:, k].reshape(rows.shape).astype(np.float32) for k in (0, 1))
    expected = cv2.remap(flight.texture, mx, my, cv2.INTER_LINEAR)[..., ::-1].astype(np.float32)
    inner = cv2.erode(mask.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    gain = float((rgb[inner] * expected[inner]).sum() / (rgb[inner] ** 2).sum())
    return float(np.abs(gain * rgb - expected)[inner].mean())
