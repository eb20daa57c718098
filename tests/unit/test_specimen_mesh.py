"""Specimen meshes: the readers (OBJ, PLY, STL, ASCII and binary), distances to the surface, the planes a
survey is rectified onto, the height raster of a curved panel against its analytic surface, and occlusion
in a photo against a scene whose hidden part is known."""

from __future__ import annotations

import struct

import cv2
import numpy as np
import pytest

from tests.crack_scenes import CurvedPanel, look_at, oblique_pose
from workers.algorithms.geometry import Camera
from workers.algorithms.specimen import (
    Mesh,
    MeshFormatError,
    best_fit_plane,
    distance_to_surface,
    plane_through,
    read_mesh,
)
from workers.algorithms.specimen.surface import _sample, mesh_surface, photo_depth, plate_surface, rectification_maps

# a unit square in two triangles and a triangle above it, with a quad for the fan
VERTICES = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0], [2, 2, 5]], dtype=np.float64)
FACES = [[0, 1, 2, 3], [0, 1, 4]]
TRIANGLES = np.array([[0, 1, 2], [0, 2, 3], [0, 1, 4]])


def obj_text() -> bytes:
    lines = ["# test", *[f"v {x} {y} {z}" for x, y, z in VERTICES], "vt 0 0", "f 1/1 2/1 3/1 4/1", "f -5 -4 -1"]
    return ("\n".join(lines) + "\n").encode()


