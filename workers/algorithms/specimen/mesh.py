"""Triangle meshes of a specimen (OBJ, PLY, STL in mm): reading, the plane a survey is rectified onto, and
distances from points to the surface.

NumPy only, so the API can check an uploaded model before it records a job. Readers keep what a
specimen needs: vertex positions and triangles (polygons are fanned into triangles); normals, colours
and texture coordinates are ignored.

The rectification plane is a :class:`PlaneFrame`: an origin and right-handed axes ``U, V, N`` (rows of
``axes``). A model point ``P`` has plane coordinates ``(x, y, h) = axes @ (P - origin)``: ``x, y`` in the
plane (mm, the rectified raster's frame, X right and Y down), ``h`` the height above it along ``N``.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

import numpy as np

MESH_SUFFIXES = (".obj", ".ply", ".stl")
MAX_TRIANGLES = 2_000_000
MAX_VERTICES = 3 * MAX_TRIANGLES  # every triangle with corners of its own (an unwelded STL)
MAX_SHOWN = 200  # characters of a parser's message (which may quote the file) kept in an error


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh: ``vertices`` (V, 3) float64 model mm, ``triangles`` (T, 3) int64 vertex indices."""

    vertices: np.ndarray
    triangles: np.ndarray

    def corners(self) -> np.ndarray:
        """(T, 3, 3) float64: each triangle's three vertices."""
        return self.vertices[self.triangles]

    def areas(self) -> np.ndarray:
        """(T,) float64 triangle areas, mm^2."""
        a, b, c = np.moveaxis(self.corners(), 1, 0)
        return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)

    @property
    def diagonal_mm(self) -> float:
        return float(np.linalg.norm(np.ptp(self.vertices, axis=0)))


@dataclass(frozen=True)
class PlaneFrame:
    """A plane: ``origin`` (3,) model mm and ``axes`` (3, 3), rows U (x), V (y), N (height), orthonormal."""

    origin: np.ndarray
    axes: np.ndarray

    def to_plane(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) model mm -> (N, 3) plane (x, y, h) mm."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.axes.T

    def to_model(self, plane: np.ndarray) -> np.ndarray:
        """(N, 3) plane (x, y, h) -> (N, 3) model mm; (N, 2) plane points are taken at h = 0."""
        plane = np.asarray(plane, dtype=np.float64)
        if plane.shape[-1] == 2:
            plane = np.concatenate([plane, np.zeros((*plane.shape[:-1], 1))], axis=-1)
        return self.origin + plane @ self.axes

    def to_json(self) -> dict[str, list[float]]:
        return {
            "origin_mm": self.origin.tolist(),
            "x_axis": self.axes[0].tolist(),
            "y_axis": self.axes[1].tolist(),
            "normal": self.axes[2].tolist(),
        }


class MeshFormatError(ValueError):
    """The file is not a mesh this module reads; the message says where it went wrong."""


def read_mesh(data: bytes, name: str) -> Mesh:
    """Parse an OBJ, PLY (ASCII or binary) or STL (ASCII or binary) file, chosen by ``name``'s suffix.

    Raises :class:`MeshFormatError` on anything malformed, on a mesh without triangles, on indices
    outside the vertex list and on non-finite coordinates.
    """
    suffix = name[name.rfind(".") :].lower() if "." in name else ""
    readers = {".obj": _read_obj, ".ply": _read_ply, ".stl": _read_stl}
    if suffix not in readers:
        raise MeshFormatError(f"{name}: unknown model format; use one of {', '.join(MESH_SUFFIXES)}")
    try:
        _check_counts(suffix, data)
        vertices, triangles = readers[suffix](data)
    except MeshFormatError as exc:
        raise MeshFormatError(f"{name}: {exc}") from None
    except (ValueError, IndexError, KeyError, TypeError, OverflowError, struct.error) as exc:  # UnicodeDecodeError too
        reason = str(exc) if len(str(exc)) <= MAX_SHOWN else str(exc)[:MAX_SHOWN] + "..."
        raise MeshFormatError(f"{name}: not a valid {suffix[1:].upper()} file ({reason})") from None
    return _checked(name, vertices, triangles)


