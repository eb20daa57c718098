"""``report.html`` and its pictures: written by ``write_report``, self-contained (nothing fetched, no script),
every name escaped, the overlap counts and residual arrows right on planted geometry, plain-language advice
where the numbers call for it."""

from __future__ import annotations

import json
import re
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from tests.scenes import make_flight
from workers.config import MosaicConfig
from workers.pipeline import process_directory
from workers.report_html import FigureData, figures, overlap_svg, positions_svg, report_page
from workers.stages.write_report import _advice, _coverage
from workers.workspace import REPORT_FIGURES, JobWorkspace

SVG = "{http://www.w3.org/2000/svg}"
HOSTILE = '<img src=x onerror="alert(1)">&.jpg'


@pytest.fixture(scope="module")
def job(tmp_path_factory: pytest.TempPathFactory) -> JobWorkspace:
    """Four synthetic frames with GPS through the pipeline; one photo's name is markup."""
    root = tmp_path_factory.mktemp("report")
    flight = make_flight(root / "frames", n_frames=4, frame_size=(360, 270), seed=2)
    shutil.move(flight.paths[1], flight.paths[1].with_name(HOSTILE))
    process_directory(root / "frames", root / "job", {"working_max_px": 360})
    return JobWorkspace(root / "job")


def test_the_report_page_is_self_contained_and_lists_its_outputs(job: JobWorkspace) -> None:
    page = (job.root / "report.html").read_text(encoding="utf-8")
    assert page.startswith("<!doctype html>") and "<script" not in page.lower()
    external = re.findall(r"""(?:src|href)\s*=\s*["'](?!data:|#)([^"']*)""", page)
    assert external == []  # nothing is fetched: pictures are inline SVG, rasters data URIs
    assert page.count("<svg") == 4 and "<style>" in page
    outputs = job.outputs()
    assert {"report.html", *REPORT_FIGURES} <= set(outputs)
    for name in REPORT_FIGURES:  # each picture is also a standalone SVG document, the same one
        text = outputs[name].read_text(encoding="utf-8")
        assert ET.fromstring(text).tag == f"{SVG}svg" and text in page


def test_every_name_is_escaped(job: JobWorkspace) -> None:
    page = (job.root / "report.html").read_text(encoding="utf-8")
    assert HOSTILE not in page and "<img" not in page
    assert "&lt;img src=x onerror=&quot;alert(1)&quot;&gt;&amp;.jpg" in page
    for name in REPORT_FIGURES:
        ET.fromstring((job.root / name).read_text(encoding="utf-8"))  # well-formed XML whatever the names held


def test_the_page_has_the_tables_in_words(job: JobWorkspace) -> None:
    page = (job.root / "report.html").read_text(encoding="utf-8")
    report = job.load_report()
    table = page.split("<h2>Photo pairs</h2>")[1].split("</table>")[0]
    assert table.count("<tr>") == len(report["pairs"]) + 1
    times = page.split("<h2>Processing time</h2>")[1]
    assert "Finding features" in times and "detect_features" not in page  # stage names as words
    assert "Planar (flat ground)" in page and "EPSG:32615" in page


def test_overlap_counts_on_planted_footprints() -> None:
    square = np.array([[0, 0], [100, 0], [100, 100], [0, 100]], np.float64)
    counts = _coverage({"a": square, "b": square + [50, 0]}, 150, 100)  # b overlaps the right half of a
    cell = 150 / 256
    column = lambda x: int(x / cell)  # noqa: E731
    assert counts[50, column(25)] == 1 and counts[50, column(75)] == 2 and counts[50, column(125)] == 1
    assert counts.max() == 2
    svg = overlap_svg(FigureData(150, 100, 0.05, {"a": square, "b": square + [50, 0]}, counts))
    share = re.search(r"(\d+) % of the mosaic is seen by two photos or more", svg)
    assert share is not None and abs(int(share[1]) - 100 / 3) <= 1.5  # the middle third, 50 of 150 px


