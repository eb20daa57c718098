"""Every bad input is answered 4xx with a message a user can act on, and nothing is stored: the cases an
attacker's run found (each answered 500, or accepted and stored, before), one test each, plus the bounds
every option of the config models must have."""

from __future__ import annotations

import io
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from PIL import Image
from pydantic import BaseModel, ValidationError

from api.errors import MAX_ECHO_CHARS
from api.limits import MAX_JSON_BYTES, MAX_JSON_DEPTH, nesting_depth
from tests.conftest import RecordingQueue
from tests.scenes import make_flight
from workers import config
from workers.algorithms.geometry import Camera
from workers.config import JOB_KINDS, MAX_ID, MAX_RASTER_PIXELS, build_config
from workers.image_meta import inspect_image

CAMERA = Camera(900, 700, 945.0, 945.0, 456.0, 346.0).to_json()
TOO_BIG = 2**64  # beyond a signed 64-bit id


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return make_flight(tmp_path_factory.mktemp("frames"), n_frames=2, frame_size=(320, 240), seed=4).paths


@pytest.fixture
def flight(client: TestClient, frames: list[Path]) -> int:
    """A flight with two photos, as a mosaic job needs."""
    flight_id = int(client.post("/api/flights", json={"name": "f"}).json()["id"])
    files = [("files", (p.name, p.read_bytes(), "image/jpeg")) for p in frames]
    assert client.post(f"/api/flights/{flight_id}/images", files=files).status_code == 201
    return flight_id


State = tuple[Any, Any, list[str]]


@pytest.fixture
def unchanged(client: TestClient, api_settings, recording_queue: RecordingQueue) -> Callable[[], None]:
    """Call to assert that the jobs, the flights, the queue and the files under the data dir are as they
    were when the test's request was about to be sent (the fixture is taken after ``flight``)."""

    def state() -> State:
        files = sorted(
            str(p.relative_to(api_settings.data_dir))
            for p in api_settings.data_dir.rglob("*")
            if p.is_file() and not p.name.startswith("fotoskhema.db")
        )
        return client.get("/api/jobs").json(), client.get("/api/flights").json(), files

    before, sent = state(), list(recording_queue.sent)

    def check() -> None:
        assert state() == before
        assert recording_queue.sent == sent

    return check


def survey_options(specimen: dict[str, Any], points: list[list[float]] | None = None, **extra: Any) -> dict:
    """Crack-survey options for one photo ``a.png`` with control points at the model ``points``."""
    points = points or [[0, 0, 0], [100, 0, 0], [0, 80, 0], [100, 80, 0], [50, 40, 0], [20, 60, 0]]
    control = [{"pixel": [100.0 + 5 * k, 100.0 + 3 * k], "model": m} for k, m in enumerate(points)]
    stages = [{"label": "0 kN", "photos": [{"image": "a.png", "control_points": control}]}]
    return {"camera": CAMERA, "specimen": specimen, "stages": stages, **extra}


def post_survey(client: TestClient, options: dict | str, model: tuple[str, bytes] | None = None) -> Any:
    files = [("model", (model[0], model[1], "application/octet-stream"))] if model else []
    data = {"options": options if isinstance(options, str) else json.dumps(options)}
    return client.post("/api/crack-surveys", data=data, files=files or None)


def put_gcps(client: TestClient, flight: int, name: str, content: str) -> Any:
    return client.put(f"/api/flights/{flight}/gcps", files={"file": (name, content.encode(), "text/plain")})


def nested(depth: int) -> dict:
    value: dict = {}
    for _ in range(depth - 1):
        value = {"a": value}
    return value


# -- Ids beyond 64 bits: HTTP 500 (the SQLite driver overflowed) -> 422 naming the bound ---------------------


def test_ids_beyond_64_bits_are_422_on_every_route(client: TestClient, unchanged: Callable[[], None]) -> None:
    schema = client.app.openapi()  # type: ignore[attr-defined]
    checked = 0
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            params = operation.get("parameters", [])  # path ids; an integer query (a line number) is not an id
            ints = [p["name"] for p in params if p["in"] == "path" and p["schema"].get("type") == "integer"]
            for name in ints:
                url = path
                for other in ints:
                    url = url.replace("{" + other + "}", str(TOO_BIG if other == name else 1))
                response = client.request(method, url)
                assert response.status_code == 422, (method, url, response.text)
                checked += 1
                if method == "head":  # an answer to HEAD has no body to say more
                    continue
                (problem,) = [p for p in response.json()["detail"] if p["loc"] == ["path", name]]
                assert str(MAX_ID) in problem["msg"]
    assert checked >= 20
    response = client.get("/api/jobs", params={"flight_id": TOO_BIG})
    assert response.status_code == 422 and response.json()["detail"][0]["loc"] == ["query", "flight_id"]
    unchanged()


