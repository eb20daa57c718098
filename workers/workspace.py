"""Every path of a job in one object, with atomic writers for its artifacts.

Artifacts are JSON, ``.npy``/``.npz`` or GeoTIFF, never pickle. Every writer goes through a temporary
file in the same folder and ``os.replace``, so a reader never sees half an artifact and a stage killed
half-way leaves nothing that looks finished.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from workers.algorithms.gcp import GCP_FILE_NAMES


@contextmanager
def atomic_path(target: Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``target``; it replaces ``target`` only if the block succeeds."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix or target.suffix, dir=target.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, target)
    finally:
        tmp_path.unlink(missing_ok=True)


def write_json(path: Path, data: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, default=_json_default))


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


class JobWorkspace:
    """The folder of one job: inputs, per-stage artifacts, reports and outputs."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    # -- inputs and configuration -------------------------------------------------------------
    def config_file(self) -> Path:
        return self.root / "config.json"

    def inputs_file(self) -> Path:
        """The frames of the job as the API (or ``fotoskhema process``) listed them."""
        return self.root / "inputs.json"

    def load_inputs(self) -> list[dict[str, Any]]:
        return list(read_json(self.inputs_file())["frames"])

    def save_inputs(self, frames: list[dict[str, Any]]) -> None:
        write_json(self.inputs_file(), {"frames": frames})

    def load_config(self) -> dict[str, Any]:
        return dict(read_json(self.config_file()))

    def save_config(self, config: dict[str, Any]) -> None:
        write_json(self.config_file(), config)

    def gcp_dir(self) -> Path:
        """Where the job keeps its copy of its flight's GCP file."""
        return self.root / "gcp"

    def gcp_file(self) -> Path | None:
        """The job's GCP file (``gcp_list.txt`` or ``ground_control_points.json``), if it has one."""
        return find_gcp_file(self.gcp_dir())

    # -- load_images ----------------------------------------------------------------------------
    def frames_file(self) -> Path:
        return self.root / "frames.json"

    def load_frames(self) -> list[dict[str, Any]]:
        return list(read_json(self.frames_file())["frames"])

    def save_frames(self, frames: list[dict[str, Any]], rejected: list[dict[str, Any]]) -> None:
        write_json(self.frames_file(), {"frames": frames, "rejected": rejected})

    def load_composed_frames(self) -> dict[int, dict[str, Any]]:
        """Frames by index as ``compose_mosaic`` sees them: orthorectified frames may be cut to fewer rows."""
        sizes = read_json(self.alignment_file()).get("frame_sizes", {})
        frames = {f["index"]: f for f in self.load_frames()}
        for k, (width, height) in sizes.items():
            frames[int(k)] = {**frames[int(k)], "width": width, "height": height}
        return frames

    def load_rejected_frames(self) -> list[dict[str, Any]]:
        return list(read_json(self.frames_file())["rejected"])

    def working_image_file(self, index: int) -> Path:
        return self.root / "work" / f"frame_{index:04d}.npy"

    def save_working_image(self, index: int, image: np.ndarray) -> None:
        _save_npy(self.working_image_file(index), image)

    def load_working_image(self, index: int, mmap: bool = False) -> np.ndarray:
        """``(H, W, 3) uint8`` BGR; memory-mapped on request, so windows cost only what they read."""
        return _load_npy(self.working_image_file(index), mmap)

    # -- detect_features ------------------------------------------------------------------------
    def features_file(self, index: int) -> Path:
        return self.root / "features" / f"frame_{index:04d}.npz"

    def save_features(self, index: int, points: np.ndarray, descriptors: np.ndarray) -> None:
        _save_npz(self.features_file(index), points=points, descriptors=descriptors)

    def load_features(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        with np.load(self.features_file(index)) as data:
            return data["points"], data["descriptors"]

    # -- match_features -------------------------------------------------------------------------
    def matches_file(self, pair: tuple[int, int]) -> Path:
        return self.root / "matches" / f"pair_{pair[0]:04d}_{pair[1]:04d}.npz"

    def save_matches(self, pair: tuple[int, int], points_i: np.ndarray, points_j: np.ndarray,
                     index_i: np.ndarray | None = None, index_j: np.ndarray | None = None) -> None:
        """Tie points of a pair, and (for tracks) the indices of their features in each frame."""
        indices = {} if index_i is None or index_j is None else {"index_i": index_i, "index_j": index_j}
        _save_npz(self.matches_file(pair), points_i=points_i, points_j=points_j, **indices)

    def load_matches(self, pair: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        with np.load(self.matches_file(pair)) as data:
            return data["points_i"], data["points_j"]

    def load_match_indices(self, pair: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Feature indices ``(M,) int`` of a pair's tie points in frame i and frame j."""
        with np.load(self.matches_file(pair)) as data:
            return data["index_i"], data["index_j"]

    def pairs_file(self) -> Path:
        return self.root / "pairs.json"

    # -- align_frames, georeference -------------------------------------------------------------
    def alignment_file(self) -> Path:
        return self.root / "alignment.json"

    def georef_file(self) -> Path:
        return self.root / "georef.json"

    # -- calibration jobs -----------------------------------------------------------------------
    def corners_file(self) -> Path:
        """Chessboard corners found per photo (``detect_corners``)."""
        return self.root / "corners.json"

    def calibration_file(self) -> Path:
        """The result of a calibration or stereo job: camera/rig JSON, RMS, per-point errors."""
        return self.root / "calibration.json"

    # -- adjust_bundle, orthorectify_frames ------------------------------------------------------
    def cameras_file(self) -> Path:
        """Adjusted cameras, poses and the triangulation report (``adjust_bundle``)."""
        return self.root / "cameras.json"

    def ortho_image_file(self, index: int) -> Path:
        return self.root / "ortho" / f"frame_{index:04d}.npy"

    def save_ortho_image(self, index: int, image: np.ndarray) -> None:
        """``(H, W, 3) uint8`` BGR: the working copy undistorted and cut to the ground it sees."""
        _save_npy(self.ortho_image_file(index), image)

    def load_compose_image(self, index: int, mmap: bool = False) -> np.ndarray:
        """The image ``compose_mosaic`` warps: the undistorted ortho frame if there is one, else the working copy."""
        path = self.ortho_image_file(index)
        return _load_npy(path, mmap) if path.exists() else self.load_working_image(index, mmap)

    # -- crack-survey jobs ------------------------------------------------------------------------
    def orientation_file(self) -> Path:
        """Each photo's pose from its control points and their residuals (``orient_camera``)."""
        return self.root / "orientation.json"

    def specimen_model_file(self, name: str) -> Path:
        """The uploaded mesh of the specimen (see :func:`specimen_model_path`)."""
        return self.root / specimen_model_path(name)

    def surface_file(self) -> Path:
        """The rectification plane and the specimen's heights above it (``rectify_specimen``), ``.npz``."""
        return self.root / "rectified" / "surface.npz"

    def save_surface(self, origin: np.ndarray, axes: np.ndarray, height: np.ndarray, mm_per_px: float) -> None:
        _save_npz(self.surface_file(), origin=origin, axes=axes, height=height, mm_per_px=np.array(mm_per_px))

    def load_surface(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """The rectification plane (origin (3,), axes (3, 3) rows U, V, N), heights (H, W) mm, mm per px."""
        with np.load(self.surface_file()) as data:
            return data["origin"], data["axes"], data["height"], float(data["mm_per_px"])

    def rectified_file(self, stage: int) -> Path:
        """Load stage ``stage``'s photos rectified onto the specimen: image and coverage mask (``.npz``)."""
        return self.root / "rectified" / f"stage_{stage:02d}.npz"

    def save_rectified(self, stage: int, image: np.ndarray, mask: np.ndarray) -> None:
        _save_npz(self.rectified_file(stage), image=image, mask=mask)

    def load_rectified(self, stage: int) -> tuple[np.ndarray, np.ndarray]:
        """``(H, W, 3) uint8`` BGR rectified image and ``(H, W) bool`` mask of what the photos see."""
        with np.load(self.rectified_file(stage)) as data:
            return data["image"], data["mask"]

    def crack_mask_file(self, stage: int) -> Path:
        return self.root / "cracks" / f"stage_{stage:02d}_mask.npy"

    def save_crack_mask(self, stage: int, mask: np.ndarray) -> None:
        _save_npy(self.crack_mask_file(stage), mask)

    def load_crack_mask(self, stage: int) -> np.ndarray:
        """``(H, W) bool`` crack pixels of the rectified image of load stage ``stage``."""
        return _load_npy(self.crack_mask_file(stage))

    def measured_cracks_file(self, stage: int) -> Path:
        """The cracks of load stage ``stage`` measured in mm (``measure_cracks``), JSON."""
        return self.root / "cracks" / f"stage_{stage:02d}.json"

    def comparison_file(self) -> Path:
        """New / grown / unchanged cracks between consecutive load stages (``compare_stages``)."""
        return self.root / "comparison.json"

    def stage_cog_file(self, stage: int) -> Path:
        return self.root / f"stage_{stage:02d}_rectified.tif"

    def stage_overlay_file(self, stage: int) -> Path:
        return self.root / f"stage_{stage:02d}_overlay.png"

    def cracks_geojson_file(self) -> Path:
        return self.root / "cracks.geojson"

    def cracks_csv_file(self) -> Path:
        return self.root / "cracks.csv"

    # -- outputs --------------------------------------------------------------------------------
    def mosaic_file(self) -> Path:
        return self.root / "mosaic.tif"

    def report_file(self) -> Path:
        return self.root / "report.json"

    def footprints_file(self) -> Path:
        return self.root / "footprints.geojson"

    def stage_report_file(self, stage: str) -> Path:
        return self.root / "reports" / f"{stage}.json"

    def save_stage_report(self, stage: str, report: dict[str, Any]) -> None:
        write_json(self.stage_report_file(stage), report)

    def load_stage_report(self, stage: str) -> dict[str, Any] | None:
        path = self.stage_report_file(stage)
        return dict(read_json(path)) if path.exists() else None

    def outputs(self) -> dict[str, Path]:
        """Downloadable outputs that exist, by public name."""
        named = {
            "mosaic.tif": self.mosaic_file(),
            "report.json": self.report_file(),
            "footprints.geojson": self.footprints_file(),
            "calibration.json": self.calibration_file(),
            "cameras.json": self.cameras_file(),
            "cracks.geojson": self.cracks_geojson_file(),
            "cracks.csv": self.cracks_csv_file(),
        }
        for path in sorted([*self.root.glob("stage_*_rectified.tif"), *self.root.glob("stage_*_overlay.png")]):
            named[path.name] = path
        return {name: path for name, path in named.items() if path.exists()}


def _save_npy(path: Path, array: np.ndarray) -> None:
    with atomic_path(path, suffix=".npy") as tmp:
        np.save(tmp, np.ascontiguousarray(array))


def _load_npy(path: Path, mmap: bool = False) -> np.ndarray:
    return np.load(path, mmap_mode="r" if mmap else None)


def _save_npz(path: Path, **arrays: np.ndarray) -> None:
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(tmp, allow_pickle=False, **arrays)


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


def flight_folder(data_dir: Path, flight_id: int) -> Path:
    """Where the photos of flight ``flight_id`` are stored."""
    return Path(data_dir) / "flights" / str(int(flight_id)) / "images"
