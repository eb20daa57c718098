"""Display names: the words a surveyor reads for every identifier the API and the reports emit.

Job kinds and statuses, pipeline stages, option values (mode, blending, resolution, features) and what a
report names (how the model was put on the map, an image's status, a ground control point's role, a camera
parameter). The viewer has a copy, ``web/labels.js``, generated from this table (``python -m core.labels >
web/labels.js``); ``tests/unit/test_labels.py`` checks that the copy matches and that every value the code can
emit has a name here. An unknown value is shown as it is, never dropped.
"""

from __future__ import annotations

import json
import sys

LABELS: dict[str, dict[str, str]] = {
    "kind": {
        "mosaic": "Mosaic",
        "calibration": "Camera calibration",
        "stereo_calibration": "Stereo rig calibration",
        "crack_survey": "Crack survey",
        "stereo_dem": "Stereo elevation model",
    },
    "status": {
        "queued": "Waiting",
        "running": "Running",
        "succeeded": "Finished",
        "failed": "Failed",
        "cancelled": "Cancelled",
    },
    "stage": {
        "load_images": "Reading the photos",
        "detect_features": "Finding features",
        "match_features": "Matching photo pairs",
        "measure_ties": "Measuring tie points",
        "match_strips": "Matching strip frames",
        "align_frames": "Aligning the photos",
        "georeference": "Placing on the map",
        "adjust_bundle": "Photo-triangulation",
        "orthorectify_frames": "Orthorectifying the photos",
        "compose_mosaic": "Blending the mosaic",
        "write_report": "Writing the report",
        "detect_corners": "Finding the board's corners",
        "calibrate_camera": "Calibrating the camera",
        "fit_plumb_line": "Fitting straight lines",
        "calibrate_stereo": "Calibrating the rig",
        "orient_camera": "Orienting the photos",
        "rectify_specimen": "Rectifying the specimen",
        "detect_cracks": "Finding cracks",
        "measure_cracks": "Measuring cracks",
        "compare_stages": "Comparing load steps",
        "write_crack_report": "Writing the crack report",
        "rectify_pair": "Rectifying the stereo pair",
        "compute_disparity": "Matching the pair pixel by pixel",
        "build_dsm": "Building the surface model",
        "write_stereo_report": "Writing the report",
    },
    "mode": {
        "planar": "Planar (flat ground)",
        "ortho": "Ortho (photo-triangulation + orthorectification)",
        "strip": "Aerial strips (planar, coarse to fine)",
    },
    "blend": {
        "feather": "Feathered overlaps",
        "multiband": "Seams cut where photos agree, multiband blending",
    },
    "resolution": {
        "working": "Working copies' resolution",
        "native": "The photos' own resolution",
    },
    "feature_type": {
        "sift": "SIFT features",
        "orb": "ORB features",
        "harris_ncc": "Harris corners matched by correlation",
    },
    "datum": {
        "gps_attitude": "GPS positions and camera attitude",
        "similarity_to_gps_and_gcps": "Fitted to the GPS positions and ground control",
        "gps_line_level_cameras": "Fitted to the GPS positions along the flight line (cameras taken as level)",
        "none": "Arbitrary: not to scale, not on the map",
        # reports written by earlier versions
        "gps": "GPS positions of the photos",
        "gcp": "Ground control points",
        "gps+gcp": "GPS positions and ground control points",
        "arbitrary": "Arbitrary: not to scale, not on the map",
    },
    "image_status": {
        "registered": "Placed",
        "placed again": "Placed again after a misfit",
        "not registered": "Not placed",
    },
    "gcp_role": {
        "control": "Control point",
        "tie": "Tie point (no known position)",
        "checkpoint": "Check point (held out)",
        "unused": "Not used (no marks on a placed photo)",
    },
    "photo_issue": {
        "blurred": "Blurred",
        "under_exposed": "Too dark",
        "over_exposed": "Too bright",
        "no_gps": "No GPS position",
        "duplicate": "Same picture as another photo",
        "size_mismatch": "Other size than the flight's photos",
        "not_checked": "Not checked",
    },
    "convention": {  # of a camera's distortion terms (workers.algorithms.geometry.camera)
        "distort_ideal": "Distorts the ideal projection (OpenCV's)",
        "restore_ideal": "Restores the ideal projection from the observed",
    },
    "camera_parameter": {
        "focal_px_original": "Focal length (px of the full-size photo)",
        "k1": "Radial distortion k1",
        "k2": "Radial distortion k2",
    },
    "eta_basis": {
        "measured": "measured on this job",
        "history": "from earlier jobs",
        "defaults": "from typical rates",
        "weights": "from the usual share of each step",
        "done": "finished",
    },
}


def label(category: str, value: str) -> str:
    """The display name of ``value`` in ``category``; the value itself when it has none."""
    return LABELS.get(category, {}).get(value, value)


def javascript() -> str:
    """``web/labels.js``: the same table for the viewer."""
    body = json.dumps(LABELS, indent=2, ensure_ascii=False)
    return (
        "/* Display names of what the API emits (generated from core/labels.py by `python -m core.labels`;\n"
        " * tests/unit/test_labels.py checks they match). `label(category, value)` falls back to the value. */\n\n"
        f"export const LABELS = Object.freeze({body});\n\n"
        '/** The display name of `value` in `category` (e.g. label("stage", "detect_features")). */\n'
        "export function label(category, value) {\n"
        "  const names = LABELS[category] || {};\n"
        '  return Object.prototype.hasOwnProperty.call(names, value) ? names[value] : String(value ?? "");\n'
        "}\n"
    )


if __name__ == "__main__":
    sys.stdout.write(javascript())
