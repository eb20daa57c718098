"""A property-based fuzz of the API from its own OpenAPI schema: whatever the request, never a 5xx.

For every route of ``create_app(settings).openapi()`` (but the event stream, which follows a live job
forever), Hypothesis builds requests from the schema: path and query parameters, JSON bodies, the
``options`` of ``POST /api/jobs`` and of the multipart routes from the config model they are validated
with, and the multipart routes' files from a small set of photos, meshes, GCP files and junk. Values mostly
fit the schema, and are often the ones an attacker sends instead: wrong types, ids beyond 64 bits, NaN and
Infinity, 1e400, NUL characters, lone surrogates, long strings, JSON nested past the limit, broken JSON. The
app holds a flight with photos, a queued mosaic job, a finished calibration, a finished stereo rig and a
finished stereo DEM with its rasters, so that ids 1-4 reach the code behind the 404s.

Deterministic (``derandomize``, no example database) and sized to run in well under a minute on two cores.
"""

from __future__ import annotations

import io
import json
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from api.main import create_app
from core.db import Database, Job
from core.kinds import JobKind, JobStatus
from core.settings import Settings
from tests.conftest import RecordingQueue, admin_client, fresh_database
from workers.algorithms.calibration import StereoRig
from workers.algorithms.geometry import Camera
from workers.config import JOB_KINDS
from workers.raster_io import write_array_cog, write_rgb_cog
from workers.workspace import job_workspace

EXAMPLES = 100  # requests per route and database: about 5000 requests in all
SKIPPED = {("get", "/api/jobs/{job_id}/events")}  # an event stream of a live job never ends
OPTIONS_MODELS = {  # the config model a route's ``options`` are validated with
    "/api/jobs": JobKind.mosaic,
    "/api/calibrations": JobKind.calibration,
    "/api/stereo-rigs": JobKind.stereo_calibration,
    "/api/crack-surveys": JobKind.crack_survey,
    "/api/stereo-dems": JobKind.stereo_dem,
}
CAMERA = Camera(64, 48, 60.0, 60.0, 32.0, 24.0)


def _operations() -> list[tuple[str, str, dict[str, Any], dict[str, Any]]]:
    with tempfile.TemporaryDirectory() as folder:
        schema = create_app(Settings(data_dir=Path(folder)), queue=RecordingQueue()).openapi()
    found = [
        (method, path, operation, schema["components"]["schemas"])
        for path, operations in schema["paths"].items()
        for method, operation in operations.items()
        if (method, path) not in SKIPPED
    ]
    # Deletions last (they take the seeded records away), and revoking tokens after everything: it may revoke
    # the fuzzing client's own token.
    return sorted(found, key=lambda op: (op[0] == "delete", op[1] == "/api/tokens/{token_id}"))


OPERATIONS = _operations()


# -- Values from a JSON schema, and values that break it ------------------------------------------------------


def nested(depth: int) -> Any:
    value: Any = []
    for _ in range(depth - 1):
        value = [value]
    return value


HOSTILE = st.sampled_from(
    [
        2**63 - 1,
        2**63,
        2**64,
        -(2**63) - 1,
        10**40,
        0,
        -1,
        1e308,
        -1e308,
        5e-324,
        float("nan"),
        float("inf"),
        float("-inf"),
        "NaN",
        "Infinity",
        "1e400",
        "-0",
        "",
        " ",
        "\x00",
        "a\x00b",
        "\u202e\ufeff",
        "x" * 3000,
        "../../etc/passwd",
        "a.jpg",
        "a.png",
        None,
        True,
        False,
        [],
        {},
        nested(5),
        nested(40),
        {"a": {"b": {"c": [1, "2", None]}}},
    ]
)
JSON_LEAF = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=20))
JSON_ANY = st.recursive(
    JSON_LEAF,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
    max_leaves=8,
)


def values(schema: dict[str, Any], defs: dict[str, Any], hostile: bool, depth: int = 0) -> st.SearchStrategy[Any]:
    """Values that fit ``schema``; if ``hostile``, a quarter of them (at every level) hostile ones or any JSON."""
    fitting = st.deferred(lambda: fit(schema, defs, hostile, depth))
    return st.one_of(fitting, fitting, fitting, HOSTILE | JSON_ANY) if hostile else fitting