def _check_counts(suffix: str, data: bytes) -> None:
    """Refuse a model with more vertices or faces than accepted before any array or list is built: the
    counts of a PLY header or a binary STL, or a count of an OBJ's ``v``/``f`` lines (one pass in C)."""
    vertices, faces = 0, 0
    if suffix == ".obj":
        lines = b"\n" + data
        vertices = lines.count(b"\nv ") + lines.count(b"\nv\t")
        faces = lines.count(b"\nf ") + lines.count(b"\nf\t")
    elif suffix == ".ply" and (end := data.find(b"end_header", 0, 1 << 20)) >= 0:
        for line in data[:end].split(b"\n"):
            parts = line.split()
            if len(parts) == 3 and parts[0] == b"element" and parts[2].isdigit():
                vertices += int(parts[2]) if parts[1] == b"vertex" else 0
                faces += int(parts[2]) if parts[1] == b"face" else 0
    elif suffix == ".stl" and len(data) >= 84 and len(data) == 84 + 50 * struct.unpack_from("<I", data, 80)[0]:
        faces = struct.unpack_from("<I", data, 80)[0]  # binary: its size matches its triangle count
    if faces > MAX_TRIANGLES:  # every face is at least one triangle
        raise MeshFormatError(f"{faces} faces; at most {MAX_TRIANGLES} triangles are accepted")
    if vertices > MAX_VERTICES:
        raise MeshFormatError(f"{vertices} vertices; at most {MAX_VERTICES} are accepted")


def _checked(name: str, vertices: np.ndarray, triangles: np.ndarray) -> Mesh:
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(triangles) == 0:
        raise MeshFormatError(f"{name}: the model has no triangles")
    if len(triangles) > MAX_TRIANGLES:
        raise MeshFormatError(f"{name}: {len(triangles)} triangles; at most {MAX_TRIANGLES} are accepted")
    if not np.all(np.isfinite(vertices)):
        raise MeshFormatError(f"{name}: some vertex coordinates are not finite numbers")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise MeshFormatError(f"{name}: a face refers to a vertex that does not exist ({len(vertices)} vertices)")
    mesh = Mesh(vertices, triangles)
    keep = mesh.areas() > 1e-12 * max(mesh.diagonal_mm, 1e-9) ** 2
    if not keep.any():
        raise MeshFormatError(f"{name}: every triangle of the model has zero area")
    return Mesh(vertices, triangles[keep])


def _fan(polygon: list[int]) -> list[list[int]]:
    return [[polygon[0], polygon[k], polygon[k + 1]] for k in range(1, len(polygon) - 1)]