def test_ids_beyond_64_bits_in_a_body_or_options_are_422(
    client: TestClient, flight: int, unchanged: Callable[[], None]
) -> None:
    response = client.post("/api/jobs", json={"flight_id": TOO_BIG})
    assert response.status_code == 422
    assert response.json()["detail"][0]["loc"] == ["body", "flight_id"] and str(MAX_ID) in response.text
    options = survey_options({"width_mm": 100, "height_mm": 80}, calibration_job=TOO_BIG)
    del options["camera"]
    response = post_survey(client, options)
    assert response.status_code == 422 and "options.calibration_job" in response.json()["detail"]
    assert client.get(f"/api/jobs/{MAX_ID}").status_code == 404  # the largest id is merely unknown
    unchanged()


# -- A DJI XMP yaw of "e": HTTP 500 (float("e")) -> the value is ignored --------------------------------------


def jpeg_with_xmp(xmp: str) -> bytes:
    out = io.BytesIO()
    Image.new("RGB", (64, 48), (90, 120, 150)).save(out, "JPEG", xmp=xmp.encode())
    return out.getvalue()


def test_a_dji_attitude_that_is_not_a_number_is_ignored(client: TestClient, tmp_path: Path) -> None:
    xmp = (
        '<x:xmpmeta><rdf:Description drone-dji:FlightYawDegree="e" drone-dji:GimbalYawDegree="+12.5" '
        'drone-dji:GimbalPitchDegree="1e999" drone-dji:GimbalRollDegree="-." /></x:xmpmeta>'
    )
    flight_id = client.post("/api/flights", json={"name": "xmp"}).json()["id"]
    response = client.post(f"/api/flights/{flight_id}/images", files={"files": ("e.jpg", jpeg_with_xmp(xmp))})
    assert response.status_code == 201, response.text
    (image,) = response.json()["images"]
    assert image["yaw"] == 12.5  # the next name DJI writes it under
    assert image["pitch"] is None and image["roll"] is None
    (tmp_path / "e.jpg").write_bytes(jpeg_with_xmp(xmp))
    assert inspect_image(tmp_path / "e.jpg")["relative_altitude"] is None


# -- Deeply nested JSON: HTTP 500 (RecursionError) or 400 "error parsing the body" -> 422 naming the limit -----


def test_json_nested_too_deep_is_422_wherever_it_is_parsed(
    client: TestClient, flight: int, unchanged: Callable[[], None]
) -> None:
    deep = '{"points": ' + "[" * 5000 + "]" * 5000 + "}"
    limit = f"at most {MAX_JSON_DEPTH} are accepted"
    answers = [
        client.post("/api/calibrations", data={"options": deep}),
        post_survey(client, deep),
        put_gcps(client, flight, "ground_control_points.json", deep),
        client.post("/api/jobs", content=deep, headers={"content-type": "application/json"}),
        client.post("/api/flights", content=deep),  # no content type: FastAPI parses it as JSON too
    ]
    for response in answers:
        assert response.status_code == 422 and limit in response.json()["detail"], response.text
    assert answers[0].json()["detail"] == f"options: JSON nested 5001 levels deep; {limit}"
    assert answers[2].json()["detail"].startswith("ground_control_points.json: JSON nested 5001 levels deep")
    assert answers[3].json()["detail"].startswith("body: JSON nested")
    # brackets inside strings are text, not nesting; the deepest valid request is far below the limit
    assert nesting_depth('{"a": "[[[[{{{{", "b": [{"c": "\\"]]]"}]}') == 3
    assert nesting_depth('"' + '\\"' * 500_000) == 0  # an unclosed run of escaped quotes: linear, no backtracking
    big = client.post("/api/jobs", json={"flight_id": flight, "options": {"x": "y" * MAX_JSON_BYTES}})
    assert big.status_code == 413 and str(MAX_JSON_BYTES) in big.json()["detail"]
    unchanged()