def fit(schema: dict[str, Any], defs: dict[str, Any], hostile: bool, depth: int) -> st.SearchStrategy[Any]:
    if "$ref" in schema:
        return fit(defs[schema["$ref"].split("/")[-1]], defs, hostile, depth)
    for key in ("anyOf", "oneOf"):
        if key in schema:
            return st.one_of([fit(s, defs, hostile, depth) for s in schema[key]])
    if "allOf" in schema:
        return fit(schema["allOf"][0], defs, hostile, depth)
    if "enum" in schema or "const" in schema:
        return st.sampled_from(schema.get("enum", [schema.get("const")]))
    kind = schema.get("type")
    if kind == "integer":
        low, high = schema.get("minimum"), schema.get("maximum")
        edges = [v + d for v in (low, high) if v is not None for d in ((-1, 0, 1) if hostile else (0,))]
        return st.integers(low, high) | (st.sampled_from(edges) if edges else st.integers())
    if kind == "number":
        low = schema.get("minimum", schema.get("exclusiveMinimum"))
        high = schema.get("maximum", schema.get("exclusiveMaximum"))
        inside = st.floats(
            low,
            high,
            allow_nan=False,
            allow_infinity=False,
            exclude_min="exclusiveMinimum" in schema,
            exclude_max="exclusiveMaximum" in schema,
        )
        return inside | st.sampled_from([v for v in (low, high, 0.0) if v is not None])
    if kind == "string":
        return st.text(max_size=min(schema.get("maxLength", 30), 30), min_size=schema.get("minLength", 0))
    if kind == "boolean":
        return st.booleans()
    if kind == "null":
        return st.none()
    if kind == "array":
        if "prefixItems" in schema:
            return st.tuples(*[values(s, defs, hostile, depth + 1) for s in schema["prefixItems"]]).map(list)
        items = values(schema.get("items", {}), defs, hostile, depth + 1) if depth < 6 else JSON_LEAF
        return st.lists(items, min_size=schema.get("minItems", 0), max_size=min(schema.get("maxItems", 4), 4))
    if kind == "object" or "properties" in schema:
        properties = schema.get("properties", {})
        required = set(schema.get("required", []))
        child = (lambda s: values(s, defs, hostile, depth + 1)) if depth < 6 else (lambda s: JSON_LEAF)
        return st.fixed_dictionaries(
            {k: child(s) for k, s in properties.items() if k in required},
            optional={k: child(s) for k, s in properties.items() if k not in required},
        ) | (st.dictionaries(st.text(max_size=8), JSON_ANY, max_size=3) if not properties else st.nothing())
    return JSON_ANY


def options_schema(path: str) -> dict[str, Any]:
    return JOB_KINDS[OPTIONS_MODELS[path]].model_json_schema()


def json_text(value: Any) -> str:
    try:
        return json.dumps(value)  # NaN and Infinity as the tokens Python writes for them
    except ValueError:  # an integer too long for Python to print
        return '{"id": ' + "9" * 5000 + "}"


BROKEN_JSON = st.sampled_from(
    ['{"a": 1', "[" * 50_000, '{"a": ' * 100 + "1" + "}" * 100, "1" * 5000, "nul", '"\\ud800"', "\xff\xfe", ""]
)


def json_texts(schema: dict[str, Any], defs: dict[str, Any]) -> st.SearchStrategy[str]:
    """JSON text of a document that fits ``schema`` (as far as its types and bounds go), of one with hostile
    values at any level, or broken JSON."""
    fitting = values(schema, defs, False).map(json_text)
    return st.one_of(fitting, fitting, values(schema, defs, True).map(json_text), BROKEN_JSON)


# -- Files a multipart route may be sent ---------------------------------------------------------------------


def _image(fmt: str, xmp: bytes = b"") -> bytes:
    out = io.BytesIO()
    pixels = np.random.default_rng(len(fmt) + len(xmp)).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(out, fmt, **({"xmp": xmp} if xmp else {}))
    return out.getvalue()


FILES = st.sampled_from(
    [
        ("a.jpg", _image("JPEG")),
        ("b.png", _image("PNG")),
        ("c.jpg", _image("JPEG", b'<x drone-dji:FlightYawDegree="e" drone-dji:GimbalPitchDegree="-1e999"/>')),
        ("d.jpg", _image("JPEG")[:200]),
        ("e.jpg", b""),
        ("f.jpg", b"\x89PNG\r\n\x1a\n" + b"\x00" * 64),
        ("m.obj", b"v 0 0 0\nv 100 0 0\nv 0 80 0\nf 1 2 3\n"),
        ("m.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty half x\nend_header\n0\n"),
        ("m.stl", b"solid x\nendsolid\n"),
        ("gcp_list.txt", b"EPSG:4326\n500 95 0 1 1 a.jpg g\n"),
        ("gcp_list.txt", b"WGS84 UTM 99N\n"),
        ("ground_control_points.json", b'{"points": [{"id": 1, "observations": {"a": 1}}]}'),
        ("ground_control_points.json", b'{"points": [{"id": "g", "position": {"latitude": 1e400}}]}'),
        ("../../x.jpg", b"\x00" * 10),
    ]
)


