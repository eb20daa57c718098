"""A drone flight over ground with relief, photographed by a real (pinhole + Brown) camera.

Unlike ``scenes.make_flight``, whose frames are homographies of a flat texture, every pixel here is a
ray of a known camera with a known pose, traced to a known terrain: the ground truth for
photo-triangulation (poses, focal, distortion) and for orthorectification (where each ground point
must land in the map).

World frame: x east, y north, z up, metres, origin at the texture centre on the datum ``z = 0``;
``origin_utm`` places it in the UTM zone ``epsg``. With ``blocks`` the ground carries box-shaped buildings
(flat textured roofs, sheer walls): sharp relief that a smooth surface cannot follow.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import rasterio
from PIL import Image
from pyproj import Transformer

from tests.scenes import FIRST_SHOT, SHOT_INTERVAL, _exif_bytes, make_texture
from tests.sfm_scenes import dji_attitude
from workers.algorithms.geometry import Camera, rotation_from_vector

if TYPE_CHECKING:
    from workers.workspace import JobWorkspace


@dataclass(frozen=True)
class Block:
    """A box-shaped building: footprint ``x0 .. x1`` by ``y0 .. y1`` (world m), a flat roof at ``top_m`` (m above
    the datum) showing the texture of its spot, sheer walls down into the terrain."""

    x0: float
    y0: float
    x1: float
    y1: float
    top_m: float

    def inside(self, x: np.ndarray, y: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
        """Whether world x, y lie on the footprint grown by ``margin_m`` (shrunk where negative)."""
        m = margin_m
        return np.asarray((x >= self.x0 - m) & (x <= self.x1 + m) & (y >= self.y0 - m) & (y <= self.y1 + m))

    def entry(self, rays: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where rays (N, 3) from ``centre`` (going down) enter the box: (N,) ray parameter t (inf where they miss
        it) and (N,) bool, True where they enter through a wall rather than the roof (slab method)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            tx = (np.array([self.x0, self.x1]) - centre[0]) / rays[:, :1]
            ty = (np.array([self.y0, self.y1]) - centre[1]) / rays[:, 1:2]
            top = (self.top_m - centre[2]) / rays[:, 2]
        side = np.maximum(tx.min(axis=1), ty.min(axis=1))
        t_in = np.maximum(side, top)
        hit = (t_in <= np.minimum(tx.max(axis=1), ty.max(axis=1))) & (t_in > 0) & np.isfinite(t_in)
        return np.where(hit, t_in, np.inf), side > top


# Four buildings with roofs 4-7 m above the datum, 6-11 m across, with gaps between them, over the middle of a
# small flight (2 x 4 frames of 480 x 360 px from 40 m, about 70 x 50 m of ground):
# ``make_terrain_flight(..., blocks=BUILDINGS)``
BUILDINGS = (
    Block(-14.0, 1.0, -5.0, 8.0, 5.0),
    Block(-1.0, -7.0, 6.0, -1.0, 7.0),
    Block(9.0, 2.0, 20.0, 9.0, 4.0),
    Block(-9.0, -10.0, -3.0, -4.0, 6.0),
)


@dataclass(frozen=True)
class TerrainFlight:
    """Frames on disk and their truth.

    paths : JPEGs in flight order. camera : the true camera (the EXIF gives only a rounded 35 mm focal).
    rotations, centres : per frame (3, 3) and (3,), ``X_cam = R (X - C)`` in the world frame.
    texture : (H, W, 3) uint8 BGR draped over the terrain; ``texture_gsd_m`` metres per texture px.
    relief_m : amplitude of the terrain. epsg, origin_utm : where the world origin is. blocks : buildings on it.
    """

    paths: list[Path]
    camera: Camera
    rotations: list[np.ndarray]
    centres: list[np.ndarray]
    texture: np.ndarray
    texture_gsd_m: float
    relief_m: float
    epsg: int
    origin_utm: tuple[float, float]
    blocks: tuple[Block, ...] = ()

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Surface height (m) at world x, y: the terrain, or a building's roof where one stands."""
        z = self.terrain_height(x, y)
        for block in self.blocks:
            z = np.where(block.inside(x, y), np.maximum(z, block.top_m), z)
        return np.asarray(z)

    def terrain_height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Terrain height (m) at world x, y: two smooth hills and a gentle slope."""
        return self.relief_m * (
            np.exp(-((x - 6) ** 2 + (y - 4) ** 2) / 150.0)
            - 0.6 * np.exp(-((x + 10) ** 2 + (y + 6) ** 2) / 90.0)
            + 0.01 * x
        )

    def texture_px(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Texture pixel (column, row) of world x, y; rows grow southwards."""
        h, w = self.texture.shape[:2]
        return x / self.texture_gsd_m + (w - 1) / 2, -y / self.texture_gsd_m + (h - 1) / 2

    def ground_point(self, rays_world: np.ndarray, centre: np.ndarray) -> np.ndarray:
        """Where rays (N, 3) from ``centre`` first meet the ground or a building, (N, 3)."""
        return self.surface_hit(rays_world, centre)[0]

    def surface_hit(self, rays_world: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where rays (N, 3) from ``centre`` first meet the ground or a building, (N, 3), and (N,) bool: on a wall.
        The terrain by fixed-point iteration on height, each building by its box, the nearest taken."""
        z = np.zeros(len(rays_world))
        for _ in range(12):  # converges geometrically: slopes are gentle next to the flying height
            t = (z - centre[2]) / rays_world[:, 2]
            xy = centre[:2] + t[:, None] * rays_world[:, :2]
            z = self.terrain_height(xy[:, 0], xy[:, 1])
        wall = np.zeros(len(rays_world), bool)
        for block in self.blocks:
            t_in, side = block.entry(rays_world, centre)
            nearer = t_in < t
            t, wall = np.where(nearer, t_in, t), np.where(nearer, side, wall)
        return centre + t[:, None] * rays_world, wall


def make_terrain_flight(
    out_dir: Path,
    rows: int = 3,
    per_row: int = 5,
    frame_size: tuple[int, int] = (800, 600),
    altitude_m: float = 50.0,
    overlap: float = 0.7,
    relief_m: float = 6.0,
    tilt_deg: float = 4.0,
    k1: float = -0.06,
    k2: float = 0.02,
    seed: int = 0,
    origin_latlon: tuple[float, float] = (52.52, 13.40),
    heading_follows_flight: bool = False,
    attitude: tuple[str, ...] = (),
    gps_noise_m: float = 0.0,
    blocks: tuple[Block, ...] = (),
) -> TerrainFlight:
    """Render a serpentine grid flight (``rows`` lines of ``per_row`` frames) to JPEGs with EXIF GPS.

    The camera looks down, turned by up to 8 degrees of yaw and tilted by up to ``tilt_deg``; with
    ``heading_follows_flight`` the image top faces the direction of flight, so every other row is turned by
    180 degrees. GPS in the EXIF is the centre (altitude above the datum) plus ``gps_noise_m`` of Gaussian
    noise per axis; the 35 mm focal length is rounded to a whole millimetre as EXIF stores it. ``attitude``
    gives, per row, the heading convention of the DJI XMP gimbal angles written with it ("yaw": the image
    top faces the yaw; "yaw+180": it faces the opposite way, as on a Phantom 3; cycled over the rows), or
    writes none when empty. ``blocks`` stand on the terrain (``BUILDINGS``: sharp relief); their walls are
    shaded darker than the ground.
    """
    rng = np.random.default_rng(seed)
    w, h = frame_size
    focal = 0.9 * w
    # The principal point is at the centre, as the adjustment assumes: with GPS alone, a nadir block cannot
    # tell a principal-point offset from a common tilt of all cameras (it shifts the map by offset x GSD).
    camera = Camera(w, h, focal, focal, (w - 1) / 2, (h - 1) / 2, k1=k1, k2=k2)
    foot_w, foot_h = altitude_m * w / focal, altitude_m * h / focal
    step_x, step_y = foot_w * (1 - overlap), foot_h * 0.55
    centres, rotations, conventions = [], [], []
    for r in range(rows):
        for c in range(per_row) if r % 2 == 0 else reversed(range(per_row)):
            x, y = (c - (per_row - 1) / 2) * step_x, ((rows - 1) / 2 - r) * step_y
            centres.append(np.array([x, y, altitude_m + rng.uniform(-2, 2)]))
            turn = 180.0 if heading_follows_flight and r % 2 else 0.0
            rotations.append(_nadir_rotation(turn + rng.uniform(-8, 8), rng.uniform(-tilt_deg, tilt_deg, 2)))
            conventions.append(attitude[r % len(attitude)] if attitude else "")
    extent = np.abs(np.array(centres)[:, :2]).max(axis=0) + np.array([foot_w, foot_h]) * 1.2
    gsd = altitude_m / focal  # the texture has the photos' own resolution at the datum
    tex = make_texture(int(2 * extent[1] / gsd) + 1, int(2 * extent[0] / gsd) + 1, seed=int(rng.integers(2**31)))
    lat, lon = origin_latlon
    epsg = (32600 if lat >= 0 else 32700) + int((lon + 180) // 6) % 60 + 1
    east, north = Transformer.from_crs(4326, epsg, always_xy=True).transform(lon, lat)
    flight = TerrainFlight(
        [Path(out_dir) / f"terrain_{i:03d}.jpg" for i in range(len(centres))],
        camera,
        rotations,
        centres,
        tex,
        gsd,
        relief_m,
        epsg,
        (float(east), float(north)),
        tuple(blocks),
    )
    noise = rng.normal(0.0, gps_noise_m, (len(centres), 3)) if gps_noise_m > 0 else np.zeros((len(centres), 3))
    _render_frames(flight, conventions, noise)
    return flight


def make_buildings_flight(out_dir: Path) -> TerrainFlight:
    """The buildings flight: 2 x 4 frames of 480 x 360 px from 40 m over 2 m hills and ``BUILDINGS`` (the ortho
    truth test, the ortho DSM browser test and ``bench/ortho_surface.py`` fly the same one)."""
    return make_terrain_flight(
        out_dir, rows=2, per_row=4, frame_size=(480, 360), altitude_m=40.0, relief_m=2.0, seed=7, blocks=BUILDINGS
    )


WALL_SHADE = 0.55  # a wall's brightness against the ground's


def _nadir_rotation(yaw_deg: float, tilt_deg: np.ndarray) -> np.ndarray:
    """World -> camera rotation of a camera looking down, image top towards north turned by ``yaw_deg``."""
    down = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # x east, y south, z down
    yaw = rotation_from_vector(np.array([0, 0, math.radians(yaw_deg)]))
    tilt = rotation_from_vector(np.array([*np.radians(tilt_deg), 0.0]))
    return tilt @ down @ yaw.T


def _xmp(R: np.ndarray, convention: str) -> bytes:
    """A DJI XMP packet with the gimbal yaw / pitch / roll of world -> camera rotation ``R`` in ``convention``."""
    yaw, pitch, roll = dji_attitude(R)
    if convention == "yaw+180":  # the metadata heading is the camera's turned by 180 degrees
        yaw = (yaw + 360.0) % 360.0 - 180.0
    return (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        '<rdf:Description xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" '
        f'drone-dji:GimbalYawDegree="{yaw:+.2f}" drone-dji:GimbalPitchDegree="{pitch:+.2f}" '
        f'drone-dji:GimbalRollDegree="{roll:+.2f}"/></rdf:RDF></x:xmpmeta>'
    ).encode()


def _render_frames(flight: TerrainFlight, conventions: list[str], gps_noise: np.ndarray) -> None:
    cam = flight.camera
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
    rays = cam.unproject(np.column_stack([u.ravel(), v.ravel()]))
    to_wgs84 = Transformer.from_crs(flight.epsg, 4326, always_xy=True)
    for i, (R, C) in enumerate(zip(flight.rotations, flight.centres, strict=True)):
        ground, wall = flight.surface_hit(rays @ R, C)  # R.T @ ray for each row
        col, row = flight.texture_px(ground[:, 0], ground[:, 1])
        shape = (cam.height, cam.width)
        image = cv2.remap(
            flight.texture,
            col.reshape(shape).astype(np.float32),
            row.reshape(shape).astype(np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REFLECT,
        )
        if wall.any():  # walls face sideways: darker than the ground and the roofs
            image[wall.reshape(shape)] = (image[wall.reshape(shape)] * WALL_SHADE).astype(np.uint8)
        fix = C + gps_noise[i]
        lon, lat = to_wgs84.transform(flight.origin_utm[0] + fix[0], flight.origin_utm[1] + fix[1])
        pitch_mm = 36.0 / cam.width  # a full-frame-equivalent sensor: EXIF's 35 mm focal is focal * 36 / width
        exif = _exif_bytes(
            gps=(float(lat), float(lon), float(fix[2])),
            focal_length_mm=round(cam.fx * pitch_mm),
            sensor_width_mm=36.0,
            pixels_per_cm=10.0 / pitch_mm,
            taken=FIRST_SHOT + i * SHOT_INTERVAL,
        )
        flight.paths[i].parent.mkdir(parents=True, exist_ok=True)
        extra = {"xmp": _xmp(R, conventions[i])} if conventions[i] else {}
        Image.fromarray(cv2.cvtColor(image, cv2.COLOR_BGR2RGB)).save(
            flight.paths[i], "JPEG", quality=93, exif=exif, **extra
        )


def level_ground_colour_error(flight: TerrainFlight, mosaic: Path, z0: float) -> tuple[float, int]:
    """Mean colour difference (levels) between an orthomosaic and the texture at each pixel's map position,
    where the terrain is within 0.15 m of the ortho plane ``z0`` (elsewhere relief displaces the ground), and
    how many such pixels there are, away from the mosaic's edges."""
    return ground_colour_error(flight, mosaic, lambda x, y: np.abs(flight.height(x, y) - z0) < 0.15)


def relief_colour_error(flight: TerrainFlight, mosaic: Path, z0: float, off_m: float = 1.0) -> tuple[float, int]:
    """The same where the terrain is more than ``off_m`` above or below the plane ``z0``: the hills and
    hollows, which an orthomosaic projected onto that plane shows displaced by their relief."""
    return ground_colour_error(flight, mosaic, lambda x, y: np.abs(flight.height(x, y) - z0) > off_m)


def block_colour_error(flight: TerrainFlight, mosaic: Path, margin_m: float = 2.0) -> tuple[float, int]:
    """The same on the buildings and the ground within ``margin_m`` of them: where an orthomosaic on a surface
    that misses them shows their roofs displaced and ghosted, and their walls over the ground beside them."""
    return ground_colour_error(flight, mosaic, lambda x, y: _near_blocks(flight, x, y, margin_m))


def _near_blocks(flight: TerrainFlight, x: np.ndarray, y: np.ndarray, margin_m: float) -> np.ndarray:
    near = np.zeros(np.shape(x), bool)
    for block in flight.blocks:
        near |= block.inside(x, y, margin_m)
    return near


def roof_shifts_m(flight: TerrainFlight, mosaic: Path, search_m: float = 5.0) -> list[float]:
    """How far (m) the orthomosaic shows each building's roof from where it stands: the offset of the best
    normalised correlation (``cv2.matchTemplate``) of the true roof (its texture, 0.5 m in from the eaves) within
    ``search_m`` around its footprint in the mosaic; one per building, in ``flight.blocks`` order."""
    with rasterio.open(mosaic) as src:
        grey = cv2.cvtColor(np.moveaxis(src.read(), 0, 2), cv2.COLOR_RGB2GRAY).astype(np.float32)
        transform = src.transform
    inverse, gsd = ~transform, transform.a
    shifts = []
    for block in flight.blocks:
        col0, row0 = inverse @ (block.x0 + 0.5 + flight.origin_utm[0], block.y1 - 0.5 + flight.origin_utm[1])
        col1, row1 = inverse @ (block.x1 - 0.5 + flight.origin_utm[0], block.y0 + 0.5 + flight.origin_utm[1])
        cols = np.arange(int(np.ceil(col0)), int(col1) + 1)
        rows = np.arange(int(np.ceil(row0)), int(row1) + 1)
        east, north = np.meshgrid(transform.c + (cols + 0.5) * gsd, transform.f + (rows + 0.5) * transform.e)
        tex_col, tex_row = flight.texture_px(east - flight.origin_utm[0], north - flight.origin_utm[1])
        truth = cv2.remap(flight.texture, tex_col.astype(np.float32), tex_row.astype(np.float32), cv2.INTER_LINEAR)
        template = cv2.cvtColor(truth, cv2.COLOR_BGR2GRAY).astype(np.float32)
        pad = int(round(search_m / gsd))
        top, left = rows[0] - pad, cols[0] - pad
        if top < 0 or left < 0 or rows[-1] + pad >= grey.shape[0] or cols[-1] + pad >= grey.shape[1]:
            raise ValueError("a building is too near the mosaic's edge to search around it")
        window = grey[top : rows[-1] + pad + 1, left : cols[-1] + pad + 1]
        _, _, _, best = cv2.minMaxLoc(cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED))
        shifts.append(float(np.hypot(best[0] - pad, best[1] - pad) * gsd))
    return shifts