# -- options.camera nested 300 deep on a planar job: stored, 500, then GET /api/jobs 500 forever -> 422 -------


@pytest.mark.parametrize("depth", [20, 300])
def test_a_camera_option_that_is_no_camera_is_refused_in_every_mode(
    client: TestClient, frames: list[Path], flight: int, unchanged: Callable[[], None], depth: int
) -> None:
    for mode in ("planar", "ortho"):
        body = {"flight_id": flight, "options": {"mode": mode, "camera": nested(depth)}}
        response = client.post("/api/jobs", json=body)
        assert response.status_code == 422, response.text
        detail = response.json()["detail"]
        assert detail.startswith("options.camera: camera.width") if depth < MAX_JSON_DEPTH else "nested" in detail
    bad = {**CAMERA, "fx": "wide"}
    response = client.post("/api/calibrations", data={"options": json.dumps({"method": "plumb_line", "camera": bad})})
    assert (
        response.status_code == 422 and response.json()["detail"] == "options.camera: camera.fx must be a finite number"
    )
    pair = [(side, (p.name, p.read_bytes(), "image/jpeg")) for side, p in zip(("left", "right"), frames, strict=True)]
    response = client.post("/api/stereo-rigs", data={"options": json.dumps({"right_camera": [1, 2]})}, files=pair)
    assert response.status_code == 422 and "options.right_camera" in response.json()["detail"]
    assert client.get("/api/jobs").status_code == 200
    unchanged()


# -- PLY with an unknown property type or without x: HTTP 500 (KeyError) -> 422 saying what is wrong ---------


PLY = (
    "ply\nformat ascii 1.0\nelement vertex 3\n{vertex}"
    "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
)
VERTICES = "0 0 0\n100 0 0\n0 80 0\n3 0 1 2\n"


@pytest.mark.parametrize(
    ("properties", "fragment"),
    [
        ("property float x\nproperty float y\nproperty quaternion z\n", "header line 6: unknown PLY property type"),
        ("property float u\nproperty float y\nproperty float z\n", "has no x property; it needs x, y and z"),
        ("property list uchar float x\nproperty float y\nproperty float z\n", "has no x property"),
        ("property float\nproperty float y\nproperty float z\n", "header line 4: expected 'property <type> <name>'"),
    ],
)
def test_a_ply_mesh_the_reader_does_not_understand_is_422(
    client: TestClient, unchanged: Callable[[], None], properties: str, fragment: str
) -> None:
    ply = PLY.format(vertex=properties) + VERTICES
    response = post_survey(client, survey_options({"mesh": "part.ply"}), ("part.ply", ply.encode()))
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert detail.startswith("options.specimen: part.ply: ") and fragment in detail
    unchanged()


# -- GCP file observations not a list: HTTP 500 (TypeError) -> 422 naming the entry --------------------------


def test_gcp_observations_that_are_not_a_list_are_422_naming_the_entry(
    client: TestClient, flight: int, unchanged: Callable[[], None]
) -> None:
    good = {"id": "g1", "position": {"latitude": 29.76, "longitude": -95.37, "altitude": 10.0}, "observations": []}
    points = [good, {**good, "id": "g2", "observations": 7}]
    response = put_gcps(client, flight, "ground_control_points.json", json.dumps({"points": points}))
    assert response.status_code == 422
    assert response.json()["detail"] == (
        "ground_control_points.json: points[1].observations: expected a list of {'shot_id': str, 'projection': [x, y]}"
    )
    unchanged()


# -- NaN and Infinity: accepted, stored, shown as null -> 422 naming the option ------------------------------


def test_nan_and_infinity_are_refused_naming_the_option(
    client: TestClient, flight: int, unchanged: Callable[[], None]
) -> None:
    for number in ("NaN", "Infinity", "-Infinity", "1e400"):
        body = f'{{"flight_id": {flight}, "options": {{"mode": "ortho", "ground_elevation_m": {number}}}}}'
        response = client.post("/api/jobs", content=body, headers={"content-type": "application/json"})
        assert response.status_code == 422, response.text
        assert response.json()["detail"].startswith("body.options.ground_elevation_m: ")
        assert response.json()["detail"].endswith("is not a finite number")
    options = survey_options({"width_mm": 100, "height_mm": 80})
    text = json.dumps(options).replace('"pixel": [100.0, 100.0]', '"pixel": [NaN, 100.0]')
    response = post_survey(client, text)
    assert response.status_code == 422
    assert (
        response.json()["detail"]
        == "options.stages[0].photos[0].control_points[0].pixel[0]: NaN is not a finite number"
    )
    unchanged()