def multipart(path: str, operation: dict[str, Any], defs: dict[str, Any]) -> st.SearchStrategy[dict[str, Any]]:
    """``data`` (the ``options`` field) and ``files`` of a multipart request."""
    body = defs[operation["requestBody"]["content"]["multipart/form-data"]["schema"]["$ref"].split("/")[-1]]
    fields = list(body["properties"])
    data = {}
    if "options" in fields:
        options = options_schema(path)
        data["options"] = json_texts(options, options.get("$defs", {})) | st.text(max_size=20)
    per_field = [
        st.lists(FILES, max_size=3).map(lambda f, k=k: [(k, file) for file in f]) for k in fields if k != "options"
    ]
    files = st.tuples(*per_field).map(lambda lists: [f for field in lists for f in field])
    return st.fixed_dictionaries({"data": st.fixed_dictionaries(data), "files": files})


# -- Requests ------------------------------------------------------------------------------------------------


SEEDED = st.sampled_from([1, 2, 3, 4])  # ids that exist (see ``seed``)
PARAMETER = st.one_of(
    SEEDED,
    SEEDED,
    SEEDED,
    st.integers(-3, 4),
    st.integers(),
    st.sampled_from([2**63 - 1, 2**63, 2**64, -(2**63) - 1, 10**30, "1e3", "0x10", "1.5", "", "NaN", "१२"]),
    st.text(max_size=12),
)


# Header parameters (the tus upload routes'): the values they take, numbers past 64 bits, junk
HEADER = st.one_of(
    st.sampled_from(
        [
            "1.0.0",
            "1.0.0",
            "0",
            "1",
            "100",
            "-1",
            "18446744073709551616",
            "1e3",
            "filename YS5qcGc=",
            "filename",
            "filename YS5qcGc=,filename Yg==",
            "sha256 " + "A" * 43 + "=",
            "sha1 x",
            ",",
            "",
        ]
    ),
    st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=20),
)


def requests_for(method: str, path: str, operation: dict[str, Any], defs: dict[str, Any]) -> st.SearchStrategy:
    parameters = operation.get("parameters", [])
    in_path = {p["name"]: PARAMETER for p in parameters if p["in"] == "path"}
    in_query = {p["name"]: PARAMETER for p in parameters if p["in"] == "query"}
    in_header = {p["name"]: HEADER for p in parameters if p["in"] == "header"}
    content = operation.get("requestBody", {}).get("content", {})
    body: st.SearchStrategy[dict[str, Any]] = st.just({})
    if "application/json" in content:
        schema = dict(defs[content["application/json"]["schema"]["$ref"].split("/")[-1]])
        if path in OPTIONS_MODELS:  # JobCreate.options: the mosaic config's schema
            options = options_schema(path)
            schema["properties"] = {**schema["properties"], "options": options}
            defs = {**defs, **options.get("$defs", {})}
        content_type = st.sampled_from(["application/json"] * 4 + ["", "text/plain", "application/geo+json"])
        body = st.fixed_dictionaries({"content": json_texts(schema, defs), "content_type": content_type})
    elif "multipart/form-data" in content:
        body = multipart(path, operation, defs)

    def build(drawn: tuple[dict[str, Any], dict[str, Any], dict[str, Any], dict[str, str]]) -> dict[str, Any]:
        path_values, query, payload, headers = drawn
        url = path
        for name, value in path_values.items():
            url = url.replace("{" + name + "}", quote(str(value), safe="") or "%20")
        request: dict[str, Any] = {"method": method, "url": url, "params": {k: str(v) for k, v in query.items()}}
        if headers:
            request["headers"] = headers
        if "content" in payload:
            request["content"] = payload["content"].encode("utf-8", "surrogatepass")
            content_type = {"content-type": payload["content_type"]} if payload["content_type"] else {}
            request["headers"] = {**headers, **content_type}
        elif payload:
            # without files httpx would send the form urlencoded, not as multipart
            request["data"], request["files"] = payload["data"], payload["files"] or [("_", ("empty", b""))]
        return request

    query = st.fixed_dictionaries({}, optional=in_query)
    headers = st.fixed_dictionaries({}, optional=in_header)
    return st.tuples(st.fixed_dictionaries(in_path), query, body, headers).map(build)