def roof_height_rms(flight: TerrainFlight, ws: JobWorkspace, inset_m: float = 0.5) -> float | None:
    """RMS (m) of the ortho surface the job saved against the buildings' roofs, ``inset_m`` in from their eaves
    (a surface gridded in cells cannot follow the wall itself); None when the job saved no surface."""
    surface = ws.load_ortho_surface()
    if surface is None:
        return None
    world = ws.load_cameras()["world"]
    shift = np.array([world["easting0"] - flight.origin_utm[0], world["northing0"] - flight.origin_utm[1]])
    errors = []
    for block in flight.blocks:
        x, y = np.meshgrid(
            np.arange(block.x0 + inset_m, block.x1 - inset_m, 0.1),
            np.arange(block.y0 + inset_m, block.y1 - inset_m, 0.1),
        )
        errors.append((surface.height_at(x - shift[0], y - shift[1]) - flight.height(x, y)).ravel())
    return float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))


def surface_height_rms(flight: TerrainFlight, ws: JobWorkspace) -> float | None:
    """RMS (m) of the ortho surface the job saved against the terrain, over the cameras' span and 10 m beyond;
    None when the job projected onto a plane (it saved no surface)."""
    surface = ws.load_ortho_surface()
    if surface is None:
        return None
    world = ws.load_cameras()["world"]
    shift = np.array([world["easting0"] - flight.origin_utm[0], world["northing0"] - flight.origin_utm[1]])
    centres = np.array(flight.centres)
    x, y = np.meshgrid(
        np.linspace(centres[:, 0].min() - 10, centres[:, 0].max() + 10, 200),
        np.linspace(centres[:, 1].min() - 10, centres[:, 1].max() + 10, 150),
    )
    error = surface.height_at(x - shift[0], y - shift[1]) - flight.height(x, y)
    return float(np.sqrt(np.mean(error**2)))