def config_models() -> list[type[BaseModel]]:
    return [m for m in vars(config).values() if isinstance(m, type) and issubclass(m, BaseModel) and m is not BaseModel]


def test_every_float_option_refuses_nan_and_infinity_itself() -> None:
    """Past the API's JSON checks too (the CLI, a stored config): every model says allow_inf_nan=False."""
    for model in config_models():
        assert model.model_config.get("allow_inf_nan") is False, model.__name__
    for bad in (math.nan, math.inf):
        with pytest.raises(ValidationError, match="finite number"):
            build_config("mosaic", {"mode": "ortho", "ground_elevation_m": bad})
        with pytest.raises(ValidationError, match="finite number"):
            build_config("calibration", {"markers": [{"image": "a.jpg", "image_points": [[bad, 1.0]]}]})


# -- GCPs at latitude 95 or longitude 500: accepted -> 422 naming the line or the entry ----------------------


@pytest.mark.parametrize(
    ("name", "content", "detail"),
    [
        (
            "gcp_list.txt",
            "EPSG:4326\n-95.37 29.76 10 5 5 a.jpg g1\n-95.37 95 10 5 5 a.jpg g2\n",
            "line 3: latitude 95.0",
        ),
        ("gcp_list.txt", "EPSG:4326\n500 29.76 10 5 5 a.jpg g1\n", "line 2: longitude 500.0 is outside -180..180"),
        ("gcp_list.txt", "EPSG:32615\n1e300 1e300 10 5 5 a.jpg g1\n", "line 2: GCP 'g1' lies outside the area"),
        ("ground_control_points.json", "95", "points[0].position: latitude 95.0 is outside -90..90 degrees"),
        ("ground_control_points.json", "-91", "points[0].position: latitude -91.0"),
    ],
)
def test_gcps_off_the_globe_are_422_naming_the_line(
    client: TestClient, flight: int, unchanged: Callable[[], None], name: str, content: str, detail: str
) -> None:
    if name.endswith(".json"):
        position = {"latitude": float(content), "longitude": 10.0, "altitude": 0.0}
        content = json.dumps({"points": [{"id": "g1", "position": position, "observations": []}]})
    response = put_gcps(client, flight, name, content)
    assert response.status_code == 422 and response.json()["detail"].startswith(f"{name}: {detail}"), response.text
    unchanged()


# -- Options without an upper bound (min_inliers 1e18, 200 000 checkpoints): accepted -> 422 -----------------


def test_numbers_and_lists_beyond_their_bounds_are_422(
    client: TestClient, flight: int, unchanged: Callable[[], None]
) -> None:
    cases = [
        ({"min_inliers": 10**18}, "options.min_inliers: Input should be less than or equal to 100000"),
        ({"checkpoints": ["g"] * 200_000}, "options.checkpoints: List should have at most 1000 items"),
        ({"min_gps_frames": 10**9}, "options.min_gps_frames: Input should be less than or equal to 10000"),
        ({"ortho_dense_px": 10**6}, "options.ortho_dense_px: Input should be less than or equal to 4096"),
        ({"ortho_surface": "lidar"}, "options.ortho_surface: Input should be 'dense', 'tie_points' or 'plane'"),
    ]
    for options, detail in cases:
        response = client.post("/api/jobs", json={"flight_id": flight, "options": options})
        assert response.status_code == 422 and response.json()["detail"].startswith(detail), response.text
    unchanged()


VALIDATED_ELSEWHERE = {"pattern"}  # both ints checked to 2..100 by _check_pattern, with a hint


