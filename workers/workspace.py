"""Every path of a job in one object, with atomic writers for its artifacts.

Artifacts are JSON, ``.npy``/``.npz`` or GeoTIFF, never pickle. Every writer goes through a temporary
file in the same folder and ``os.replace``, so a reader never sees half an artifact and a stage killed
half-way leaves nothing that looks finished.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import numpy as np

from workers.algorithms.sfm import GCP_FILE_NAMES
from workers.gps_file import GPS_FILE_NAMES
from workers.records import Alignment, Coverage, Frame, Georef, PairRecord, RejectedFrame

if TYPE_CHECKING:  # imported where used: the API imports this module and must not load OpenCV
    from workers.algorithms.cracks import Crack
    from workers.algorithms.sfm import GroundSurface
    from workers.algorithms.specimen import Surface


@contextmanager
def atomic_path(target: Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``target``; it replaces ``target`` only if the block succeeds."""
    fd, tmp = _temp_beside(target, suffix)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@contextmanager
def atomic_file(target: Path, suffix: str = "") -> Iterator[BinaryIO]:
    """:func:`atomic_path`'s file, open for writing (binary). The small files a part writes (its record, a pair's
    matches) cost their system calls more than their bytes: each is a point where a part thread waits for the
    interpreter lock while the other threads compute. Opened once and its folder made only when missing, they take
    about half the calls: the 30-frame flight's 290 part records and 202 matches files took its threads 0.56-0.68
    s, now 0.36-0.44, and the whole run 3.82 -> 3.67 s (medians of seven, fresh processes, alternated)."""
    fd, tmp = _temp_beside(target, suffix)
    try:
        with os.fdopen(fd, "wb") as file:
            yield file
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _temp_beside(target: Path, suffix: str) -> tuple[int, str]:
    """A new file ``.<name>.<random><suffix>`` in ``target``'s folder (made when missing): its descriptor, path."""
    prefix, ending = f".{target.name}.", suffix or target.suffix
    try:
        return tempfile.mkstemp(ending, prefix, target.parent)
    except FileNotFoundError:  # the folder's first file
        target.parent.mkdir(parents=True, exist_ok=True)
        return tempfile.mkstemp(ending, prefix, target.parent)


def write_json(path: Path, data: Any) -> None:
    payload = json.dumps(data, indent=2, default=_json_default).encode()
    with atomic_file(path) as file:
        file.write(payload)


def read_json(path: Path) -> Any:
    return json.loads(path.read_text())


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot serialise {type(value).__name__}")


# The JSON and CSV artifacts of a job folder, named once for their readers, writers and ``_stage_outputs``
_CONFIG = "config.json"
_INPUTS = "inputs.json"
_FRAMES = "frames.json"
_PAIRS = "pairs.json"
_ALIGNMENT = "alignment.json"
_GEOREF = "georef.json"
_COVERAGE = "coverage.json"
_SEAMS = "seams.json"  # multiband: the region each frame owns, output px
_CUTLINES = "cutlines.geojson"
_CORNERS = "corners.json"
_CALIBRATION = "calibration.json"
_CAMERAS = "cameras.json"
_TIE_POINTS = "tie_points.npz"
_ORTHO_SURFACE = "ortho_surface.npz"
_ORIENTATION = "orientation.json"
_COMPARISON = "comparison.json"
_REPORT = "report.json"
_REPORT_HTML = "report.html"  # the same report for people: pictures, tables, warnings (write_report)
# the report's pictures, also outputs of their own (the viewer's quality card shows them): name -> what they show
REPORT_FIGURES = {
    "report-overlap.svg": "overlap",
    "report-tie-points.svg": "tie_points",
    "report-positions.svg": "positions",
    "report-residuals.svg": "residuals",
}
_CRACKS_CSV = "cracks.csv"
_MOSAIC = "mosaic.tif"
_FRAME_INDEX = "frame_index.tif"  # which frame each mosaic pixel was taken from: index + 1, 0 = none
_FOOTPRINTS = "footprints.geojson"
_GCP_POINTS = "gcps.geojson"  # the ground control points as the map has them (write_report)
_CRACKS_GEOJSON = "cracks.geojson"
# stereo DEM jobs
_RECTIFICATION = "rectification.json"
_RECTIFIED = "work/rectified.npz"
_DISPARITY_ARRAYS = "work/disparity.npz"
_DISPARITY = "disparity.tif"
_CONFIDENCE = "confidence.tif"
_DEPTH = "depth.tif"
_DSM = "dsm.tif"
_DSM_MASK = "dsm_mask.tif"
_DSM_VIEW = "view/dsm.tif"
_DISPARITY_VIEW = "view/disparity.tif"


_PART_KEY = re.compile(r"[A-Za-z0-9_]{1,64}")  # a part's key names its record file


def _measured_cracks_name(step: int) -> str:
    return f"cracks/stage_{step:02d}.json"


