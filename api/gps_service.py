"""GPS side file of a flight: ODM's ``geo.txt`` or a CSV ``name,lat,lon,alt[,accuracy]``, checked by parsing
it before it replaces the previous one. A job of the flight takes the position of every photo named in it from
the file instead of the photo's EXIF tags."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from api.errors import InvalidInputError, NotFoundError, TooLargeError
from api.limits import MAX_GPS_BYTES
from core.db import Database, Flight
from workers.gps_file import GPS_FILE_NAMES, GpsFile, GpsFix, gps_file_name, parse_gps_file
from workers.workspace import atomic_path, find_gps_file, flight_folder


def gps_file(data_dir: Path, flight_id: int) -> Path | None:
    """The flight's GPS side file, if it has one."""
    return find_gps_file(flight_folder(data_dir, flight_id).parent)


def store_gps(db: Database, data_dir: Path, flight_id: int, filename: str, content: bytes) -> dict[str, Any]:
    """Check and store ``content`` as the flight's GPS side file; the previous one stays if it is bad."""
    with db.session() as s:
        flight = s.get(Flight, flight_id)
        if flight is None:
            raise NotFoundError(f"flight {flight_id} not found")
        exif = {i.filename: bool((i.meta or {}).get("gps")) for i in flight.images}
    if len(content) > MAX_GPS_BYTES:
        raise TooLargeError(f"{filename}: a GPS file over {MAX_GPS_BYTES} bytes is not accepted")
    try:
        text = content.decode("utf-8")
        parsed = parse_gps_file(gps_file_name(filename, text), text)
    except UnicodeDecodeError:
        raise InvalidInputError(f"{filename}: not a UTF-8 text file") from None
    except ValueError as exc:
        raise InvalidInputError(f"{filename}: {exc}") from None
    if not parsed.fixes:
        raise InvalidInputError(f"{filename}: no image positions in it")
    folder = flight_folder(data_dir, flight_id).parent
    with atomic_path(folder / parsed.name) as tmp:
        tmp.write_text(text, encoding="utf-8")
    for other in GPS_FILE_NAMES:
        if other != parsed.name:
            (folder / other).unlink(missing_ok=True)
    return gps_summary(parsed, exif)


def gps_summary(parsed: GpsFile, exif: dict[str, bool]) -> dict[str, Any]:
    """What the file holds, and where each photo of the flight (name -> has EXIF GPS) now takes its GPS from."""
    named = {fix.name for fix in parsed.fixes}
    from_file = sum(name in named for name in exif)
    from_exif = sum(has and name not in named for name, has in exif.items())
    return {
        "file": parsed.name,
        "crs": parsed.crs,
        "fixes": len(parsed.fixes),
        "with_altitude": sum(fix.alt is not None for fix in parsed.fixes),
        "with_accuracy": sum(fix.accuracy_m is not None for fix in parsed.fixes),
        "images_not_in_flight": sorted(named - set(exif)),
        "gps_source": {"side_file": from_file, "exif": from_exif, "none": len(exif) - from_file - from_exif},
    }


def side_file_fixes(data_dir: Path, flight_id: int) -> tuple[str, dict[str, GpsFix]]:
    """The flight's side file name and its fixes by image name; ``("", {})`` when it has none."""
    path = gps_file(data_dir, flight_id)
    if path is None:
        return "", {}
    try:  # it parsed when it was stored; this only fails if the file was changed by hand since
        parsed = parse_gps_file(path.name, path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise InvalidInputError(f"flight {flight_id}: its GPS file {path.name} no longer reads ({exc})") from None
    return path.name, {fix.name: fix for fix in parsed.fixes}