def ply_ascii() -> bytes:
    header = [
        "ply",
        "format ascii 1.0",
        "comment made by hand",
        f"element vertex {len(VERTICES)}",
        "property float x",
        "property float y",
        "property float z",
        "property uchar red",
        f"element face {len(FACES)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    body = [f"{x} {y} {z} 255" for x, y, z in VERTICES] + [f"{len(f)} {' '.join(map(str, f))}" for f in FACES]
    return ("\n".join(header + body) + "\n").encode()


def ply_binary(order: str) -> bytes:
    name = "binary_little_endian" if order == "<" else "binary_big_endian"
    header = [
        "ply",
        f"format {name} 1.0",
        f"element vertex {len(VERTICES)}",
        "property double x",
        "property double y",
        "property double z",
        f"element face {len(FACES)}",
        "property list uchar uint vertex_indices",
        "end_header",
    ]
    body = b"".join(struct.pack(order + "3d", *v) for v in VERTICES)
    body += b"".join(struct.pack(order + "B" + "I" * len(f), len(f), *f) for f in FACES)
    return ("\n".join(header) + "\n").encode() + body


def stl_ascii() -> bytes:
    facets = "".join(
        "facet normal 0 0 1\n outer loop\n"
        + "".join(f"  vertex {x} {y} {z}\n" for x, y, z in VERTICES[t])
        + " endloop\nendfacet\n"
        for t in TRIANGLES
    )
    return f"solid test\n{facets}endsolid test\n".encode()


def stl_binary() -> bytes:
    header = b"solid but binary".ljust(80, b" ")
    records = b"".join(
        struct.pack("<3f", 0, 0, 1) + struct.pack("<9f", *VERTICES[t].ravel()) + b"\0\0" for t in TRIANGLES
    )
    return header + struct.pack("<I", len(TRIANGLES)) + records


def triangle_set(mesh: Mesh) -> set[tuple[tuple[float, ...], ...]]:
    """The triangles as sets of corner coordinates, independent of vertex numbering and rotation."""
    return {tuple(sorted(map(tuple, corners))) for corners in mesh.corners().round(6)}


@pytest.mark.parametrize(
    ("name", "make"),
    [
        ("m.obj", obj_text),
        ("m.ply", ply_ascii),
        ("m.ply", lambda: ply_binary("<")),
        ("m.ply", lambda: ply_binary(">")),
        ("m.stl", stl_ascii),
        ("M.STL", stl_binary),
    ],
    ids=["obj", "ply-ascii", "ply-le", "ply-be", "stl-ascii", "stl-binary"],
)
def test_every_format_reads_the_same_triangles(name: str, make) -> None:
    mesh = read_mesh(make(), name)
    assert triangle_set(mesh) == triangle_set(Mesh(VERTICES, TRIANGLES))
    assert np.isclose(mesh.areas().sum(), 100.0 + 0.5 * 10 * np.hypot(2, 5))


PLY_HEAD = b"ply\nformat ascii 1.0\nelement vertex 3\n"
PLY_FACE = b"element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"


@pytest.mark.parametrize(
    ("name", "data", "fragment"),
    [
        ("m.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n", "not a valid OBJ file"),
        ("m.obj", b"v 0 0 0\nv 1 0 0\nf 1 2 3\n", "refers to a vertex that does not exist"),
        ("m.obj", b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "zero area"),
        ("m.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no triangles"),
        ("m.obj", b"v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "not finite"),
        ("m.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n", "'vertex' and 'face'"),
        ("m.ply", b"PK\x03\x04zip", "no PLY header"),
        ("m.ply", PLY_HEAD + b"property quad x\n" + PLY_FACE, "header line 4: unknown PLY property type 'quad'"),
        ("m.ply", PLY_HEAD + b"property float y\nproperty float z\n" + PLY_FACE, "has no x property"),
        ("m.ply", PLY_HEAD + b"property float x y z\n" + PLY_FACE, "header line 4: expected 'property <type>"),
        ("m.ply", b"ply\nformat ascii 1.0\nelement vertex -3\n" + PLY_FACE, "header line 3: expected 'element"),
        ("m.stl", b"\x00" * 84 + b"\x01" * 7, "neither a binary STL"),
        ("m.step", b"ISO-10303-21;", "unknown model format"),
    ],
)
def test_malformed_models_are_refused_saying_why(name: str, data: bytes, fragment: str) -> None:
    with pytest.raises(MeshFormatError, match=fragment.replace("(", r"\(")):
        read_mesh(data, name)


def test_distance_to_surface_matches_sampling_the_triangles() -> None:
    rng = np.random.default_rng(0)
    mesh = Mesh(VERTICES, TRIANGLES)
    points = rng.uniform(-5, 15, (200, 3))
    # brute force: dense barycentric samples of every triangle
    u, v = np.meshgrid(np.linspace(0, 1, 201), np.linspace(0, 1, 201))
    keep = u + v <= 1
    w = np.column_stack([1 - u[keep] - v[keep], u[keep], v[keep]])
    samples = np.concatenate([w @ corners for corners in mesh.corners()])
    brute = np.array([np.min(np.linalg.norm(samples - p, axis=1)) for p in points])
    exact = distance_to_surface(mesh, points, chunk=700)  # several chunks
    assert np.all(exact <= brute + 1e-9) and np.max(brute - exact) < 0.06  # samples are 0.05 mm apart


def test_planes_of_a_curved_panel() -> None:
    panel = CurvedPanel(200.0, 150.0, 120.0)
    mesh = panel_mesh(panel)
    frame = best_fit_plane(mesh)
    assert np.allclose(frame.axes @ frame.axes.T, np.eye(3), atol=1e-12)
    assert frame.axes[0] @ [1, 0, 0] > 0.999 and frame.axes[1] @ [0, 1, 0] > 0.999  # U along X, V along Y
    plane = frame.to_plane(mesh.vertices)
    assert abs(plane[:, 0].min()) < 1e-9 and abs(plane[:, 1].min()) < 1e-9  # origin at the box corner
    assert np.allclose(frame.to_model(plane), mesh.vertices)
    chosen = plane_through(mesh, np.array([[0, 0, 0], [0, 150, 0], [panel.chord_mm, 0, 0]]))
    assert np.allclose(chosen.axes[0], [0, 1, 0]) and np.allclose(chosen.axes[1], [1, 0, 0])
    with pytest.raises(ValueError, match="not on one line"):
        plane_through(mesh, np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2]]))


