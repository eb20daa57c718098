"""A cracked specimen (a plate or a curved panel) photographed obliquely per load stage by a real
(pinhole + Brown) camera.

Model frame: X right, Y down the plate, Z = 0 on its surface (Z grows into the plate), mm; a curved
panel bulges from Z = 0 toward the cameras. Cracks and texture live in surface coordinates (s, y) mm,
true lengths on the surface (the plate's X, Y; a panel's arc length and Y). The coating is a grain
texture under a light ramp and a directional light; cracks are dark grooves of known width along known
polylines. Every photo pixel is a ray of the true camera traced to the surface (as in
``terrain_scenes``); a crack darkens the pixel by the fraction of its footprint it covers, so thin
cracks seen obliquely are rendered without aliasing. Stage 2 keeps the cracks of stage 1, grows one and
adds new ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from workers.algorithms.geometry import Camera

TEXTURE_MM_PER_PX = 0.1  # resolution of the coating texture and of the crack distance field
# control marks besides the corners, (X, Y) mm on a 200 x 150 mm specimen (scaled with other sizes)
MARKS_MM = ((50.0, 40.0), (150.0, 110.0), (60.0, 115.0))


@dataclass(frozen=True)
class TrueCrack:
    line_mm: np.ndarray  # (N, 2) float64 (x, y) mm centreline
    width_mm: float
    status: str  # "first" (stage 1), "unchanged", "grown" or "new" in stage 2

    @property
    def length_mm(self) -> float:
        return float(np.linalg.norm(np.diff(self.line_mm, axis=0), axis=1).sum())


@dataclass(frozen=True)
class Photo:
    path: Path
    stage: int
    view: int  # index into the views the scene was made with
    R: np.ndarray  # (3, 3) true pose, X_cam = R (X - C)
    C: np.ndarray  # (3,) mm
    control_points: list[dict[str, list[float]]]  # {"pixel": [x, y] (noisy), "model": [X, Y, 0]}


@dataclass
class CrackSurveyScene:
    width_mm: float
    height_mm: float
    camera: Camera
    stages: list[list[TrueCrack]]  # the cracks present at each load stage, in surface (s, y) mm
    photos: list[Photo] = field(default_factory=list)
    specimen: Plate | CurvedPanel | None = None
    mesh_path: Path | None = None  # a curved panel's OBJ
    photo_mm_per_px: float = 0.0  # the first view's nominal sampling at the plate's centre, mm per photo px

    def options(self, mm_per_px: float, views: tuple[int, ...] | None = None) -> dict:
        """The crack-survey options a user would send for these photos (only ``views``, by index, if given)."""
        stages = [
            {
                "label": f"stage {s + 1}",
                "load": 10.0 * (s + 1),
                "photos": [
                    {"image": p.path.name, "control_points": p.control_points}
                    for p in self.photos
                    if p.stage == s and (views is None or p.view in views)
                ],
            }
            for s in range(len(self.stages))
        ]
        specimen = (
            {"mesh": self.mesh_path.name}
            if self.mesh_path is not None
            else {"width_mm": self.width_mm, "height_mm": self.height_mm}
        )
        return {"camera": self.camera.to_json(), "specimen": specimen, "stages": stages, "mm_per_px": mm_per_px}

    def paths(self, views: tuple[int, ...] | None = None) -> list[Path]:
        return [p.path for p in self.photos if views is None or p.view in views]


def wandering_line(
    rng: np.random.Generator, start: np.ndarray, angle: float, length_mm: float, step_mm: float = 1.0
) -> np.ndarray:
    """(N, 2) centreline of a gently wandering crack of ``length_mm`` from ``start``."""
    points = [start]
    for _ in range(int(round(length_mm / step_mm))):
        angle += rng.normal(0, 0.04)
        points.append(points[-1] + step_mm * np.array([math.cos(angle), math.sin(angle)]))
    return np.array(points)


def _place_cracks(
    rng: np.random.Generator,
    n: int,
    width_mm: float,
    height_mm: float,
    taken: list[np.ndarray],
    status: str,
    spacing_mm: float = 12.0,
    edge_mm: float = 8.0,
    widths_mm: tuple[float, ...] | None = None,
    lengths_mm: tuple[float, float] = (50.0, 80.0),
) -> list[TrueCrack]:
    cracks: list[TrueCrack] = []
    for _ in range(5000):
        if len(cracks) == n:
            return cracks
        start = rng.uniform([edge_mm, edge_mm], [width_mm - edge_mm, height_mm - edge_mm])
        line = wandering_line(rng, start, rng.uniform(0, 2 * np.pi), rng.uniform(*lengths_mm))
        inside = (line.min(axis=0) >= edge_mm).all() and (
            line.max(axis=0) <= [width_mm - edge_mm, height_mm - edge_mm]
        ).all()
        far = all(np.min(np.linalg.norm(line[:, None] - other[None], axis=2)) > spacing_mm for other in taken)
        if inside and far:
            taken.append(line)
            width = float(rng.uniform(0.6, 1.2))
            if widths_mm is not None:  # the classes in turn, counting the cracks placed before
                width = widths_mm[(len(taken) - 1) % len(widths_mm)]
            cracks.append(TrueCrack(line, width, status))
    raise RuntimeError(f"no room for {n} cracks {spacing_mm} mm apart")


def _grow(rng: np.random.Generator, crack: TrueCrack, extra_mm: float) -> TrueCrack:
    tail = crack.line_mm[-1] - crack.line_mm[-2]
    more = wandering_line(rng, crack.line_mm[-1], math.atan2(tail[1], tail[0]), extra_mm)
    return TrueCrack(np.vstack([crack.line_mm, more[1:]]), crack.width_mm, "grown")


def make_stages(
    seed: int,
    width_mm: float,
    height_mm: float,
    widths_mm: tuple[float, ...] | None = None,
    cracks: tuple[int, int] = (5, 2),
    lengths_mm: tuple[float, float] = (50.0, 80.0),
) -> list[list[TrueCrack]]:
    """Stage 1: ``cracks[0]`` cracks. Stage 2: the same, one of them (listed first) grown by 15 mm, and
    ``cracks[1]`` new cracks. Lengths uniform in ``lengths_mm``; widths uniform in 0.6-1.2 mm, or
    ``widths_mm`` in turn."""
    rng = np.random.default_rng(seed)
    taken: list[np.ndarray] = []
    first = _place_cracks(
        rng, cracks[0], width_mm, height_mm, taken, "first", widths_mm=widths_mm, lengths_mm=lengths_mm
    )
    found = _grow_one(rng, first, taken, width_mm, height_mm)
    if found is None:
        raise RuntimeError(f"seed {seed}: no room to grow any crack")
    index, grown = found
    taken[index] = grown.line_mm
    unchanged = [TrueCrack(c.line_mm, c.width_mm, "unchanged") for k, c in enumerate(first) if k != index]
    first.insert(0, first.pop(index))  # the grown crack first in both stages
    new = _place_cracks(rng, cracks[1], width_mm, height_mm, taken, "new", widths_mm=widths_mm, lengths_mm=lengths_mm)
    return [first, [grown, *unchanged, *new]]


def _grow_one(
    rng: np.random.Generator, cracks: list[TrueCrack], taken: list[np.ndarray], width_mm: float, height_mm: float
) -> tuple[int, TrueCrack] | None:
    """One crack of ``cracks`` grown by 15 mm at its end, staying on the plate and away from the others."""
    for index, crack in enumerate(cracks):
        others = [t for k, t in enumerate(taken) if k != index]
        for _ in range(40):
            grown = _grow(rng, crack, 15.0)
            extension = grown.line_mm[len(crack.line_mm) :]
            inside = (extension.min(axis=0) >= 8).all() and (
                extension.max(axis=0) <= [width_mm - 8, height_mm - 8]
            ).all()
            if inside and all(np.min(np.linalg.norm(extension[:, None] - o[None], axis=2)) > 12 for o in others):
                return index, grown
    return None


def look_at(C: np.ndarray, target: np.ndarray, right: np.ndarray) -> np.ndarray:
    """World -> camera rotation of a camera at ``C`` looking at ``target``, image x along ``right``."""
    z = (target - C) / np.linalg.norm(target - C)
    x = right - (right @ z) * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def oblique_pose(
    camera: Camera, width_mm: float, height_mm: float, elevation_deg: float, azimuth_deg: float, fill: float = 0.85
) -> tuple[np.ndarray, np.ndarray]:
    """A camera seeing the whole plate at ``elevation_deg`` above its plane, from the direction
    ``azimuth_deg`` (0: from +Y, the bottom of the plate), the plate filling ``fill`` of the frame."""
    centre = np.array([width_mm / 2, height_mm / 2, 0.0])
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    direction = np.array([math.cos(e) * math.sin(a), math.cos(e) * math.cos(a), -math.sin(e)])
    right = np.array([math.cos(a), -math.sin(a), 0.0])
    corners = np.array([[0, 0, 0], [width_mm, 0, 0], [0, height_mm, 0], [width_mm, height_mm, 0]], float)
    distance = 2.0 * max(width_mm, height_mm)
    for _ in range(6):  # scale the distance until the plate spans ``fill`` of the limiting frame side
        C = centre + distance * direction
        R = look_at(C, centre, right)
        uv = camera.project((corners - C) @ R.T)
        span = max((uv[:, 0].max() - uv[:, 0].min()) / camera.width, (uv[:, 1].max() - uv[:, 1].min()) / camera.height)
        distance *= span / fill
    return R, centre + distance * direction


def nominal_sampling(camera: Camera, width_mm: float, height_mm: float, elevation: float, azimuth: float) -> float:
    """mm per photo pixel at the centre of a plate seen from :func:`oblique_pose`: the geometric mean of
    ``distance / f`` across the view and ``distance / (f sin(elevation))`` along it."""
    R, C = oblique_pose(camera, width_mm, height_mm, elevation, azimuth)
    distance = float(np.linalg.norm(C - np.array([width_mm / 2, height_mm / 2, 0.0])))
    f = math.sqrt(camera.fx * camera.fy)
    return distance / (f * math.sqrt(math.sin(math.radians(elevation))))


def _coating(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) float32 grain of the coating around 150: standard deviations 6, 2 and 3 at 0.15, 1 and 3 mm."""
    grain = np.full(shape, 150.0, np.float32)
    for sigma_mm, amplitude in ((0.15, 6.0), (1.0, 2.0), (3.0, 3.0)):
        s = sigma_mm / TEXTURE_MM_PER_PX
        noise = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), s)
        grain += amplitude * noise / noise.std()
    return grain