# -- The app under fuzz --------------------------------------------------------------------------------------


def seed(client: TestClient, settings_: Settings) -> None:
    """Flight 1 with two photos and job 1 (a queued mosaic); job 2 a finished calibration, job 3 a rig."""
    flight = client.post("/api/flights", json={"name": "fuzz"}).json()["id"]
    photos = [("files", (f"p{k}.jpg", _image("JPEG", b"x" * k))) for k in range(2)]
    assert client.post(f"/api/flights/{flight}/images", files=photos).status_code == 201
    assert client.post("/api/jobs", json={"flight_id": flight}).status_code == 202
    db = Database(settings_.resolved_database_url())
    rig = StereoRig(CAMERA, CAMERA, np.eye(3), np.array([-100.0, 0.0, 0.0]))
    results = {JobKind.calibration: {"camera": CAMERA.to_json()}, JobKind.stereo_calibration: {"rig": rig.to_json()}}
    for kind, result in results.items():
        with db.session() as s:
            job = Job(flight_id=None, kind=kind, options={}, status=JobStatus.succeeded)
            s.add(job)
            s.flush()
            ws = job_workspace(settings_.data_dir, job.id)
            ws.save_config(JOB_KINDS[kind]().model_dump())
            ws.save_inputs([{"name": "a.jpg", "side": "", "pair": 0, "width": 64, "height": 48}])
            ws.save_calibration(result)
    _seed_stereo_dem(db, settings_)
    db.engine.dispose()


def _seed_stereo_dem(db: Database, settings_: Settings) -> None:
    """Job 4: a finished stereo DEM with a small DSM, its mask, a disparity map and their pictures."""
    with db.session() as s:
        job = Job(flight_id=None, kind=JobKind.stereo_dem, options={}, status=JobStatus.succeeded)
        s.add(job)
        s.flush()
        ws = job_workspace(settings_.data_dir, job.id)
    ws.save_config(JOB_KINDS[JobKind.stereo_dem](geometry="rpc").model_dump())
    ws.save_inputs([])
    heights = np.linspace(400, 450, 48 * 64, dtype=np.float32).reshape(48, 64)
    transform = (1.0, 0.0, 500_000.0, 0.0, -1.0, 5_000_000.0)
    write_array_cog(ws.dsm_path(), heights, transform=transform, epsg=32632, nodata=-9999.0)
    write_array_cog(ws.dsm_mask_path(), np.ones((48, 64), np.uint8), transform=transform, epsg=32632, nodata=0)
    write_array_cog(ws.disparity_path(), heights - 420, nodata=float("nan"))
    write_array_cog(ws.confidence_path(), np.ones((48, 64), np.float32))
    rgb, shown = np.full((48, 64, 3), 120, np.uint8), np.ones((48, 64), bool)
    write_rgb_cog(ws.dsm_view_path(), ws.view_scratch_path("dsm"), rgb, shown, crs=32632, transform=transform)
    write_rgb_cog(ws.disparity_view_path(), ws.view_scratch_path("disparity"), rgb, shown)


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def fuzzed(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    url = fresh_database(request.getfixturevalue("postgres_base_url")) if request.param == "postgresql" else ""
    app_settings = Settings(
        data_dir=tmp_path_factory.mktemp("fuzz") / "data", database_url=url, redis_url="redis://127.0.0.1:1/0"
    )
    with admin_client(app_settings, RecordingQueue()) as client:
        seed(client, app_settings)
        yield client


@pytest.mark.parametrize(
    ("method", "path", "operation", "defs"), OPERATIONS, ids=[f"{m.upper()} {p}" for m, p, _, _ in OPERATIONS]
)
def test_no_request_built_from_the_schema_is_answered_5xx(
    fuzzed: TestClient, method: str, path: str, operation: dict[str, Any], defs: dict[str, Any]
) -> None:
    @settings(
        max_examples=EXAMPLES,
        derandomize=True,
        database=None,
        deadline=None,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    @given(request=requests_for(method, path, operation, defs))
    def answered_without_5xx(request: dict[str, Any]) -> None:
        response = fuzzed.request(**request)  # a server exception is raised here, with its traceback
        assert response.status_code < 500, (response.status_code, response.text[:500])
        if response.status_code >= 400 and method != "head":  # an answer to HEAD has no body
            assert "detail" in response.json()

    answered_without_5xx()
