"""NodeODM-compatible routes (``api.nodeodm``): WebODM adds this service as a processing node with its URL and
a token, e.g. ``http://survey.example.org:8000`` and an API token of the user the tasks should belong to.

NodeODM clients send the token as ``?token=`` (NodeODM's own scheme); these routes, and only these, take it
there (or as ``Authorization: Bearer``). Answers use NodeODM's field names; a refusal carries NodeODM's
``{"error": ...}`` beside our ``{"detail": ...}``, with an HTTP status that says what it is (401, 404, 409,
413, 422), so PyODM raises on it either way. A task of another user answers 404, as one that does not exist.
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from typing import Annotated, Any

from fastapi import APIRouter, Depends, File, Form, Header, Query, Request, Response, UploadFile
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, StreamingResponse
from fastapi.routing import APIRoute
from starlette.concurrency import run_in_threadpool

from api import nodeodm
from api.auth import token_cache
from api.deps import DbDep, QueueDep, SettingsDep
from api.errors import ApiError, ConflictError, InvalidInputError, UnauthorizedError
from api.gcp_service import MAX_GCP_BYTES, store_gcps
from api.gps_service import store_gps
from api.limits import MAX_GPS_BYTES, parse_json
from api.uploads import display_name, store_uploads
from api.zipstream import zip_chunks
from core import accounts
from core.accounts import Principal


class NodeOdmRoute(APIRoute):
    """Answers every refusal of these routes (ours and FastAPI's 422) with NodeODM's ``error`` field too."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def handle(request: Request) -> Response:
            try:
                return await handler(request)
            except ApiError as exc:
                body = {"error": exc.detail, "detail": exc.detail}
                return JSONResponse(body, status_code=exc.status_code, headers=exc.headers)
            except RequestValidationError as exc:
                problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors()[:5])
                return JSONResponse({"error": problems, "detail": problems}, status_code=422)

        return handle


def node_user(
    request: Request,
    tokens: Annotated[accounts.TokenCache, Depends(token_cache)],
    token: Annotated[str | None, Query(max_length=512, description="an API token (NodeODM's scheme)")] = None,
) -> Principal:
    """The user of ``?token=`` or of ``Authorization: Bearer``; 401 without a valid one."""
    scheme, _, bearer = request.headers.get("authorization", "").partition(" ")
    secret = (token or (bearer if scheme.lower() == "bearer" else "")).strip()
    if not secret:
        raise UnauthorizedError("this node needs a token: add ?token=<API token> to its URL")
    principal = tokens.authenticate(secret)
    if principal is None:
        raise UnauthorizedError("the token is unknown or revoked")
    return principal


NodeUser = Annotated[Principal, Depends(node_user)]
router = APIRouter(tags=["NodeODM"], route_class=NodeOdmRoute)


@router.get("/info")
def info(_user: NodeUser, db: DbDep) -> dict[str, Any]:
    """NodeODM's node information (``engine``: fotoskhema)."""
    return nodeodm.node_info(db)


@router.get("/options")
def options(_user: NodeUser) -> list[dict[str, Any]]:
    """The options a task may set: NodeODM names, types, defaults, domains, help."""
    return nodeodm.node_options()


@router.post("/task/new/init")
def init(
    user: NodeUser,
    db: DbDep,
    name: Annotated[str, Form(max_length=1000)] = "",
    options: Annotated[str, Form(max_length=1024 * 1024)] = "[]",
    set_uuid: Annotated[str | None, Header(alias="set-uuid", max_length=64)] = None,
) -> dict[str, str]:
    """A new task; its photos follow with ``task/new/upload/{uuid}``. ``webhook``, ``skipPostProcessing``,
    ``outputs`` and ``dateCreated`` are accepted and not used (this node calls no URL it is given)."""
    return {"uuid": nodeodm.init_task(db, user, name, options, set_uuid)}