def _read_obj(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    vertices: list[list[float]] = []
    triangles: list[list[int]] = []
    for number, raw in enumerate(data.decode("utf-8", errors="replace").splitlines(), start=1):
        parts = raw.split("#", 1)[0].split()
        if not parts:
            continue
        if parts[0] == "v":
            if len(parts) < 4:
                raise MeshFormatError(f"line {number}: a vertex needs x y z")
            vertices.append([float(p) for p in parts[1:4]])
        elif parts[0] == "f":
            if len(parts) < 4:
                raise MeshFormatError(f"line {number}: a face needs at least three vertices")
            # "f v/vt/vn ...": 1-based, negative counts back from the last vertex read so far
            indices = [int(p.split("/")[0]) for p in parts[1:]]
            triangles += _fan([i - 1 if i > 0 else len(vertices) + i for i in indices])
    return np.array(vertices, dtype=np.float64), np.array(triangles, dtype=np.int64)


def _read_stl(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    # A binary STL may begin with "solid" too: it is binary when its size matches its triangle count.
    if len(data) >= 84:
        count = struct.unpack_from("<I", data, 80)[0]
        if len(data) == 84 + 50 * count:
            records = np.frombuffer(
                data,
                dtype=np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")]),
                count=count,
                offset=84,
            )
            return _weld(records["corners"].astype(np.float64))
    text = data.decode("ascii")
    if not text.lstrip().startswith("solid"):
        raise MeshFormatError("neither a binary STL (size does not match its triangle count) nor an ASCII one")
    numbers = re.findall(r"vertex\s+(\S+)\s+(\S+)\s+(\S+)", text)
    if len(numbers) % 3:
        raise MeshFormatError(f"{len(numbers)} vertices is not a whole number of triangles")
    return _weld(np.array(numbers, dtype=np.float64).reshape(-1, 3, 3))


def _weld(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """STL stores every triangle's corners: shared vertices are merged so the mesh is connected."""
    vertices, inverse = np.unique(corners.reshape(-1, 3), axis=0, return_inverse=True)
    return vertices, inverse.reshape(-1, 3)


_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


@dataclass
class _PlyElement:
    name: str
    count: int
    properties: list[tuple[str, str, str | None]]  # (name, value type, list count type or None)


def _read_ply(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise MeshFormatError("no PLY header (it must start with 'ply' and close with 'end_header')")
    body = data[data.index(b"\n", end) + 1 :]
    fmt, elements = _ply_header(data[:end].decode("ascii").splitlines())
    if fmt == "ascii":
        return _ply_ascii(body.decode("ascii").split(), elements)
    return _ply_binary(body, elements, "<" if fmt == "binary_little_endian" else ">")


def _ply_header(lines: list[str]) -> tuple[str, list[_PlyElement]]:
    fmt, elements = "", []
    for number, line in enumerate(lines[1:], start=2):
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format" and len(parts) >= 2:
            fmt = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise MeshFormatError(f"header line {number}: expected 'element <name> <count>'")
            elements.append(_PlyElement(parts[1], int(parts[2]), []))
        elif parts[0] == "property" and elements:
            elements[-1].properties.append(_ply_property(number, parts))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise MeshFormatError(f"unknown PLY format {fmt!r}")
    names = [e.name for e in elements]
    if "vertex" not in names or "face" not in names:
        raise MeshFormatError("a PLY model needs 'vertex' and 'face' elements")
    vertex = elements[names.index("vertex")]
    scalars = {name for name, _, count in vertex.properties if count is None}
    if missing := [axis for axis in "xyz" if axis not in scalars]:
        raise MeshFormatError(f"the PLY 'vertex' element has no {', '.join(missing)} property; it needs x, y and z")
    return fmt, elements


def _ply_property(number: int, parts: list[str]) -> tuple[str, str, str | None]:
    """(name, value type, list count type or None) of a ``property`` header line."""
    is_list = parts[1:2] == ["list"]
    if len(parts) != (5 if is_list else 3):
        raise MeshFormatError(
            f"header line {number}: expected 'property <type> <name>' or 'property list <type> <type> <name>'"
        )
    types = parts[2:4] if is_list else parts[1:2]
    if unknown := [t for t in types if t not in _PLY_TYPES]:
        raise MeshFormatError(
            f"header line {number}: unknown PLY property type {unknown[0]!r}; known: {', '.join(_PLY_TYPES)}"
        )
    if is_list:
        return parts[4], _PLY_TYPES[parts[3]], _PLY_TYPES[parts[2]]
    return parts[2], _PLY_TYPES[parts[1]], None


def _ply_ascii(tokens: list[str], elements: list[_PlyElement]) -> tuple[np.ndarray, np.ndarray]:
    at, vertices, triangles = 0, np.zeros((0, 3)), []
    for element in elements:
        rows = []
        for _ in range(element.count):
            row: dict[str, object] = {}
            for name, _kind, count_kind in element.properties:
                if count_kind is None:
                    row[name], at = float(tokens[at]), at + 1
                else:
                    n = int(tokens[at])
                    row[name], at = [int(float(t)) for t in tokens[at + 1 : at + 1 + n]], at + 1 + n
            rows.append(row)
        if element.name == "vertex":
            vertices = np.array([[r["x"], r["y"], r["z"]] for r in rows], dtype=np.float64)
        elif element.name == "face":
            triangles = [t for r in rows for t in _fan(_face_list(r))]
    return vertices, np.array(triangles, dtype=np.int64)


def _face_list(row: dict[str, object]) -> list[int]:
    value = row.get("vertex_indices", row.get("vertex_index"))
    if not isinstance(value, list):
        raise MeshFormatError("a PLY face needs a 'vertex_indices' list")
    return value


def _ply_binary(body: bytes, elements: list[_PlyElement], order: str) -> tuple[np.ndarray, np.ndarray]:
    at, vertices, triangles = 0, np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    for element in elements:
        if all(count is None for _, _, count in element.properties):  # fixed-size records: one read
            dtype = np.dtype([(name, order + kind) for name, kind, _ in element.properties])
            table = np.frombuffer(body, dtype=dtype, count=element.count, offset=at)
            at += dtype.itemsize * element.count
            if element.name == "vertex":
                vertices = np.column_stack([table["x"], table["y"], table["z"]]).astype(np.float64)
            continue
        faces = []
        for _ in range(element.count):
            row: dict[str, object] = {}
            for name, kind, count_kind in element.properties:
                if count_kind is None:
                    row[name] = np.frombuffer(body, order + kind, 1, at)[0]
                    at += np.dtype(kind).itemsize
                else:
                    n = int(np.frombuffer(body, order + count_kind, 1, at)[0])
                    at += np.dtype(count_kind).itemsize
                    row[name] = np.frombuffer(body, order + kind, n, at).astype(np.int64).tolist()
                    at += n * np.dtype(kind).itemsize
            faces.append(row)
        if element.name == "face":
            triangles = np.array([t for r in faces for t in _fan(_face_list(r))], dtype=np.int64)
    return vertices, triangles


def best_fit_plane(mesh: Mesh) -> PlaneFrame:
    """The least-squares plane of the surface (area-weighted triangle centroids), as a :class:`PlaneFrame`.

    ``U`` is the direction of largest extent and ``V`` the next, each turned to point along the positive
    model axis it is closest to, so a panel modelled X right and Y down is rectified the same way up;
    ``N = U x V``. The origin is the corner of the surface's bounding box in (U, V), so every plane
    coordinate of the surface is >= 0.
    """
    corners = mesh.corners()
    weights = mesh.areas()
    centroids = corners.mean(axis=1)
    centre = np.average(centroids, axis=0, weights=weights)
    d = centroids - centre
    _, vectors = np.linalg.eigh((d * weights[:, None]).T @ d)
    u, v = vectors[:, 2], vectors[:, 1]
    u = u if u @ _dominant(u) >= 0 else -u
    v = v if v @ _dominant(v) >= 0 else -v
    return _framed(mesh, centre, u, v)


def _dominant(axis: np.ndarray) -> np.ndarray:
    """The model axis (X, Y or Z) an axis is closest to, as a unit vector."""
    unit = np.zeros(3)
    unit[int(np.argmax(np.abs(axis)))] = 1.0
    return unit


def plane_through(mesh: Mesh, points: np.ndarray) -> PlaneFrame:
    """The plane through three model points (3, 3): the first is on it, ``U`` runs toward the second, and
    the third is on the +V side. Origin moved to the surface's bounding-box corner as in :func:`best_fit_plane`."""
    p = np.asarray(points, dtype=np.float64).reshape(3, 3)
    u, w = p[1] - p[0], p[2] - p[0]
    normal = np.cross(u, w)
    if np.linalg.norm(normal) <= 1e-9 * np.linalg.norm(u) * np.linalg.norm(w) or np.linalg.norm(normal) == 0:
        raise ValueError("the three plane points must be distinct and not on one line")
    u /= np.linalg.norm(u)
    v = np.cross(normal / np.linalg.norm(normal), u)
    return _framed(mesh, p[0], u, v)


def _framed(mesh: Mesh, centre: np.ndarray, u: np.ndarray, v: np.ndarray) -> PlaneFrame:
    axes = np.stack([u, v, np.cross(u, v)])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    local = (mesh.vertices - centre) @ axes.T
    origin = centre + local[:, 0].min() * axes[0] + local[:, 1].min() * axes[1]
    return PlaneFrame(origin, axes)


def distance_to_surface(mesh: Mesh, points: np.ndarray, chunk: int = 200_000) -> np.ndarray:
    """(N,) float64 distance from each of ``points`` (N, 3) mm to the nearest point of the mesh, mm.

    Closest point on a triangle by its Voronoi regions (Ericson, *Real-Time Collision Detection*, 5.1.5),
    for every point against every triangle, in chunks of about ``chunk`` pairs.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    corners = mesh.corners()
    best = np.full(len(points), np.inf)
    step = max(1, chunk // max(len(points), 1))
    for start in range(0, len(corners), step):
        a, b, c = (corners[start : start + step, k][None] for k in range(3))
        closest = _closest_on_triangles(points[:, None], a, b, c)
        best = np.minimum(best, np.linalg.norm(closest - points[:, None], axis=2).min(axis=1))
    return best


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points (N, T, 3) on triangles (1, T, 3) x3 to points (N, 1, 3)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp, cp = p - b, p - c
    d3, d4, d5, d6 = _dot(ab, bp), _dot(ac, bp), _dot(ab, cp), _dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v, w = vb * denom, vc * denom
        result = a + ab * v[..., None] + ac * w[..., None]  # inside the face
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    regions = [  # Ericson's tests in reverse: the last that holds wins
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + (c - b) * t_bc[..., None]),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * t_ac[..., None]),
        ((d6 >= 0) & (d5 <= d6), np.broadcast_to(c, result.shape)),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * t_ab[..., None]),
        ((d3 >= 0) & (d4 <= d3), np.broadcast_to(b, result.shape)),
        ((d1 <= 0) & (d2 <= 0), np.broadcast_to(a, result.shape)),
    ]
    for condition, point in regions:
        result = np.where(condition[..., None], point, result)
    return result


def _dot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.einsum("...k,...k->...", x, y)