def ground_colour_error(
    flight: TerrainFlight, mosaic: Path, where: Callable[[np.ndarray, np.ndarray], np.ndarray]
) -> tuple[float, int]:
    """Mean colour difference (levels) between an orthomosaic and the texture at each pixel's map position over
    the ground ``where`` selects by world x, y, away from the mosaic's edges, and how many pixels that is."""
    with rasterio.open(mosaic) as src:
        assert src.crs.to_epsg() == flight.epsg
        rgb = np.moveaxis(src.read(), 0, 2).astype(np.float32)
        mask = src.dataset_mask() > 0
        rows, cols = np.mgrid[0 : src.height, 0 : src.width]
        east, north = rasterio.transform.xy(src.transform, rows.ravel(), cols.ravel())
    x = np.asarray(east) - flight.origin_utm[0]
    y = np.asarray(north) - flight.origin_utm[1]
    col, row = flight.texture_px(x, y)
    expected = cv2.remap(
        flight.texture,
        col.reshape(rows.shape).astype(np.float32),
        row.reshape(rows.shape).astype(np.float32),
        cv2.INTER_LINEAR,
    )[..., ::-1].astype(np.float32)
    chosen = where(x, y).reshape(rows.shape)
    inner = (cv2.erode(mask.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0) & chosen
    return float(np.abs(rgb - expected)[inner].mean()), int(inner.sum())