def unbounded(schema: dict, node: Any, path: str) -> list[str]:
    """Paths in a JSON schema of numbers without a maximum and arrays without maxItems."""
    if not isinstance(node, dict):
        return []
    if "$ref" in node:
        return unbounded(schema, schema["$defs"][node["$ref"].split("/")[-1]], path)
    found = []
    kind = node.get("type")
    if kind in ("integer", "number") and "maximum" not in node and "exclusiveMaximum" not in node:
        found.append(path)
    if kind == "array" and "maxItems" not in node:
        found.append(path)
    for key in ("anyOf", "prefixItems"):
        found += [p for k, item in enumerate(node.get(key, [])) for p in unbounded(schema, item, f"{path}[{k}]")]
    found += unbounded(schema, node.get("items"), f"{path}[]")
    for name, child in node.get("properties", {}).items():
        if name not in VALIDATED_ELSEWHERE:
            found += unbounded(schema, child, f"{path}.{name}")
    return found


def test_every_numeric_and_list_option_has_an_upper_bound_and_every_default_is_valid() -> None:
    for kind, model in JOB_KINDS.items():
        schema = model.model_json_schema()
        assert unbounded(schema, schema, str(kind)) == []
        if kind != "crack_survey":  # the others need no option; a survey's defaults are checked in its tests
            assert build_config(kind, {}).model_dump() == model().model_dump()  # validate_default: in bounds


# -- A crack survey's raster of 200001 x 200001 px: refused by the worker only -> 422 by the API --------------


def test_a_rectified_raster_over_the_workers_limit_is_422(client: TestClient, unchanged: Callable[[], None]) -> None:
    from workers.stages import rectify_specimen  # only to compare: the API never imports the stages

    assert MAX_RASTER_PIXELS == rectify_specimen.MAX_RASTER_PIXELS
    plate = survey_options({"width_mm": 1000, "height_mm": 1000}, mm_per_px=0.005)
    response = post_survey(client, plate)
    assert response.status_code == 422
    assert response.json()["detail"] == (
        "options.mm_per_px: Value error, the specimen is 200001 x 200001 px at 0.005 mm/px, "
        f"more than {MAX_RASTER_PIXELS} px; choose a coarser mm_per_px"
    )
    obj = grid_obj(1000.0, 600.0, 4)
    points = [[0, 0, 0], [1000, 0, 0], [0, 600, 0], [1000, 600, 0], [500, 400, 0], [200, 300, 0]]
    plane = [[0, 0, 0], [1000, 0, 0], [0, 600, 0]]  # the best-fit plane of a grid is a little askew
    mesh = survey_options({"mesh": "plate.obj", "plane": plane}, points, mm_per_px=0.005)
    response = post_survey(client, mesh, ("plate.obj", obj.encode()))
    assert response.status_code == 422
    assert response.json()["detail"].startswith("options.mm_per_px: plate.obj: the specimen is 200001 x 120001 px")
    unchanged()


def grid_obj(width_mm: float, height_mm: float, n: int) -> str:
    """A flat rectangle as an OBJ of n x n cells, two triangles each."""
    vertices = [f"v {i * width_mm / n} {j * height_mm / n} 0" for j in range(n + 1) for i in range(n + 1)]
    faces = []
    for j in range(n):
        for i in range(n):
            a = j * (n + 1) + i + 1
            faces += [f"f {a} {a + 1} {a + n + 2}", f"f {a} {a + n + 2} {a + n + 1}"]
    return "\n".join(vertices + faces) + "\n"


# -- A 422 echoed the whole refused input back -> at most MAX_ECHO_CHARS of it --------------------------------


def test_a_422_never_echoes_a_huge_input(client: TestClient, unchanged: Callable[[], None]) -> None:
    for body in ({"name": "x" * 500_000}, {"name": "f", "description": ["d"] * 100_000}):
        response = client.post("/api/flights", json=body)
        assert response.status_code == 422 and len(response.content) < 2000
        (problem,) = response.json()["detail"]
        assert problem["msg"] and len(problem["input"]) <= MAX_ECHO_CHARS + 3
    response = client.post("/api/flights", json={"name": "a\x00b"})
    assert response.status_code == 422 and "NUL" in response.text
    unchanged()


def test_a_blank_flight_name_is_422(client: TestClient, unchanged: Callable[[], None]) -> None:
    response = client.post("/api/flights", json={"name": " \t "})
    assert response.status_code == 422 and "blank" in response.text
    unchanged()
    named = client.post("/api/flights", json={"name": "  north field  "}).json()
    assert named["name"] == "north field"