class JobWorkspace:
    """The folder of one job: inputs, per-stage artifacts, reports and outputs.

    Every file a job writes is named here and only here. JSON and array artifacts are read and written through
    ``load_x()`` / ``save_x()``; their paths are private. Rasters that GDAL or a browser open by path (the
    mosaic COG, each load step's COG and overlay) have public ``*_path()`` getters, as the tile routes need.
    """

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def _json(self, name: str) -> Any:
        return read_json(self.root / name)

    def _save_json(self, name: str, data: Any) -> None:
        write_json(self.root / name, data)

    # -- inputs and configuration -------------------------------------------------------------
    def has_config(self) -> bool:
        return (self.root / _CONFIG).exists()

    def load_config(self) -> dict[str, Any]:
        return dict(self._json(_CONFIG))

    def save_config(self, config: dict[str, Any]) -> None:
        self._save_json(_CONFIG, config)

    def load_inputs(self) -> list[dict[str, Any]]:
        """The frames of the job as the API (or ``fotoskhema process``) listed them."""
        return list(self._json(_INPUTS)["frames"])

    def save_inputs(self, frames: list[dict[str, Any]]) -> None:
        self._save_json(_INPUTS, {"frames": frames})

    def input_file(self, relative: str) -> Path:
        """Where the API stores an uploaded input of the job (photos of a photo-owning job), by relative name."""
        return self.root / relative

    def images_dir(self) -> Path:
        """The folder of the photos a photo-owning job (calibration, rig, crack survey) was uploaded with."""
        return self.root / "images"

    def gcp_dir(self) -> Path:
        """Where the job keeps its copy of its flight's GCP file."""
        return self.root / "gcp"

    def gcp_file(self) -> Path | None:
        """The job's GCP file (``gcp_list.txt`` or ``ground_control_points.json``), if it has one."""
        return find_gcp_file(self.gcp_dir())

    # -- load_images ----------------------------------------------------------------------------
    def load_frames(self) -> list[Frame]:
        """The decoded frames, in input order (``load_images``)."""
        return [Frame.from_json(f) for f in self._json(_FRAMES)["frames"]]

    def save_frames(self, frames: list[Frame], rejected: list[RejectedFrame]) -> None:
        self._save_json(_FRAMES, {"frames": [f.to_json() for f in frames], "rejected": [r.to_json() for r in rejected]})

    def load_composed_frames(self) -> dict[int, Frame]:
        """Frames by index as ``compose_mosaic`` sees them: orthorectified frames may be cut to fewer rows."""
        frames = {f.index: f for f in self.load_frames()}
        for k, (width, height) in self.load_alignment().frame_sizes.items():
            frames[k] = frames[k].with_size(width, height)
        return frames

    def load_rejected_frames(self) -> list[RejectedFrame]:
        """The inputs ``load_images`` could not decode."""
        return [RejectedFrame.from_json(r) for r in self._json(_FRAMES)["rejected"]]

    def _working_image_file(self, index: int) -> Path:
        return self.root / "work" / f"frame_{index:04d}.npy"

    def save_working_image(self, index: int, image: np.ndarray) -> None:
        _save_npy(self._working_image_file(index), image)

    def load_working_image(self, index: int, mmap: bool = False) -> np.ndarray:
        """``(H, W, 3) uint8`` BGR; memory-mapped on request, so windows cost only what they read."""
        return load_npy(self._working_image_file(index), mmap)

    # -- detect_features ------------------------------------------------------------------------
    def _features_file(self, index: int) -> Path:
        return self.root / "features" / f"frame_{index:04d}.npz"

    def save_features(self, index: int, points: np.ndarray, descriptors: np.ndarray) -> None:
        save_npz(self._features_file(index), points=points, descriptors=descriptors)

    def load_features(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        with load_npz(self._features_file(index)) as data:
            return data["points"], data["descriptors"]

    def save_tie_corners(self, index: int, corners: np.ndarray) -> None:
        """(N, 2) float32 pixel (x, y) corners of a working copy where planar tie points are correlated."""
        save_npz(self._tie_corners_file(index), corners=corners)

    def tie_corners_exist(self, index: int) -> bool:
        return self._tie_corners_file(index).exists()

    def load_tie_corners(self, index: int) -> np.ndarray:
        with load_npz(self._tie_corners_file(index)) as data:
            return np.asarray(data["corners"])

    def _tie_corners_file(self, index: int) -> Path:
        return self.root / "features" / f"corners_{index:04d}.npz"

    # -- match_features -------------------------------------------------------------------------
    def _matches_file(self, pair: tuple[int, int]) -> Path:
        return self.root / "matches" / f"pair_{pair[0]:04d}_{pair[1]:04d}.npz"

    def save_matches(
        self,
        pair: tuple[int, int],
        points_i: np.ndarray,
        points_j: np.ndarray,
        index_i: np.ndarray | None = None,
        index_j: np.ndarray | None = None,
    ) -> None:
        """Tie points of a pair, and (for tracks) the indices of their features in each frame."""
        indices = {} if index_i is None or index_j is None else {"index_i": index_i, "index_j": index_j}
        save_npz(self._matches_file(pair), points_i=points_i, points_j=points_j, **indices)

    def load_matches(self, pair: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        with load_npz(self._matches_file(pair)) as data:
            return data["points_i"], data["points_j"]

    def load_match_indices(self, pair: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Feature indices ``(M,) int`` of a pair's tie points in frame i and frame j."""
        with load_npz(self._matches_file(pair)) as data:
            return data["index_i"], data["index_j"]

    def load_pairs(self) -> list[PairRecord]:
        """Every pair ``match_features`` tried: frames, matches, inliers, model, whether it was accepted."""
        return [PairRecord.from_json(p) for p in self._json(_PAIRS)["pairs"]]

    def save_pairs(self, pairs: list[PairRecord]) -> None:
        self._save_json(_PAIRS, {"pairs": [p.to_json() for p in pairs]})

    # -- align_frames / orthorectify_frames, georeference, compose_mosaic -------------------------
    def load_alignment(self) -> Alignment:
        """Frame -> plane homographies, rejected frames and tie-point residuals (``align_frames``)."""
        return Alignment.from_json(self._json(_ALIGNMENT))

    def save_alignment(self, alignment: Alignment) -> None:
        self._save_json(_ALIGNMENT, alignment.to_json())

    def load_georef(self) -> Georef:
        """The output grid: output pixel -> plane homography, size, CRS and pixel size (``georeference``)."""
        return Georef.from_json(self._json(_GEOREF))

    def save_georef(self, georef: Georef) -> None:
        self._save_json(_GEOREF, georef.to_json())

    def load_coverage(self) -> Coverage:
        """The mosaic's outline in output pixels and the share of the grid it covers (``compose_mosaic``)."""
        return Coverage.from_json(self._json(_COVERAGE))

    def save_coverage(self, coverage: Coverage) -> None:
        self._save_json(_COVERAGE, coverage.to_json())

    def save_seams(self, owned: dict[int, list[np.ndarray]]) -> None:
        """Frame -> rings (N, 2) of the region it owns in a multiband mosaic, output px."""
        self._save_json(_SEAMS, {str(k): [r.tolist() for r in rings] for k, rings in owned.items()})

    def load_seams(self) -> dict[int, list[np.ndarray]] | None:
        """What ``save_seams`` saved, or None for a mosaic without seams (feathered)."""
        if not (self.root / _SEAMS).exists():
            return None
        return {int(k): [np.array(r, np.float64) for r in rings] for k, rings in self._json(_SEAMS).items()}

    def remove_seams(self) -> None:
        (self.root / _SEAMS).unlink(missing_ok=True)
        (self.root / _CUTLINES).unlink(missing_ok=True)

    def save_cutlines(self, collection: dict[str, Any]) -> None:
        self._save_json(_CUTLINES, collection)

    def _native_image_file(self, index: int) -> Path:
        return self.root / "native" / f"frame_{index:04d}.npy"

    def save_native_image(self, index: int, image: np.ndarray) -> None:
        """``(H, W, 3) uint8`` BGR: the whole photo, for a mosaic at its own resolution (scratch)."""
        _save_npy(self._native_image_file(index), image)

    def native_image_exists(self, index: int) -> bool:
        return self._native_image_file(index).exists()

    def load_native_image(self, index: int, mmap: bool = False) -> np.ndarray:
        return load_npy(self._native_image_file(index), mmap)

    def native_image_windows(self, index: int) -> NpyWindows:
        """The full photo :meth:`save_native_image` kept, read by window (:class:`NpyWindows`)."""
        return NpyWindows(self._native_image_file(index))

    def remove_native_images(self) -> None:
        """Drop the full photos ``compose_mosaic`` decoded: the job's inputs keep them, at a tenth of the size."""
        shutil.rmtree(self.root / "native", ignore_errors=True)

    def mosaic_scratch_path(self) -> Path:
        """What ``compose_mosaic``'s scratch files for ``mosaic.tif`` are named after (its overviews' tile rows,
        its header: ``workers.cog_writer``)."""
        return self.root / "mosaic.tmp.tif"

    def frame_index_scratch_path(self) -> Path:
        """What the scratch files for ``frame_index.tif`` are named after, as :meth:`mosaic_scratch_path`."""
        return self.root / "frame_index.tmp.tif"

    # -- calibration jobs -----------------------------------------------------------------------
    def load_corners(self) -> dict[str, Any]:
        """Chessboard corners found per photo (``detect_corners``)."""
        return dict(self._json(_CORNERS))

    def save_corners(self, corners: dict[str, Any]) -> None:
        self._save_json(_CORNERS, corners)

    def has_calibration(self) -> bool:
        return (self.root / _CALIBRATION).exists()

    def load_calibration(self) -> dict[str, Any]:
        """The result of a calibration or stereo job: camera/rig JSON, RMS, per-point errors."""
        return dict(self._json(_CALIBRATION))

    def save_calibration(self, calibration: dict[str, Any]) -> None:
        self._save_json(_CALIBRATION, calibration)

    # -- adjust_bundle, orthorectify_frames ------------------------------------------------------
    def load_cameras(self) -> dict[str, Any]:
        """Adjusted cameras, poses and the triangulation report (``adjust_bundle``)."""
        return dict(self._json(_CAMERAS))

    def save_cameras(self, cameras: dict[str, Any]) -> None:
        self._save_json(_CAMERAS, cameras)

    def save_tie_points(self, points: np.ndarray) -> None:
        """The adjusted tie points, (N, 3) float64 in the job's world frame (``adjust_bundle``)."""
        save_npz(self.root / _TIE_POINTS, points=np.asarray(points, np.float64).reshape(-1, 3))

    def load_tie_points(self) -> np.ndarray:
        """(N, 3) float64 world points ``adjust_bundle`` saved."""
        with load_npz(self.root / _TIE_POINTS) as data:
            return np.asarray(data["points"])

    def save_ortho_surface(self, surface: GroundSurface | None) -> None:
        """The surface ``orthorectify_frames`` projected onto; None removes it (the frames went onto a plane)."""
        path = self.root / _ORTHO_SURFACE
        if surface is None:
            path.unlink(missing_ok=True)
            return
        origin = np.array([surface.x0, surface.y0, surface.cell])
        save_npz(path, heights=surface.heights, origin=origin)

    def load_ortho_surface(self) -> GroundSurface | None:
        """The surface ``save_ortho_surface`` kept, or None."""
        from workers.algorithms.sfm import GroundSurface  # SciPy: loaded only here

        path = self.root / _ORTHO_SURFACE
        if not path.exists():
            return None
        with load_npz(path) as data:
            x0, y0, cell = (float(v) for v in data["origin"])
            return GroundSurface(np.asarray(data["heights"]), x0, y0, cell)

    def _ortho_image_file(self, index: int) -> Path:
        return self.root / "ortho" / f"frame_{index:04d}.npy"

    def save_ortho_image(self, index: int, image: np.ndarray) -> None:
        """``(H, W, 3) uint8`` BGR: the working copy undistorted and cut to the ground it sees."""
        _save_npy(self._ortho_image_file(index), image)

    def load_compose_image(self, index: int, mmap: bool = False) -> np.ndarray:
        """The image ``compose_mosaic`` warps: the undistorted ortho frame if there is one, else the working copy."""
        return load_npy(self._compose_image_file(index), mmap)

    def compose_image_windows(self, index: int) -> NpyWindows:
        """:meth:`load_compose_image`'s image, read by window (:class:`NpyWindows`)."""
        return NpyWindows(self._compose_image_file(index))

    def _compose_image_file(self, index: int) -> Path:
        path = self._ortho_image_file(index)
        return path if path.exists() else self._working_image_file(index)

    # -- crack-survey jobs ------------------------------------------------------------------------
    def load_orientation(self) -> list[dict[str, Any]]:
        """Each photo's pose from its control points and their residuals (``orient_camera``)."""
        return list(self._json(_ORIENTATION)["photos"])

    def save_orientation(self, photos: list[dict[str, Any]]) -> None:
        self._save_json(_ORIENTATION, {"photos": photos})

    def specimen_model_file(self, name: str) -> Path:
        """The uploaded mesh of the specimen (see :func:`specimen_model_path`)."""
        return self.root / specimen_model_path(name)

    def _surface_file(self) -> Path:
        return self.root / "rectified" / "surface.npz"

    def save_surface(self, surface: Surface) -> None:
        """The rectification plane and the specimen's heights above it (``rectify_specimen``), without the mesh."""
        plane = surface.frame
        save_npz(
            self._surface_file(),
            origin=plane.origin,
            axes=plane.axes,
            height=surface.height,
            mm_per_px=np.array(surface.mm_per_px),
        )

    def load_surface(self) -> Surface:
        """The surface ``rectify_specimen`` wrote: heights and plane are all later stages need."""
        from workers.algorithms.specimen import PlaneFrame, Surface

        with load_npz(self._surface_file()) as data:
            return Surface(PlaneFrame(data["origin"], data["axes"]), data["height"], float(data["mm_per_px"]))

    def _rectified_file(self, step: int) -> Path:
        return self.root / "rectified" / f"stage_{step:02d}.npz"

    def save_rectified(
        self, step: int, image: np.ndarray, mask: np.ndarray, footprint: tuple[np.ndarray, float] | None = None
    ) -> None:
        """Load step ``step``'s photos rectified onto the specimen: image and coverage mask, and the photos'
        pixel footprint on a coarse raster of the plane with its mm per px (``specimen.photo_footprint``)."""
        extra = {} if footprint is None else {"footprint": footprint[0], "footprint_mm_per_px": np.array(footprint[1])}
        save_npz(self._rectified_file(step), image=image, mask=mask, **extra)

    def load_photo_footprint(self, step: int) -> tuple[np.ndarray, float] | None:
        """``(h, w, 3) float32`` photo pixel footprint of load step ``step`` and its raster's mm per px (None
        when ``rectify_specimen`` wrote none)."""
        with load_npz(self._rectified_file(step)) as data:
            if "footprint" not in data:
                return None
            return data["footprint"], float(data["footprint_mm_per_px"])

    def load_rectified(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        """``(H, W, 3) uint8`` BGR rectified image and ``(H, W) bool`` mask of what the photos see."""
        with load_npz(self._rectified_file(step)) as data:
            return data["image"], data["mask"]

    def _crack_mask_file(self, step: int) -> Path:
        return self.root / "cracks" / f"stage_{step:02d}_mask.npy"

    def save_crack_mask(self, step: int, mask: np.ndarray) -> None:
        _save_npy(self._crack_mask_file(step), mask)

    def load_crack_mask(self, step: int) -> np.ndarray:
        """``(H, W) bool`` crack pixels of the rectified image of load step ``step``."""
        return load_npy(self._crack_mask_file(step))

    def save_measured_cracks(self, step: int, cracks: list[Crack], summary: dict[str, Any]) -> None:
        """The cracks of load step ``step`` measured in mm (``measure_cracks``) and their totals."""
        self._save_json(_measured_cracks_name(step), {"cracks": [crack_to_json(c) for c in cracks], "summary": summary})

    def load_measured_cracks(self, step: int) -> tuple[list[Crack], dict[str, Any]]:
        data = self._json(_measured_cracks_name(step))
        return [crack_from_json(c) for c in data["cracks"]], dict(data["summary"])

    def load_comparison(self) -> list[dict[str, Any]]:
        """New / grown / unchanged cracks between consecutive load steps (``compare_stages``)."""
        return list(self._json(_COMPARISON)["pairs"])

    def save_comparison(self, pairs: list[dict[str, Any]]) -> None:
        self._save_json(_COMPARISON, {"pairs": pairs})

    def load_step_cog_path(self, step: int) -> Path:
        """Load step ``step``'s rectified specimen as a COG (an output, read by the tile routes)."""
        return self.root / f"stage_{step:02d}_rectified.tif"

    def load_step_scratch_path(self, step: int) -> Path:
        return self.root / f"stage_{step:02d}.tmp.tif"

    def load_step_overlay_path(self, step: int) -> Path:
        """Load step ``step``'s rectified specimen with its cracks drawn, PNG (an output)."""
        return self.root / f"stage_{step:02d}_overlay.png"

    def save_cracks_geojson(self, collection: dict[str, Any]) -> None:
        self._save_json(_CRACKS_GEOJSON, collection)

    def save_cracks_csv(self, text: str) -> None:
        with atomic_path(self.root / _CRACKS_CSV) as tmp:
            tmp.write_text(text)

    # -- stereo DEM jobs ---------------------------------------------------------------------------
    def load_rectification(self) -> dict[str, Any]:
        """How the pair was rectified, its disparity range and geometry (``rectify_pair``)."""
        return dict(self._json(_RECTIFICATION))

    def save_rectification(self, rectification: dict[str, Any]) -> None:
        self._save_json(_RECTIFICATION, rectification)

    def save_rectified_pair(
        self, left: np.ndarray, right: np.ndarray, valid_left: np.ndarray, valid_right: np.ndarray
    ) -> None:
        """The rectified pair, uint8 (H, W) or (H, W, 3), and the (H, W) bool pixels each photo covers."""
        save_npz(self.root / _RECTIFIED, left=left, right=right, valid_left=valid_left, valid_right=valid_right)

    def load_rectified_pair(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(left, right, valid_left, valid_right)`` as ``save_rectified_pair`` saved them."""
        with load_npz(self.root / _RECTIFIED) as data:
            return data["left"], data["right"], data["valid_left"], data["valid_right"]

    def save_disparity_arrays(
        self, disparity: np.ndarray, dense: np.ndarray, filled: np.ndarray, confidence: np.ndarray
    ) -> None:
        """The matcher's maps (``disparity.Disparity``'s fields), left rectified view, px."""
        save_npz(self.root / _DISPARITY_ARRAYS, disparity=disparity, dense=dense, filled=filled, confidence=confidence)

    def load_disparity_arrays(self) -> dict[str, np.ndarray]:
        """``disparity``, ``dense``, ``filled``, ``confidence`` (H, W) as ``save_disparity_arrays`` saved them."""
        with load_npz(self.root / _DISPARITY_ARRAYS) as data:
            return {name: data[name] for name in ("disparity", "dense", "filled", "confidence")}

    def disparity_path(self) -> Path:
        """The left view's disparity, float32 px, NaN where none (an output)."""
        return self.root / _DISPARITY

    def confidence_path(self) -> Path:
        """Per pixel of ``disparity.tif`` how far it is trusted, 0 where filled or none (an output)."""
        return self.root / _CONFIDENCE

    def depth_path(self) -> Path:
        """A rig pair's depth in the rectified left camera, the rig's units (an output)."""
        return self.root / _DEPTH

    def dsm_path(self) -> Path:
        """The DSM COG, float32 metres (an output, read by the point route)."""
        return self.root / _DSM

    def dsm_mask_path(self) -> Path:
        """Per DSM cell: 0 no data, 1 measured, 2 filled (an output)."""
        return self.root / _DSM_MASK

    def dsm_view_path(self) -> Path:
        """The DSM as colour-ramped, hillshaded RGB COG (read by the tile routes)."""
        return self.root / _DSM_VIEW

    def remove_dsm(self) -> None:
        """Remove the DSM's files (an ortho job run again onto the plane has none)."""
        for path in (self.dsm_path(), self.dsm_mask_path(), self.dsm_view_path()):
            path.unlink(missing_ok=True)

    def disparity_view_path(self) -> Path:
        """The disparity as colour-ramped RGB COG in the left view's pixels (read by the tile routes)."""
        return self.root / _DISPARITY_VIEW

    def view_scratch_path(self, name: str) -> Path:
        """Scratch GeoTIFF of a view COG before it is translated (``name``: "dsm" or "disparity")."""
        return self.root / "view" / f"{name}.tmp.tif"

    # -- outputs --------------------------------------------------------------------------------
    def mosaic_path(self) -> Path:
        """The mosaic COG (an output, read by the tile routes)."""
        return self.root / _MOSAIC

    def frame_index_path(self) -> Path:
        """COG (uint16) of the frame each mosaic pixel was taken from: its index + 1 (footprints' ``index``), 0 =
        none (an output)."""
        return self.root / _FRAME_INDEX

    def save_report_html(self, html: str, figures: dict[str, str]) -> None:
        """``report.html`` and its pictures (``REPORT_FIGURES`` name -> SVG text); a picture not given is removed."""
        for name in REPORT_FIGURES:
            if name in figures:
                with atomic_path(self.root / name) as tmp:
                    tmp.write_text(figures[name], encoding="utf-8")
            else:
                (self.root / name).unlink(missing_ok=True)
        with atomic_path(self.root / _REPORT_HTML) as tmp:
            tmp.write_text(html, encoding="utf-8")

    def has_report(self) -> bool:
        return (self.root / _REPORT).exists()

    def load_report(self) -> dict[str, Any]:
        return dict(self._json(_REPORT))

    def save_report(self, report: dict[str, Any]) -> None:
        self._save_json(_REPORT, report)

    def load_footprints(self) -> dict[str, Any]:
        return dict(self._json(_FOOTPRINTS))

    def save_footprints(self, collection: dict[str, Any]) -> None:
        self._save_json(_FOOTPRINTS, collection)

    def load_gcp_points(self) -> dict[str, Any]:
        return dict(self._json(_GCP_POINTS))

    def save_gcp_points(self, collection: dict[str, Any]) -> None:
        self._save_json(_GCP_POINTS, collection)

    def _stage_report_file(self, stage: str) -> Path:
        return self.root / "reports" / f"{stage}.json"

    def save_stage_report(self, stage: str, report: dict[str, Any]) -> None:
        write_json(self._stage_report_file(stage), report)

    def load_stage_report(self, stage: str) -> dict[str, Any] | None:
        path = self._stage_report_file(stage)
        return dict(read_json(path)) if path.exists() else None

    def stage_outputs_present(self, stage: str) -> bool:
        """Whether every file pipeline stage ``stage`` writes is still there: a finished stage whose files were
        lost (a cleaned scratch disk, a restored backup), or whose inputs naming them cannot be read, runs again
        instead of being skipped."""
        try:
            return all(path.exists() for path in self._stage_outputs(stage))
        except (OSError, ValueError, KeyError, TypeError):  # a lost or corrupt frames.json, config, ...
            return False

    def _stage_outputs(self, stage: str) -> list[Path]:
        """The files ``stage`` writes; per-frame, per-pair and per-load-step files as the artifacts that list
        those frames, pairs and load steps say."""
        r = self.root

        def frames() -> list[int]:
            return [f.index for f in self.load_frames()]

        def steps() -> range:
            return range(len(self.load_config().get("stages", [])))

        outputs = {
            "load_images": lambda: [r / _FRAMES, *(self._working_image_file(k) for k in frames())],
            "detect_features": lambda: [self._features_file(k) for k in frames()],
            "match_features": lambda: [
                r / _PAIRS,
                *(self._matches_file(p.pair) for p in self.load_pairs() if p.accepted),
            ],
            "measure_ties": lambda: [
                r / _PAIRS,
                *(self._matches_file(p.pair) for p in self.load_pairs() if p.accepted),
            ],
            "match_strips": lambda: [
                r / _PAIRS,
                *(self._matches_file(p.pair) for p in self.load_pairs() if p.accepted),
            ],
            "align_frames": lambda: [r / _ALIGNMENT],
            "georeference": lambda: [r / _GEOREF],
            "adjust_bundle": lambda: [r / _CAMERAS, r / _TIE_POINTS],
            "orthorectify_frames": lambda: [
                r / _GEOREF,
                *(self._ortho_image_file(k) for k in self.load_alignment().homographies),
                *self._ortho_dsm_outputs(),
            ],
            "compose_mosaic": lambda: [r / _COVERAGE, self.mosaic_path(), r / _FRAME_INDEX],
            "write_report": lambda: [r / _REPORT, r / _REPORT_HTML],
            "detect_corners": lambda: [r / _CORNERS],
            "calibrate_camera": lambda: [r / _CALIBRATION],
            "fit_plumb_line": lambda: [r / _CALIBRATION],
            "calibrate_stereo": lambda: [r / _CALIBRATION],
            "orient_camera": lambda: [r / _ORIENTATION],
            "rectify_specimen": lambda: [self._surface_file(), *(self._rectified_file(s) for s in steps())],
            "detect_cracks": lambda: [self._crack_mask_file(s) for s in steps()],
            "measure_cracks": lambda: [r / _measured_cracks_name(s) for s in steps()],
            "compare_stages": lambda: [r / _COMPARISON],
            "write_crack_report": lambda: [
                r / _REPORT,
                r / _CRACKS_CSV,
                *(self.load_step_cog_path(s) for s in steps()),
            ],
            "rectify_pair": lambda: [r / _RECTIFICATION, r / _RECTIFIED],
            "compute_disparity": lambda: [r / _DISPARITY_ARRAYS, r / _DISPARITY, r / _CONFIDENCE, r / _DISPARITY_VIEW],
            "build_dsm": lambda: self._surface_outputs(),
            "write_stereo_report": lambda: [r / _REPORT],
        }
        listed = outputs.get(stage)
        return listed() if listed is not None else []

    # -- a stage done in parts (workers.pipeline.run_parted; spread over workers by workers.tasks) ---------------
    def _parts_dir(self, stage: str) -> Path:
        return self.root / "parts" / stage

    def save_plan(self, stage: str, keys: list[str], started: float) -> None:
        """The keys of ``stage``'s parts, in the order its ``finish`` reads them, and when the stage started
        (epoch seconds: its wall time runs across the processes that do its parts)."""
        write_json(self._parts_dir(stage) / "plan.json", {"keys": keys, "started": started})

    def load_plan(self, stage: str) -> list[str]:
        return [str(k) for k in read_json(self._parts_dir(stage) / "plan.json")["keys"]]

    def plan_started(self, stage: str) -> float:
        return float(read_json(self._parts_dir(stage) / "plan.json")["started"])

    def save_part_inputs(self, stage: str, inputs: dict[str, Any]) -> None:
        """What ``stage``'s plan worked out for its parts (JSON), written before the plan."""
        write_json(self._parts_dir(stage) / "inputs.json", inputs)

    def load_part_inputs(self, stage: str) -> dict[str, Any]:
        return dict(read_json(self._parts_dir(stage) / "inputs.json"))

    def save_part_arrays(self, stage: str, **arrays: np.ndarray) -> None:
        """Arrays ``stage``'s plan worked out for its parts (a multiband mosaic's seam labels)."""
        save_npz(self._parts_dir(stage) / "arrays.npz", **arrays)

    def load_part_arrays(self, stage: str) -> dict[str, np.ndarray]:
        with load_npz(self._parts_dir(stage) / "arrays.npz") as data:
            return {name: data[name] for name in data.files}

    def compose_band_path(self, y: int) -> Path:
        """A band of mosaic rows from ``y`` that one part of ``compose_mosaic`` wrote (scratch): a GeoTIFF of the
        COG's own tiles."""
        return self._parts_dir("compose_mosaic") / f"band_{y:07d}.tif"

    def index_band_path(self, y: int) -> Path:
        """The frame index of the band of rows from ``y`` (uint16 GeoTIFF of the COG's tiles; scratch), beside its
        pixels."""
        return self._parts_dir("compose_mosaic") / f"index_{y:07d}.tif"

    def part_inputs_version(self, stage: str) -> int:
        """Changes whenever ``save_part_inputs`` writes again (its file's modification time, ns)."""
        return (self._parts_dir(stage) / "inputs.json").stat().st_mtime_ns

    def save_part(self, stage: str, key: str, record: dict[str, Any]) -> None:
        """One finished part's record: written last, after the part's own files, so it marks the part done."""
        if not _PART_KEY.fullmatch(key):
            raise ValueError(f"part key {key!r} is not a plain name")
        write_json(self._parts_dir(stage) / f"part_{key}.json", record)

    def load_part(self, stage: str, key: str) -> dict[str, Any]:
        return dict(read_json(self._parts_dir(stage) / f"part_{key}.json"))

    def parts_done(self, stage: str) -> set[str]:
        folder = self._parts_dir(stage)
        return {p.stem.removeprefix("part_") for p in folder.glob("part_*.json")} if folder.is_dir() else set()

    def remove_parts(self, stage: str) -> None:
        shutil.rmtree(self._parts_dir(stage), ignore_errors=True)

    def _ortho_dsm_outputs(self) -> list[Path]:
        """An ortho job's DSM files: written when it kept a surface and has map coordinates."""
        if not (self.root / _ORTHO_SURFACE).exists() or not self.load_georef().georeferenced:
            return []
        return [self.dsm_path(), self.dsm_mask_path(), self.dsm_view_path()]

    def _surface_outputs(self) -> list[Path]:
        """What ``build_dsm`` writes for the pair's geometry: a DSM (rpc), a depth map (rig) or nothing more."""
        geometry = self.load_rectification()["geometry"]
        if geometry == "rpc":
            return [self.dsm_path(), self.dsm_mask_path(), self.dsm_view_path()]
        if geometry == "rig":
            return [self.depth_path()]
        return [self.root / _RECTIFICATION]

    def forget_stage_report(self, stage: str) -> None:
        """Make pipeline stage ``stage`` run again on the next delivery (its report marks it done)."""
        self._stage_report_file(stage).unlink(missing_ok=True)

    def outputs(self) -> dict[str, Path]:
        """Downloadable outputs that exist, by public name."""
        names = [
            _MOSAIC,
            _FRAME_INDEX,
            _DSM,
            _REPORT,
            _REPORT_HTML,
            *REPORT_FIGURES,
            _FOOTPRINTS,
            _CUTLINES,
            _GCP_POINTS,
            _CALIBRATION,
            _CAMERAS,
            _CRACKS_GEOJSON,
            _CRACKS_CSV,
            _DSM_MASK,
            _DISPARITY,
            _CONFIDENCE,
            _DEPTH,
        ]
        named = {name: self.root / name for name in names}
        for path in sorted([*self.root.glob("stage_*_rectified.tif"), *self.root.glob("stage_*_overlay.png")]):
            named[path.name] = path
        return {name: path for name, path in named.items() if path.exists()}


def crack_to_json(crack: Crack) -> dict[str, Any]:
    return {
        "paths_mm": [p.tolist() for p in crack.paths_mm],
        "length_mm": crack.length_mm,
        "mean_width_mm": crack.mean_width_mm,
        "max_width_mm": crack.max_width_mm,
        "orientation_deg": crack.orientation_deg,
        "endpoints_mm": crack.endpoints_mm.tolist(),
        "bbox_mm": list(crack.bbox_mm),
        "photo_mm_per_px": crack.photo_mm_per_px,
    }


def crack_from_json(data: dict[str, Any]) -> Crack:
    from workers.algorithms.cracks import Crack

    return Crack(
        paths_mm=tuple(np.array(p, dtype=np.float64).reshape(-1, 2) for p in data["paths_mm"]),
        length_mm=float(data["length_mm"]),
        mean_width_mm=float(data["mean_width_mm"]),
        max_width_mm=float(data["max_width_mm"]),
        orientation_deg=float(data["orientation_deg"]),
        endpoints_mm=np.array(data["endpoints_mm"], dtype=np.float64).reshape(-1, 2),
        bbox_mm=(
            float(data["bbox_mm"][0]),
            float(data["bbox_mm"][1]),
            float(data["bbox_mm"][2]),
            float(data["bbox_mm"][3]),
        ),
        photo_mm_per_px=None if data.get("photo_mm_per_px") is None else float(data["photo_mm_per_px"]),
    )


def _save_npy(path: Path, array: np.ndarray) -> None:
    with atomic_file(path, suffix=".npy") as file:
        np.save(file, np.ascontiguousarray(array))


# CPython 3.11's AST constructor counts its recursion depth per interpreter, not per thread, and np.load parses every
# .npy header (a .npz's members too) with ast.literal_eval: two threads loading at once can fail with "SystemError:
# AST constructor recursion depth mismatch" (python/cpython#106905; seen once in CI, composing on two threads).
# Every load of the job's arrays holds this lock: headers are a few dozen bytes, and the arrays read are small or
# memory-mapped.
NPY_LOCK = threading.RLock()


def load_npy(path: Path, mmap: bool = False) -> np.ndarray:
    """``np.load`` of a ``.npy`` under :data:`NPY_LOCK` (memory-mapped, read-only, with ``mmap``)."""
    with NPY_LOCK:
        return np.load(path, mmap_mode="r" if mmap else None)


class NpyWindows:
    """Windows of an (H, W, C) ``.npy`` image, ``reader[r0:r1, c0:c1]`` -> a copy, read from the file by rows
    (``os.pread``, safe across threads): nothing of the file stays mapped. A memory map keeps every page it has
    touched in the process's resident set while it is open: composing the Brighton strip, its working copies' rows
    held 27 MiB of the job's peak that way (compose's bands 324 -> 271 MiB; the same seconds). ``shape`` as the
    array's."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        with NPY_LOCK, open(self.path, "rb") as f:  # the header is parsed by ast.literal_eval (see NPY_LOCK)
            version = np.lib.format.read_magic(f)
            if version not in ((1, 0), (2, 0)):
                raise ValueError(f"{self.path.name}: .npy format {version} (np.save writes 1.0 or 2.0)")
            read_header = (
                np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            )
            shape, fortran, dtype = read_header(f)
            self._offset = f.tell()
        if fortran or len(shape) != 3:
            raise ValueError(f"{self.path.name}: not a C-ordered (H, W, C) image")
        self.shape, self.dtype = tuple(shape), np.dtype(dtype)
        self._row_bytes = shape[1] * shape[2] * self.dtype.itemsize

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        rows, cols = key
        r0, r1, _ = rows.indices(self.shape[0])
        c0, c1, _ = cols.indices(self.shape[1])
        if r1 <= r0 or c1 <= c0:
            return np.empty((max(r1 - r0, 0), max(c1 - c0, 0), self.shape[2]), self.dtype)
        fd = os.open(self.path, os.O_RDONLY)
        try:
            data = os.pread(fd, (r1 - r0) * self._row_bytes, self._offset + r0 * self._row_bytes)
        finally:
            os.close(fd)
        if len(data) != (r1 - r0) * self._row_bytes:
            raise ValueError(f"{self.path.name} is shorter than its header says")
        block = np.frombuffer(data, self.dtype).reshape(r1 - r0, self.shape[1], self.shape[2])
        return block if (c0, c1) == (0, self.shape[1]) else np.ascontiguousarray(block[:, c0:c1])


@contextmanager
def load_npz(path: Path) -> Iterator[Any]:
    """``np.load`` of a ``.npz``, held under :data:`NPY_LOCK` while its members are read."""
    with NPY_LOCK, np.load(path) as data:
        yield data


def save_npz(path: Path, **arrays: np.ndarray) -> None:
    """``np.savez`` of ``arrays`` (no pickles) into ``path``, atomically (:func:`atomic_file`)."""
    with atomic_file(path, suffix=".npz") as file:
        np.savez(file, allow_pickle=False, **arrays)


ProgressFn = Callable[[float, str], None]
"""``progress(fraction_of_stage in [0, 1], detail such as "frame 4/12")``."""


def specimen_model_path(name: str) -> Path:
    """Where a job keeps its specimen's mesh, relative to its folder: a fixed name with the upload's suffix
    (the API writes it there before the job's folder exists as a workspace)."""
    return Path("specimen") / f"model{Path(name).suffix.lower()}"


def noop_progress(_fraction: float, _detail: str) -> None:
    return None


def job_workspace(data_dir: Path, job_id: int) -> JobWorkspace:
    """Where the job ``job_id`` keeps its files under the service's data folder."""
    return JobWorkspace(Path(data_dir) / "jobs" / str(int(job_id)))


def find_gcp_file(folder: Path) -> Path | None:
    """The GCP file in ``folder`` (ODM's or OpenSfM's name), if there is one."""
    return next((folder / n for n in GCP_FILE_NAMES if (folder / n).exists()), None)


def find_gps_file(folder: Path) -> Path | None:
    """The GPS side file in ``folder`` (ODM's ``geo.txt`` or the CSV's name), if there is one."""
    return next((folder / n for n in GPS_FILE_NAMES if (folder / n).exists()), None)


def flight_folder(data_dir: Path, flight_id: int) -> Path:
    """Where the photos of flight ``flight_id`` are stored."""
    return Path(data_dir) / "flights" / str(int(flight_id)) / "images"


def flight_uploads_folder(data_dir: Path, flight_id: int) -> Path:
    """Where the part files of a flight's unfinished resumable uploads are (same file system as its photos)."""
    return Path(data_dir) / "flights" / str(int(flight_id)) / "uploads"


def flight_upload_path(data_dir: Path, flight_id: int, upload_id: str) -> Path:
    """The part file of resumable upload ``upload_id`` (hex) of flight ``flight_id``."""
    if not upload_id.isalnum():
        raise ValueError(f"not an upload id: {upload_id!r}")
    return flight_uploads_folder(data_dir, flight_id) / f"{upload_id}.part"