def test_residual_arrows_point_from_the_camera_to_its_gps_fix() -> None:
    data = FigureData(400, 300, 0.05, {}, np.zeros((3, 4), np.uint8))
    data.cameras = {"a": np.array([100.0, 100.0]), "b": np.array([300.0, 100.0])}
    data.gps = {"a": np.array([102.0, 100.0]), "b": np.array([300.0, 99.0])}  # a: 2 px east, b: 1 px north
    data.gcps = [("G1", "control", np.array([200.0, 200.0]), np.array([200.0, 201.0]))]
    root = ET.fromstring(positions_svg(data))
    lines = [
        (float(g.get("x1")), float(g.get("y1")), float(g.get("x2")), float(g.get("y2")))
        for g in root.iter(f"{SVG}line")
    ]
    factor = float(re.search(r"drawn (\d+) x", positions_svg(data))[1])
    assert (100.0, 100.0, 100.0 + 2 * factor, 100.0) in lines and (300.0, 100.0, 300.0, 100.0 - factor) in lines
    assert (200.0, 200.0, 200.0, 200.0 + factor) in lines
    assert 0.08 * 500 / 2 / 2 < factor <= 0.08 * 500 / 2  # the longest arrow (2 px) about 8 % of the diagonal


def test_advice_names_single_coverage_bad_photos_and_a_bending_strip() -> None:
    coverage = np.ones((10, 10), np.uint8)
    coverage[:, 5:] = 2
    data = FigureData(100, 100, 0.05, {}, coverage)
    u_shape = [0.9, 0.6, 0.2, 0.09, 0.15, 0.3, 0.5]
    data.per_photo = [(f"p{k}", 0.2 if k != 3 else 2.5, g) for k, g in enumerate(u_shape)]
    advice = _advice({"gps_residual_rms_m": 0.45}, data, MosaicConfig(gps_sigma_m=5.0))
    text = " ".join(advice)
    assert "50 % of the mosaic is seen by one photo only" in text
    assert "p3 fits the other photos worse" in text
    assert "grow toward both ends of the flight (0.70 m at the ends, 0.09 m in the middle)" in text
    assert "ortho mode" in text
    quiet = FigureData(100, 100, 0.05, {}, np.full((10, 10), 3, np.uint8))
    quiet.per_photo = [(f"p{k}", 0.2, 0.1) for k in range(7)]
    assert _advice({"gps_residual_rms_m": 0.1}, quiet, MosaicConfig()) == []


def test_a_report_without_map_or_photos_still_renders() -> None:
    data = FigureData(50, 40, None, {}, np.zeros((4, 5), np.uint8))
    svgs = figures(data)
    page = report_page({"mode": "planar", "warnings": ["2 of 3 frames are not in the map: a.jpg"]}, data, svgs, [])
    assert "2 of 3 frames are not in the map" in page and "no photos to show" in page
    assert all(ET.fromstring(s).tag == f"{SVG}svg" for s in svgs.values())


def test_all_clear_is_said_only_when_there_is_nothing_to_check() -> None:
    data = FigureData(50, 40, None, {}, np.zeros((4, 5), np.uint8))
    clear = "Nothing the processing found needs your attention."
    assert clear in report_page({"mode": "planar"}, data, figures(data), [])
    advised = report_page({"mode": "planar"}, data, figures(data), ["p3 fits the other photos worse"])
    assert "p3 fits the other photos worse" in advised and clear not in advised
    warned = report_page(
        {"mode": "planar", "warnings": ["1 of 3 frames is not in the map: a.jpg"]}, data, figures(data), []
    )
    assert clear not in warned


def test_the_page_says_what_the_frames_were_projected_onto() -> None:
    data = FigureData(50, 40, None, {}, np.zeros((4, 5), np.uint8))
    dense = {"kind": "dense", "pairs": 14, "dense_points": 635185, "coverage": 0.969, "cell_m": 0.342}
    page = report_page({"mode": "ortho", "ortho_surface": dense}, data, figures(data), [])
    assert "dense stereo between overlapping photos (14 pairs, 635,185 points, 97 % of the ground two photos" in page
    why = "no pair of frames overlaps enough for dense stereo"
    tie = {"kind": "tie_points", "points": 8446, "cell_m": 3.075, "why": why}
    page = report_page({"mode": "ortho", "ortho_surface": tie}, data, figures(data), [])
    assert "a surface gridded from 8,446 tie points" in page and why in page