@router.post("/task/new/upload/{uuid}")
async def upload(
    uuid: str, user: NodeUser, db: DbDep, settings: SettingsDep, images: list[UploadFile] = File(...)
) -> dict[str, bool]:
    """Photos of the task, and its ``geo.txt`` or ``gcp_list.txt``; a photo sent again is taken as sent."""
    task = await run_in_threadpool(nodeodm.task_or_404, db, uuid, user)
    if task.job_id is not None:
        raise ConflictError(f"task {task.uuid} is committed: it takes no more files")
    photos = [f for f in images if nodeodm.side_file_kind(display_name(f.filename)) is None]
    for side in (f for f in images if f not in photos):
        name = display_name(side.filename)
        if (kind := nodeodm.side_file_kind(name)) == "unused":
            continue
        store = store_gps if kind == "gps" else store_gcps
        content = await side.read((MAX_GPS_BYTES if store is store_gps else MAX_GCP_BYTES) + 1)
        await run_in_threadpool(store, db, settings.data_dir, task.flight_id, name, content)
    if photos:
        try:
            await store_uploads(db, settings, task.flight_id, photos)
        except ConflictError as exc:  # the same photo again (a client's retry): already there
            if "already in this flight" not in exc.detail:
                raise
    return {"success": True}


@router.post("/task/new/commit/{uuid}")
def commit(uuid: str, user: NodeUser, db: DbDep, settings: SettingsDep, queue: QueueDep) -> dict[str, str]:
    """Start the task (a mosaic job of its photos)."""
    task = nodeodm.task_or_404(db, uuid, user)
    nodeodm.commit_task(db, settings, queue, task, user)
    return {"uuid": task.uuid}


@router.get("/task/list")
def task_list(user: NodeUser, db: DbDep) -> list[dict[str, str]]:
    """Your tasks (every task for an admin)."""
    return [{"uuid": u} for u in nodeodm.task_ids(db, user)]


@router.get("/task/{uuid}/info")
def task_info(
    uuid: str, user: NodeUser, db: DbDep, with_output: Annotated[int | None, Query(ge=-100_000, le=100_000)] = None
) -> dict[str, Any]:
    """NodeODM's TaskInfo: status code (10 queued, 20 running, 30 failed, 40 completed, 50 canceled), progress."""
    return nodeodm.task_info(db, nodeodm.task_or_404(db, uuid, user), with_output)


@router.get("/task/{uuid}/output")
def task_output(
    uuid: str, user: NodeUser, db: DbDep, line: Annotated[int, Query(ge=-100_000, le=100_000)] = 0
) -> list[str]:
    """The task's console output from line ``line`` (negative: the last lines)."""
    lines = nodeodm.output_lines(db, nodeodm.task_or_404(db, uuid, user))
    return lines[line:]


@router.get("/task/{uuid}/download/{asset}", responses={200: {"content": {"application/zip": {}}}})
def download(uuid: str, asset: str, user: NodeUser, db: DbDep, settings: SettingsDep) -> StreamingResponse:
    """``all.zip``: the finished task's outputs in ODM's layout (the orthophoto as
    ``odm_orthophoto/odm_orthophoto.tif``), streamed."""
    task = nodeodm.task_or_404(db, uuid, user)
    if asset != "all.zip":
        raise InvalidInputError("Invalid asset")
    entries = nodeodm.archive_entries(settings, db, task)
    headers = {"Content-Disposition": 'attachment; filename="all.zip"'}
    return StreamingResponse(zip_chunks(entries), media_type="application/zip", headers=headers)


@router.post("/task/cancel")
async def cancel(request: Request, user: NodeUser, db: DbDep) -> dict[str, bool]:
    """Stop the task (form or JSON field ``uuid``)."""
    task = await run_in_threadpool(nodeodm.task_or_404, db, await _uuid_of(request), user)
    await run_in_threadpool(nodeodm.cancel_task, db, task)
    return {"success": True}


@router.post("/task/remove")
async def remove(request: Request, user: NodeUser, db: DbDep, settings: SettingsDep) -> dict[str, bool]:
    """Delete the task with its photos and outputs (form or JSON field ``uuid``)."""
    task = await run_in_threadpool(nodeodm.task_or_404, db, await _uuid_of(request), user)
    await run_in_threadpool(nodeodm.remove_task, db, settings, task)
    return {"success": True}


async def _uuid_of(request: Request) -> str:
    """The ``uuid`` of a form (PyODM) or JSON body."""
    if request.headers.get("content-type", "").split(";")[0].strip().lower() == "application/json":
        body = parse_json(await request.body(), "body")
        value = body.get("uuid") if isinstance(body, dict) else None
    else:
        value = (await request.form()).get("uuid")
    if not isinstance(value, str) or not value.strip():
        raise InvalidInputError("uuid param missing.")
    return value.strip()[:64]