def crack_field(cracks: list[TrueCrack], shape: tuple[int, int]) -> np.ndarray:
    """(H, W) float32 on the texture grid: max over cracks of (half width - distance to its centreline), mm."""
    field = np.full(shape, -1e3, np.float32)
    for crack in cracks:
        canvas = np.full(shape, 255, np.uint8)
        points = np.rint(crack.line_mm / TEXTURE_MM_PER_PX * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(canvas, [points], False, 0, 1, cv2.LINE_8, shift=4)
        distance = cv2.distanceTransform(canvas, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * TEXTURE_MM_PER_PX
        # that is the distance to the drawn pixels, up to half a texture pixel off the line, which widened every
        # crack by ~0.03 mm: across the crack and its edges, the exact distance to the polyline instead
        rows, cols = np.nonzero(distance < crack.width_mm / 2 + 2 * TEXTURE_MM_PER_PX)
        exact, _ = cKDTree(dense_line(crack.line_mm, 0.005)).query(np.column_stack([cols, rows]) * TEXTURE_MM_PER_PX)
        distance[rows, cols] = exact
        field = np.maximum(field, crack.width_mm / 2 - distance)
    return field


@dataclass(frozen=True)
class Plate:
    """The flat specimen: surface (s, y) coordinates are its model (X, Y), Z = 0."""

    width_mm: float
    height_mm: float

    def to_model(self, sy: np.ndarray) -> np.ndarray:
        """(N, 2) surface (s, y) mm -> (N, 3) model mm."""
        return np.column_stack([sy, np.zeros(len(sy))])

    def trace(self, C: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where rays (N, 3) from ``C`` first meet the specimen: (N, 2) surface (s, y) mm, (N,) bool hit and
        (N,) cosine between the surface's outward normal and a light from above the top right."""
        t = -C[2] / rays[:, 2]
        xy = C[:2] + t[:, None] * rays[:, :2]
        hit = (t > 0) & (xy[:, 0] >= 0) & (xy[:, 0] <= self.width_mm) & (xy[:, 1] >= 0) & (xy[:, 1] <= self.height_mm)
        return xy, hit, np.full(len(rays), -LIGHT[2])


LIGHT = np.array([0.45, -0.35, -0.82]) / np.linalg.norm([0.45, -0.35, -0.82])  # toward the light, from the surface


@dataclass(frozen=True)
class CurvedPanel:
    """A cylindrical panel bulging toward the cameras (-Z): arc length ``width_mm`` across (surface s), height
    along its axis (model Y), radius ``radius_mm``. Its long edges lie on Z = 0 at X = 0 and X = chord.

    The cylinder is developable, so surface (s, y) distances are true lengths on the panel.
    """

    width_mm: float
    height_mm: float
    radius_mm: float

    @property
    def half_angle(self) -> float:
        return self.width_mm / (2 * self.radius_mm)

    @property
    def chord_mm(self) -> float:
        return 2 * self.radius_mm * math.sin(self.half_angle)

    @property
    def axis(self) -> np.ndarray:
        """(X, Z) of the cylinder's axis, mm."""
        return np.array([self.chord_mm / 2, self.radius_mm * math.cos(self.half_angle)])

    def to_model(self, sy: np.ndarray) -> np.ndarray:
        phi = (np.asarray(sy)[:, 0] - self.width_mm / 2) / self.radius_mm
        return np.column_stack(
            [
                self.axis[0] + self.radius_mm * np.sin(phi),
                np.asarray(sy)[:, 1],
                self.axis[1] - self.radius_mm * np.cos(phi),
            ]
        )

    def trace(self, C: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`Plate.trace`: the nearer intersection with the cylinder, on the panel."""
        o = C[[0, 2]] - self.axis
        d = rays[:, [0, 2]]
        a, b, c = np.sum(d * d, axis=1), 2 * d @ o, o @ o - self.radius_mm**2
        disc = b * b - 4 * a * c
        t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
        P = C + t[:, None] * rays
        phi = np.arctan2(P[:, 0] - self.axis[0], self.axis[1] - P[:, 2])
        sy = np.column_stack([self.radius_mm * phi + self.width_mm / 2, P[:, 1]])
        hit = (disc > 0) & (t > 0) & (np.abs(phi) <= self.half_angle) & (sy[:, 1] >= 0) & (sy[:, 1] <= self.height_mm)
        normal = np.column_stack([np.sin(phi), np.zeros_like(phi), -np.cos(phi)])
        return sy, hit, normal @ LIGHT

    def write_mesh(self, path: Path, n_arc: int = 64, n_y: int = 12) -> None:
        """The panel as an OBJ of (n_arc x n_y) quads split in triangles, model mm."""
        s, y = np.meshgrid(np.linspace(0, self.width_mm, n_arc + 1), np.linspace(0, self.height_mm, n_y + 1))
        vertices = self.to_model(np.column_stack([s.ravel(), y.ravel()]))
        k = np.arange((n_y + 1) * (n_arc + 1)).reshape(n_y + 1, n_arc + 1)
        a, b, c, d = k[:-1, :-1].ravel(), k[:-1, 1:].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel()
        faces = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
        lines = [f"v {x:.6f} {yy:.6f} {z:.6f}" for x, yy, z in vertices] + [
            f"f {i + 1} {j + 1} {m + 1}" for i, j, m in faces
        ]
        path.write_text("# curved panel, mm\n" + "\n".join(lines) + "\n")


def _nearest_centreline(cracks: list[TrueCrack], points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For surface points (N, 2) mm: (N,) exact distance to the nearest crack's centreline (points 0.005 mm
    apart along it), mm; (N,) that crack's width, mm; (N, 2) the centreline's unit normal there."""
    lines = [dense_line(c.line_mm, 0.005) for c in cracks]
    tangents = [np.gradient(line, axis=0) for line in lines]
    tangent = np.concatenate(tangents)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    widths = np.concatenate([np.full(len(line), c.width_mm) for line, c in zip(lines, cracks, strict=True)])
    distance, index = cKDTree(np.concatenate(lines)).query(points)
    return distance, widths[index], np.column_stack([-tangent[index, 1], tangent[index, 0]])


def _spread_cdf(t: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """P(U + V <= t) for independent U, V uniform on widths ``a`` and ``b`` centred on 0."""

    def ramp2(x: np.ndarray) -> np.ndarray:
        return np.maximum(x, 0.0) ** 2 / 2

    h, k = (a + b) / 2, np.abs(a - b) / 2
    return (ramp2(t + h) - ramp2(t + k) - ramp2(t - k) + ramp2(t - h)) / (a * b)


def render_photo(
    camera: Camera,
    R: np.ndarray,
    C: np.ndarray,
    coating: np.ndarray,
    field_mm: np.ndarray,
    specimen: Plate | CurvedPanel,
    rng: np.random.Generator,
    cracks: list[TrueCrack] | None = None,
    contrast: float = 0.5,
    blur_px: float = 0.0,
) -> np.ndarray:
    """(H, W) uint8: the specimen (coating under a light ramp and a directional light, cracks ``contrast``
    darker than the coating) on a dark background, blurred by a Gaussian PSF of ``blur_px``, with noise.

    With ``cracks`` (the true cracks ``field_mm`` was made from) a pixel's cover is the exact share of its
    footprint (the parallelogram of its neighbours' rays on the specimen, the crack locally straight) the
    crack covers, at the pixel's exact distance from the nearest crack's centreline (not the field's 0.1 mm
    grid, whose interpolation rounds the centreline's ridge off by up to 0.05 mm), so a hairline narrower
    than a pixel darkens it by its width over the footprint's extent across it, and a row of pixels across
    a crack holds its exact darkness deficit; without, the edge-only approximation ``0.5 + inside /
    footprint`` (right for cracks wider than a pixel). Rendered in bands of rows (a 4000 x 3000 photo
    would hold some 5 GiB of float64 rays and maps at once)."""
    centrelines = None if cracks is None else _Centrelines.of(cracks)
    image = np.empty((camera.height, camera.width), np.float64)
    step = max(1, (1 << 20) // camera.width)
    for top in range(0, camera.height, step):
        stop = min(top + step, camera.height)
        image[top:stop] = _render_rows(camera, R, C, coating, field_mm, specimen, top, stop, centrelines, contrast)
    if blur_px > 0:
        image = cv2.GaussianBlur(image.astype(np.float32), (0, 0), blur_px)
    image = image + rng.normal(0, 3.0, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class _Centrelines:
    """Every crack's centreline as points 0.005 mm apart, with that crack's width and the unit normal there."""

    tree: cKDTree
    widths: np.ndarray  # (M,) mm
    normals: np.ndarray  # (M, 2)

    @classmethod
    def of(cls, cracks: list[TrueCrack]) -> _Centrelines:
        lines = [dense_line(c.line_mm, 0.005) for c in cracks]
        tangent = np.concatenate([np.gradient(line, axis=0) for line in lines])
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
        widths = np.concatenate([np.full(len(line), c.width_mm) for line, c in zip(lines, cracks, strict=True)])
        return cls(cKDTree(np.concatenate(lines)), widths, np.column_stack([-tangent[:, 1], tangent[:, 0]]))

    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For surface points (N, 2) mm: (N,) exact distance to the nearest centreline, mm, (N,) that crack's
        width, mm, and (N, 2) its unit normal there."""
        distance, index = self.tree.query(points)
        return distance, self.widths[index], self.normals[index]


def _render_rows(
    camera: Camera,
    R: np.ndarray,
    C: np.ndarray,
    coating: np.ndarray,
    field_mm: np.ndarray,
    specimen: Plate | CurvedPanel,
    top: int,
    stop: int,
    centrelines: _Centrelines | None,
    contrast: float,
) -> np.ndarray:
    """(stop - top, W) float64 grey of photo rows ``top:stop`` of :func:`render_photo`, before blur and noise."""
    first, last = max(top - 1, 0), min(stop + 1, camera.height)  # a row of margin for the footprint's gradient
    u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(first, last, dtype=np.float64))
    rays = camera.unproject(np.column_stack([u.ravel(), v.ravel()])) @ R  # R.T @ ray per row
    sy, hit, lit = specimen.trace(C, rays)
    xy = sy.reshape(last - first, camera.width, 2)
    # the pixel's footprint on the plate (mm): a crack darkens it by the share of the footprint it covers
    du, dv = np.gradient(xy, axis=1), np.gradient(xy, axis=0)
    keep = slice(top - first, stop - first)
    xy, du, dv = xy[keep], du[keep], dv[keep]
    on_plate = hit.reshape(-1, camera.width)[keep]
    width_mm, height_mm = specimen.width_mm, specimen.height_mm
    shade = (0.55 + 0.45 * np.clip(lit, 0, 1) / -LIGHT[2]).reshape(-1, camera.width)[keep]  # 1 where facing -Z
    col, row = (xy[..., 0] / TEXTURE_MM_PER_PX).astype(np.float32), (xy[..., 1] / TEXTURE_MM_PER_PX).astype(np.float32)
    albedo = cv2.remap(coating, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    inside = cv2.remap(field_mm, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    footprint = np.sqrt(np.abs(du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0]))
    if centrelines is None:
        cover = np.clip(0.5 + inside / footprint, 0.0, 1.0)
    else:
        cover = np.zeros(on_plate.shape)
        # every pixel whose footprint may reach a crack (the field is good to a texture pixel out there)
        reach = 2 * (np.abs(du).sum(-1) + np.abs(dv).sum(-1)) + 3 * TEXTURE_MM_PER_PX
        near = on_plate & (inside > -reach)
        d, w, n = centrelines.nearest(xy[near])
        # the footprint is the parallelogram du x dv: across the crack (normal n) it spreads as the sum of two
        # uniform variables |du . n| and |dv . n| wide (an oblique view's pixels are longer along the view)
        a = np.maximum(np.abs(np.einsum("ij,ij->i", du[near], n)), 1e-3 * footprint[near])
        b = np.maximum(np.abs(np.einsum("ij,ij->i", dv[near], n)), 1e-3 * footprint[near])
        cover[near] = np.clip(_spread_cdf(d + w / 2, a, b) - _spread_cdf(d - w / 2, a, b), 0.0, 1.0)
    light = 0.75 + 0.5 * (0.6 * xy[..., 0] / width_mm + 0.4 * (1 - xy[..., 1] / height_mm))  # from the top right
    return np.where(on_plate, albedo * light * shade * (1 - contrast * cover), 45.0)


def make_crack_survey(
    out_dir: Path,
    views: list[tuple[float, float]],
    seed: int = 0,
    width_mm: float = 200.0,
    height_mm: float = 150.0,
    frame_size: tuple[int, int] = (900, 700),
    panel_radius_mm: float | None = None,
    widths_px: tuple[float, ...] | None = None,
    contrast: float = 0.5,
    blur_px: float = 0.0,
    widths_mm: tuple[float, ...] | None = None,
    cracks: tuple[int, int] = (5, 2),
    lengths_mm: tuple[float, float] = (50.0, 80.0),
) -> CrackSurveyScene:
    """Render two load stages, each photographed from ``views`` (elevation, azimuth) degrees, to PNGs.

    The specimen is a plate, or with ``panel_radius_mm`` a :class:`CurvedPanel` of arc width ``width_mm``
    whose mesh is written to ``out_dir / "panel.obj"`` (the scene's ``mesh_path``). The camera is re-set
    between stages (a few mm and a degree off); control points are the specimen's corners and ``MARKS_MM``
    (in surface coordinates, scaled to the specimen's size), projected through the true camera with 0.3 px
    noise.

    Hairline scenes: ``widths_px`` gives the cracks' widths in turn in photo pixels of the first view (its
    nominal sampling at the plate's centre, ``scene.photo_mm_per_px``; a plate only), or ``widths_mm`` in
    mm, rendered with exact sub-pixel cover, ``contrast`` (share of the coating's brightness a crack takes
    away) and a Gaussian PSF of ``blur_px`` photo pixels. ``cracks``: how many at stage 1 and how many new
    at stage 2, ``lengths_mm``: the range of their lengths (:func:`make_stages`).
    """
    rng = np.random.default_rng(seed)
    w, h = frame_size
    camera = Camera(w, h, 1.05 * w, 1.05 * w, w / 2 + 6.0, h / 2 - 4.0, k1=-0.09, k2=0.04, t1=3e-4, t2=-2e-4)
    specimen = (
        Plate(width_mm, height_mm) if panel_radius_mm is None else CurvedPanel(width_mm, height_mm, panel_radius_mm)
    )
    sampling = nominal_sampling(camera, width_mm, height_mm, *views[0])
    exact_cover = widths_px is not None or widths_mm is not None
    if exact_cover and panel_radius_mm is not None:
        raise ValueError("hairline widths are for a plate")
    if widths_px is not None:
        widths_mm = tuple(w * sampling for w in widths_px)
    stages = make_stages(seed, width_mm, height_mm, widths_mm, cracks, lengths_mm)
    scene = CrackSurveyScene(width_mm, height_mm, camera, stages, specimen=specimen, photo_mm_per_px=sampling)
    shape = (int(round(height_mm / TEXTURE_MM_PER_PX)) + 1, int(round(width_mm / TEXTURE_MM_PER_PX)) + 1)
    coating = _coating(rng, shape)
    marks = np.array(MARKS_MM) * [width_mm / 200.0, height_mm / 150.0]
    model = specimen.to_model(np.array([[0, 0], [width_mm, 0], [0, height_mm], [width_mm, height_mm], *marks]))
    out_dir.mkdir(parents=True, exist_ok=True)
    if isinstance(specimen, CurvedPanel):
        scene.mesh_path = out_dir / "panel.obj"
        specimen.write_mesh(scene.mesh_path)
    extent = specimen.chord_mm if isinstance(specimen, CurvedPanel) else width_mm
    for s, cracks in enumerate(scene.stages):
        field_mm = crack_field(cracks, shape)
        exact = cracks if exact_cover else None
        for k, (elevation, azimuth) in enumerate(views):
            R, C = oblique_pose(camera, extent, height_mm, elevation + rng.uniform(-1, 1), azimuth + rng.uniform(-2, 2))
            C = C + rng.uniform(-3, 3, 3)
            image = render_photo(camera, R, C, coating, field_mm, specimen, rng, exact, contrast, blur_px)
            path = out_dir / f"stage{s + 1}_view{k + 1}_{int(elevation)}deg.png"
            cv2.imwrite(str(path), image)
            pixels = camera.project((model - C) @ R.T) + rng.normal(0, 0.3, (len(model), 2))
            points = [{"pixel": p.tolist(), "model": m.tolist()} for p, m in zip(pixels, model, strict=True)]
            scene.photos.append(Photo(path, s, k, R, C, points))
    return scene


def run_survey(scene: CrackSurveyScene, root: Path, options: dict) -> dict:
    """Run every stage of a crack survey in this process over a workspace at ``root`` (no API, no database)
    on the scene's photos with ``options``; return its ``report.json``."""
    from workers.pipeline import PIPELINES, run_stage
    from workers.workspace import JobWorkspace

    ws = JobWorkspace(root)
    ws.root.mkdir(parents=True, exist_ok=True)
    names = {p["image"] for stage in options["stages"] for p in stage["photos"]}
    ws.save_config(options)
    ws.save_inputs([{"name": p.path.name, "path": str(p.path)} for p in scene.photos if p.path.name in names])
    for spec in PIPELINES["crack_survey"]:
        run_stage(ws, "crack_survey", spec.name)
    return ws.load_report()


def dense_line(line: np.ndarray, step: float = 0.05) -> np.ndarray:
    """(M, 2) points every ``step`` mm along a polyline (N, 2)."""
    along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))]
    s = np.arange(0.0, along[-1] + step, step)
    return np.column_stack([np.interp(s, along, line[:, 0]), np.interp(s, along, line[:, 1])])


@dataclass(frozen=True)
class CrackScore:
    """How a survey's report found one stage's true cracks."""

    found: list[float]  # per true crack, the share of its centreline within tolerance of a reported crack
    widths_mm: list[float | None]  # per true crack, the mean width of the reported crack along it (None: none)
    false_mm: float  # reported length farther than tolerance from every true crack
    true_mm: float  # total true length


def score_stage(stage: dict, truth: list[TrueCrack], tolerance_mm: float) -> CrackScore:
    """Score one stage of ``report.json`` against its true cracks: recall by centreline, false length, and the
    width of the reported crack that covers most of each true crack."""

    reported = [np.concatenate([dense_line(np.array(p)) for p in c["paths_mm"] if len(p) > 1]) for c in stage["cracks"]]
    trees = [cKDTree(points) for points in reported]
    found, widths = [], []
    for crack in truth:
        points = dense_line(crack.line_mm)
        near = [tree.query(points)[0] <= tolerance_mm for tree in trees]
        found.append(float(np.logical_or.reduce(near).mean()) if near else 0.0)
        best = int(np.argmax([n.sum() for n in near])) if near else -1
        widths.append(stage["cracks"][best]["mean_width_mm"] if best >= 0 and near[best].mean() > 0.5 else None)
    every_true = cKDTree(np.concatenate([dense_line(c.line_mm) for c in truth]))
    false = sum(0.05 * float((every_true.query(points)[0] > tolerance_mm).sum()) for points in reported)
    return CrackScore(found, widths, false, sum(c.length_mm for c in truth))


def rows_along(stage: dict, truth: list[TrueCrack], tolerance_mm: float) -> list[dict | None]:
    """Per true crack, the reported crack of ``stage`` (``report.json``) with most of its length within
    ``tolerance_mm`` of it, if over half (None: none)."""

    out: list[dict | None] = []
    for crack in truth:
        tree = cKDTree(dense_line(crack.line_mm))
        best, best_share = None, 0.5
        for row in stage["cracks"]:
            points = np.concatenate([dense_line(np.array(q)) for q in row["paths_mm"] if len(q) > 1])
            share = float((tree.query(points)[0] <= tolerance_mm).mean())
            if share > best_share:
                best, best_share = row, share
        out.append(best)
    return out


def photo_px_across(scene: CrackSurveyScene, crack: TrueCrack, stage: int) -> float:
    """The true photo sampling across ``crack`` in load step ``stage``, mm per photo pixel (see
    :func:`crack_sampling`). A crack ``w`` mm wide spans ``w / photo_px_across`` photo pixels across it."""
    return crack_sampling(scene, crack, stage)[1]


def crack_sampling(scene: CrackSurveyScene, crack: TrueCrack, stage: int) -> tuple[float, float]:
    """The true photo sampling where ``crack`` is in load step ``stage``, mm per photo pixel: isotropic (the
    square root of a photo pixel's area on the plate) and across the crack (the extent along its normal
    ``n`` of a photo pixel, ``|J^-T n|`` with ``J`` the true camera's Jacobian of photo pixel by plate (x, y)
    mm), medians along its centreline, each point from its most finely sampling photo (a plate only)."""
    points = dense_line(crack.line_mm, 0.5)
    tangent = np.gradient(points, axis=0)
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    model = np.column_stack([points, np.zeros(len(points))])
    best_density, across = np.zeros(len(points)), np.full(len(points), np.nan)
    for photo in (p for p in scene.photos if p.stage == stage):

        def project(offset: list[float], photo: Photo = photo) -> np.ndarray:
            return scene.camera.project((model + offset - photo.C) @ photo.R.T)

        step = 1e-3  # mm
        du = (project([step, 0, 0]) - project([-step, 0, 0])) / (2 * step)
        dv = (project([0, step, 0]) - project([0, -step, 0])) / (2 * step)
        J = np.stack([du, dv], axis=2)  # (N, 2 photo, 2 plate): photo px per mm
        density = np.abs(np.linalg.det(J))
        better = density > best_density
        across[better] = np.linalg.norm(np.einsum("nji,nj->ni", np.linalg.inv(J), normal), axis=1)[better]
        best_density = np.maximum(best_density, density)
    return float(np.median(1.0 / np.sqrt(best_density))), float(np.nanmedian(across))