def test_the_page_says_how_well_a_strips_corners_are_known() -> None:
    data = FigureData(50, 40, None, {}, np.zeros((4, 5), np.uint8))
    precision = {"median_m": 0.35, "max_m": 1.24, "max_photo_px": 4.96, "worst_frame": "<b>strip_000</b>.tif"}
    page = report_page({"mode": "strip", "corner_precision": precision}, data, figures(data), [])
    assert (
        "Frame corners known to (1σ)</dt><dd>35.0 cm median, 1.24 m at &lt;b&gt;strip_000&lt;/b&gt;.tif (5.0 photo px)"
        in page
    )
    assert "<b>strip_000" not in page  # a file name is text


@pytest.mark.realdata
def test_the_brighton_strips_bend_is_named(tmp_path: Path) -> None:
    """The issue's case: on the real Brighton strip the planar model's GPS residuals are U-shaped."""
    from tests.conftest import shared_data

    process_directory(shared_data("drone_brighton_strip1"), tmp_path / "job", {"working_max_px": 1024})
    page = (tmp_path / "job" / "report.html").read_text(encoding="utf-8")
    assert "grow toward both ends of the flight" in page


@pytest.mark.realdata
def test_a_pair_the_adjustment_dropped_blames_no_photo(tmp_path: Path) -> None:
    """On the Brighton strip the adjustment drops the weak pair DJI_0026-DJI_0028: its misfit is the reason, so it
    is not its photos' RMS (counted, they were 7.6 and 10.2 px against the strip's 0.88, and the report told the
    user to look for motion blur in them)."""
    from tests.conftest import shared_data

    report = process_directory(shared_data("drone_brighton_strip1"), tmp_path / "job", {})
    dropped = [p["frames"] for p in report["pairs"] if p["inliers"] and p["reason_unused"].startswith("weakest")]
    assert dropped == [["DJI_0026.JPG", "DJI_0028.JPG"]]
    footprints = json.loads((tmp_path / "job" / "footprints.geojson").read_text())
    rms = {f["properties"]["name"]: f["properties"]["rms_px"] for f in footprints["features"]}
    assert max(rms.values()) < 1.5 * report["tie_point_rms_px"], rms  # measured 1.00 against 0.88
    assert "fit the other photos worse" not in (tmp_path / "job" / "report.html").read_text(encoding="utf-8")


@pytest.mark.realdata
def test_no_pair_has_more_inliers_than_matches(tmp_path: Path) -> None:
    """budapest1-6 (no GPS): pairs re-measured by correlation report the candidates they examined as matches (the
    descriptor matches had been kept: budapest1-2 showed 44 matches and 96 inliers)."""
    from tests.conftest import shared_data

    report = process_directory(shared_data("stitching"), tmp_path / "job", {})
    assert len(report["frames_used"]) == 6 and report["georeferenced"] is False
    guided = [p for p in report["pairs"] if p["found_by"] == "guided"]
    assert guided and all(p["inliers"] <= p["matches"] for p in report["pairs"]), report["pairs"]


def test_the_pairs_table_has_an_rms_column_only_where_pairs_have_one() -> None:
    data = FigureData(50, 40, None, {}, np.zeros((4, 5), np.uint8))

    def pairs_table(rms: float | None) -> str:
        pair = {"frames": ["a.jpg", "b.jpg"], "matches": 90, "inliers": 80, "used": True, "tie_point_rms_px": rms}
        page = report_page({"mode": "planar", "pairs": [pair]}, data, figures(data), [])
        return page.split("<h2>Photo pairs</h2>")[1].split("</table>")[0]

    assert "RMS px" in pairs_table(0.61) and "0.61" in pairs_table(0.61)
    assert "RMS px" not in pairs_table(None)  # an ortho job's: its misfits are per photo
