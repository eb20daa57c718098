"""Ground control points of a flight: one file (ODM ``gcp_list.txt`` or OpenSfM
``ground_control_points.json``), checked by parsing it before it replaces the previous one."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from api.errors import InvalidInputError, NotFoundError, TooLargeError
from api.limits import MAX_GCP_BYTES, check_json
from core.db import Database, Flight
from workers.algorithms.sfm import GCP_FILE_NAMES, GroundControlPoint, LocalFrame, gcp_file_name, parse_gcp_file
from workers.workspace import atomic_path, find_gcp_file, flight_folder

CHECK_FRAME = LocalFrame(epsg=32631, easting0=0.0, northing0=0.0)  # positions are not used when checking


def gcp_file(data_dir: Path, flight_id: int) -> Path | None:
    """The flight's GCP file, if it has one."""
    return find_gcp_file(flight_folder(data_dir, flight_id).parent)


def store_gcps(db: Database, data_dir: Path, flight_id: int, filename: str, content: bytes) -> dict[str, Any]:
    """Check and store ``content`` as the flight's GCP file; the previous one stays if it is bad."""
    with db.session() as s:
        flight = s.get(Flight, flight_id)
        if flight is None:
            raise NotFoundError(f"flight {flight_id} not found")
        sizes = {i.filename: (i.width, i.height) for i in flight.images}
    if len(content) > MAX_GCP_BYTES:
        raise TooLargeError(f"{filename}: a GCP file over {MAX_GCP_BYTES} bytes is not a GCP file")
    name = gcp_file_name(filename)
    try:
        text = content.decode("utf-8")
        if name == GCP_FILE_NAMES[1]:  # OpenSfM's JSON: bounded before it is parsed
            check_json(text, filename, MAX_GCP_BYTES)
        gcps = parse_gcp_file(name, text, sizes, CHECK_FRAME)
    except UnicodeDecodeError:
        raise InvalidInputError(f"{filename}: not a UTF-8 text file") from None
    except ValueError as exc:
        raise InvalidInputError(f"{filename}: {exc}") from None
    if not any(g.position is not None for g in gcps):
        raise InvalidInputError(f"{filename}: no ground control point with a known position")
    folder = flight_folder(data_dir, flight_id).parent
    with atomic_path(folder / name) as tmp:
        tmp.write_text(text, encoding="utf-8")
    for other in GCP_FILE_NAMES:
        if other != name:
            (folder / other).unlink(missing_ok=True)
    return gcp_summary(name, gcps, sizes)


def gcp_summary(name: str, gcps: list[GroundControlPoint], sizes: dict[str, tuple[int, int]]) -> dict[str, Any]:
    images = {image for g in gcps for image in g.observations}
    return {
        "file": name,
        "points": len(gcps),
        "with_position": sum(g.position is not None for g in gcps),
        "observations": sum(len(g.observations) for g in gcps),
        "images_not_in_flight": sorted(images - set(sizes)),
    }
