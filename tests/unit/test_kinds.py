"""One set of job kinds and statuses: ``core.kinds`` in Python, ``web/kinds.js`` in the viewer, the same names
and values; and the API's request schema names only kinds that exist."""

from __future__ import annotations

import enum
import re
from pathlib import Path
from typing import get_args

import pytest

from api.models import JobCreate
from core.kinds import JobKind, JobStatus
from workers.config import JOB_KINDS
from workers.pipeline import PIPELINES, VARIANT_OPTIONS, job_kind

KINDS_JS = Path(__file__).resolve().parents[2] / "web" / "kinds.js"
# export const Name = Object.freeze({ KEY: "value", ... }); over one line or several
FROZEN = re.compile(r"export\s+const\s+(\w+)\s*=\s*Object\.freeze\(\s*\{(.*?)\}\s*\)\s*;", re.DOTALL)
ENTRY = re.compile(r"""\s*([A-Z_][A-Z0-9_]*)\s*:\s*(["'])([^"']*)\2\s*""")


def js_enums(text: str) -> dict[str, dict[str, str]]:
    """``{const name: {key: value}}`` of the frozen objects a module exports; fails on an entry it cannot read."""
    enums = {}
    for name, body in FROZEN.findall(text):
        body = re.sub(r"//[^\n]*|/\*.*?\*/", "", body, flags=re.DOTALL)
        entries = [e for e in body.split(",") if e.strip()]  # a trailing comma is allowed
        parsed = [ENTRY.fullmatch(e) for e in entries]
        assert all(parsed), f"{name}: cannot read {[e for e, m in zip(entries, parsed, strict=True) if not m]}"
        enums[name] = {m[1]: m[3] for m in parsed if m}
    return enums


def python_enum(members: type[enum.StrEnum]) -> dict[str, str]:
    return {m.name.upper(): m.value for m in members}


def test_the_parser_reads_one_line_and_several() -> None:
    text = (
        'export const A = Object.freeze({ X: "x", Y_Z: "y_z" });\n'
        "export const B = Object.freeze({\n  P: 'p', // the first\n  Q: \"q\",\n});\n"
    )
    assert js_enums(text) == {"A": {"X": "x", "Y_Z": "y_z"}, "B": {"P": "p", "Q": "q"}}


def test_the_viewer_names_the_same_kinds_and_statuses() -> None:
    if not KINDS_JS.exists():
        pytest.fail(f"{KINDS_JS} is missing: the viewer's copy of the job kinds and statuses")
    enums = js_enums(KINDS_JS.read_text(encoding="utf-8"))
    assert enums.get("JobKind") == python_enum(JobKind)
    assert enums.get("JobStatus") == python_enum(JobStatus)


def test_every_kind_has_a_config_and_a_pipeline() -> None:
    assert set(JOB_KINDS) == set(JobKind)
    assert {job_kind(p) for p in PIPELINES} == set(JobKind)
    assert set(VARIANT_OPTIONS) <= set(JobKind)


def test_the_job_request_names_a_known_kind() -> None:
    """``JobCreate.kind`` is a plain Literal (for its 422 wording); it must spell a JobKind."""
    literal = JobCreate.model_fields["kind"].annotation
    assert [JobKind(v) for v in get_args(literal)] == [JobKind.mosaic]


def test_statuses_finished() -> None:
    assert {s for s in JobStatus if s.finished} == {JobStatus.succeeded, JobStatus.failed, JobStatus.cancelled}
    assert JobStatus("queued") is JobStatus.queued and f"{JobStatus.queued}" == "queued"