def panel_mesh(panel: CurvedPanel, n_arc: int = 64, n_y: int = 12) -> Mesh:
    s, y = np.meshgrid(np.linspace(0, panel.width_mm, n_arc + 1), np.linspace(0, panel.height_mm, n_y + 1))
    vertices = panel.to_model(np.column_stack([s.ravel(), y.ravel()]))
    k = np.arange((n_y + 1) * (n_arc + 1)).reshape(n_y + 1, n_arc + 1)
    a, b, c, d = k[:-1, :-1].ravel(), k[:-1, 1:].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel()
    return Mesh(vertices, np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])]))


def test_height_raster_of_a_panel_follows_the_cylinder() -> None:
    panel = CurvedPanel(200.0, 150.0, 120.0)
    mesh = panel_mesh(panel, n_arc=128)
    camera_side = np.array([panel.chord_mm / 2, 75.0, -400.0])
    surface = mesh_surface(mesh, best_fit_plane(mesh), 0.5, camera_side)
    points = surface.points().reshape(-1, 3)
    on = np.all(np.isfinite(points), axis=1)
    assert on.mean() > 0.97  # the panel fills its bounding box in the plane
    axis = panel.axis
    radial = np.hypot(points[on, 0] - axis[0], points[on, 2] - axis[1])
    assert np.max(np.abs(radial - panel.radius_mm)) < 0.05  # chords of 128 facets sag by 0.04 mm at most
    normals = surface.normals().reshape(-1, 3)[on]
    outward = np.column_stack([points[on, 0] - axis[0], np.zeros(on.sum()), points[on, 2] - axis[1]]) / radial[:, None]
    assert np.percentile(np.abs(np.einsum("ij,ij->i", normals, outward)), 5) > 0.999
    xy = np.array([[10.0, 20.0], [80.0, 70.0]])
    assert np.allclose(np.hypot(*(surface.lift(xy)[:, [0, 2]] - axis).T), panel.radius_mm, atol=0.05)


def test_a_wall_hides_what_is_behind_it_from_one_photo_only() -> None:
    """A 100 x 100 mm plate with a 40 mm wall standing along X = 50: a camera low on the +X side cannot see
    the strip just behind the wall (X < 50, its shadow), a camera straight above sees all of the plate."""
    plate = [[0, 0, 0], [100, 0, 0], [100, 100, 0], [0, 100, 0]]
    wall = [[50, 0, 0], [50, 100, 0], [50, 100, -40], [50, 0, -40]]
    mesh = Mesh(np.array(plate + wall, float), np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]))
    camera = Camera(800, 600, 700.0, 700.0, 400.0, 300.0, k1=-0.05)
    frame = plane_through(mesh, np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0]]))
    assert np.allclose(frame.axes, np.eye(3)) and np.allclose(frame.origin, 0.0)
    surface = mesh_surface(mesh, frame, 1.0, np.array([50.0, 50.0, -500.0]))
    assert surface.shape == (101, 101) and np.all(surface.height == 0.0)  # the wall, edge-on, covers no pixel
    low_C = np.array([180.0, 50.0, -60.0])  # 60 mm above the plate, 130 mm from the wall's foot
    top_C = np.array([50.0, 50.0, -400.0])
    low = photo_depth(mesh, camera, look_at(low_C, np.array([40.0, 50.0, 0.0]), np.array([0.0, -1.0, 0.0])), low_C)
    top = photo_depth(mesh, camera, look_at(top_C, np.array([50.0, 50.0, 0.0]), np.array([1.0, 0.0, 0.0])), top_C)
    x = np.arange(2.5, 100.0, 5.0)
    points = np.column_stack([x, np.full_like(x, 50.0), np.zeros_like(x)])
    # the wall's top edge (X = 50, Z = -40) seen from low_C shadows the plate down to X = 50 - 40 * 130 / 20
    shadow_start = 50.0 - 40.0 * (180.0 - 50.0) / (60.0 - 40.0)
    expected_low = (x > 50.0) | (x < shadow_start)
    assert shadow_start < 0  # from this low camera the whole strip behind the wall is hidden
    assert np.array_equal(low.visible(points), expected_low)
    assert top.visible(points).all()
    # the rectification maps say the same: no density behind the wall from the low camera
    rows = slice(45, 56)
    _, _, density = rectification_maps(camera, low.R, low.C, surface, rows, low)
    # column = X mm; the pixel next to the wall's foot may go either way
    assert np.all(density[:, :49] == 0) and np.all(density[:, 51:] > 0)


