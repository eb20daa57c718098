"""Every identifier the API and the reports can emit has a display name (core.labels), and the viewer's copy
(web/labels.js) is the same table."""

from __future__ import annotations

import inspect
import re
from pathlib import Path
from typing import get_args

from core.eta import BASES
from core.kinds import JobKind, JobStatus
from core.labels import LABELS, javascript, label
from workers.algorithms.geometry.camera import CONVENTIONS
from workers.algorithms.sfm import DATUMS, GCP_ROLES, IMAGE_STATUSES
from workers.config import MosaicConfig
from workers.pipeline import PIPELINES

LABELS_JS = Path(__file__).resolve().parents[2] / "web" / "labels.js"


def emitted() -> dict[str, set[str]]:
    """category -> every value the code can put in a job record or report under it."""
    from workers.stages import adjust_bundle

    literal = {name: set(get_args(MosaicConfig.model_fields[name].annotation)) for name in ("mode", "blend")}
    source = inspect.getsource(adjust_bundle.triangulation_report)
    return {
        "kind": {k.value for k in JobKind},
        "status": {s.value for s in JobStatus},
        "stage": {spec.name for specs in PIPELINES.values() for spec in specs},
        "mode": literal["mode"],
        "blend": literal["blend"],
        "resolution": set(get_args(MosaicConfig.model_fields["output_resolution"].annotation)),
        "feature_type": set(get_args(MosaicConfig.model_fields["feature_type"].annotation)),
        "datum": set(DATUMS),
        "image_status": set(IMAGE_STATUSES),
        "gcp_role": set(GCP_ROLES),
        "camera_parameter": set(re.findall(r'"(\w+)": \{"initial"', source)),
        "eta_basis": set(BASES),
        "convention": set(CONVENTIONS),
    }


def test_every_value_the_api_emits_has_a_display_name() -> None:
    for category, values in emitted().items():
        assert values, f"found no {category} values: the test no longer reads them"
        missing = values - set(LABELS.get(category, {}))
        assert not missing, f"no display name for {category} {sorted(missing)} (add them to core/labels.py)"


def test_display_names_are_words_not_identifiers() -> None:
    for category, names in LABELS.items():
        for value, name in names.items():
            assert name and "_" not in name and name != value, (category, value, name)
    assert label("datum", "gps_line_level_cameras").startswith("Fitted to the GPS")
    assert label("camera_parameter", "focal_px_original") == "Focal length (px of the full-size photo)"
    assert label("stage", "something_new") == "something_new"  # shown as it is, never dropped


def test_the_viewer_has_the_same_table() -> None:
    assert LABELS_JS.read_text(encoding="utf-8") == javascript(), "regenerate: python -m core.labels > web/labels.js"