def test_a_plate_surface_is_its_own_plane() -> None:
    surface = plate_surface(200.0, 150.0, 0.25)
    assert surface.shape == (601, 801)
    assert np.allclose(surface.points()[600, 800], [200.0, 150.0, 0.0])
    assert np.allclose(surface.lift(np.array([[12.5, 7.25]])), [[12.5, 7.25, 0.0]])


def test_a_plates_interpolated_maps_match_the_exact_ones() -> None:
    """The plate's maps come from nodes 8 px apart: against every pixel computed exactly, under 0.01 px."""
    camera = Camera(900, 700, 945.0, 945.0, 456.0, 346.0, k1=-0.09, k2=0.04, t1=3e-4, t2=-2e-4)
    surface = plate_surface(200.0, 150.0, 0.25)
    R, C = oblique_pose(camera, 200.0, 150.0, 30.0, 15.0)
    rows = slice(37, 301)  # a block not starting on a node row
    map_x, map_y, density = rectification_maps(camera, R, C, surface, rows)
    uv, exact_density, seen = _sample(camera, R, C, surface.points(rows), surface.normals(rows))
    assert seen.mean() > 0.9 and np.array_equal(density > 0, seen)
    error = np.hypot(map_x - uv[..., 0], map_y - uv[..., 1])
    assert error[seen].max() < 0.01
    assert np.max(np.abs(density[seen] / exact_density[seen] - 1)) < 1e-4


def test_photo_sampling_on_a_coarse_raster_is_the_photos() -> None:
    """The sampling measured on a 0.5 mm raster, as ``rectify_specimen`` measures it before choosing the
    detection raster, agrees with the same measure on a 0.1 mm raster and with the pose's nominal value."""
    from tests.crack_scenes import nominal_sampling
    from workers.algorithms.specimen import photo_sampling

    camera = Camera(900, 700, 945.0, 945.0, 456.0, 346.0, k1=-0.09, k2=0.04, t1=3e-4, t2=-2e-4)
    for elevation in (30.0, 60.0):
        pose = oblique_pose(camera, 200.0, 150.0, elevation, 0.0)
        coarse = photo_sampling(camera, [pose], plate_surface(200.0, 150.0, 0.5))
        fine = photo_sampling(camera, [pose], plate_surface(200.0, 150.0, 0.1))
        assert abs(coarse / fine - 1) < 0.01, (coarse, fine)
        assert abs(coarse / nominal_sampling(camera, 200.0, 150.0, elevation, 0.0) - 1) < 0.05
    assert np.isnan(photo_sampling(camera, [], plate_surface(200.0, 150.0, 0.5)))


def test_resampled_raster_keeps_positions_on_the_plane() -> None:
    """A dot at (x, y) mm stays at (x, y) mm when a 0.1 mm raster is resampled to 0.25 mm and to 0.05 mm."""
    from workers.algorithms.specimen import raster_shape, resample_raster

    dot = np.full(raster_shape(40.0, 30.0, 0.1), 200, np.uint8)
    dot[180, 120] = 0  # (x, y) = (12, 18) mm
    image = cv2.GaussianBlur(dot, (0, 0), 3.0)
    mask = np.ones(image.shape, bool)
    for out in (0.25, 0.05):
        shape = raster_shape(40.0, 30.0, out)
        resampled, seen = resample_raster(image, mask, 0.1, shape, out)
        assert resampled.shape == shape and seen.all()
        weight = np.maximum(200.0 - resampled, 0.0)
        rows, cols = np.indices(shape)
        x, y = (weight * cols).sum() / weight.sum() * out, (weight * rows).sum() / weight.sum() * out
        assert np.hypot(x - 12.0, y - 18.0) < 0.02, (out, x, y)  # the dot's centroid, mm
