/* Display names of what the API emits (generated from core/labels.py by `python -m core.labels`;
 * tests/unit/test_labels.py checks they match). `label(category, value)` falls back to the value. */

export const LABELS = Object.freeze({
  "kind": {
    "mosaic": "Mosaic",
    "calibration": "Camera calibration",
    "stereo_calibration": "Stereo rig calibration",
    "crack_survey": "Crack survey",
    "stereo_dem": "Stereo elevation model"
  },
  "status": {
    "queued": "Waiting",
    "running": "Running",
    "succeeded": "Finished",
    "failed": "Failed",
    "cancelled": "Cancelled"
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
    "write_stereo_report": "Writing the report"
  },
  "mode": {
    "planar": "Planar (flat ground)",
    "ortho": "Ortho (photo-triangulation + orthorectification)",
    "strip": "Aerial strips (planar, coarse to fine)"
  },
  "blend": {
    "feather": "Feathered overlaps",
    "multiband": "Seams cut where photos agree, multiband blending"
  },
  "resolution": {
    "working": "Working copies' resolution",
    "native": "The photos' own resolution"
  },
  "feature_type": {
    "sift": "SIFT features",
    "orb": "ORB features",
    "harris_ncc": "Harris corners matched by correlation"
  },
  "datum": {
    "gps_attitude": "GPS positions and camera attitude",
    "similarity_to_gps_and_gcps": "Fitted to the GPS positions and ground control",
    "gps_line_level_cameras": "Fitted to the GPS positions along the flight line (cameras taken as level)",
    "none": "Arbitrary: not to scale, not on the map",
    "gps": "GPS positions of the photos",
    "gcp": "Ground control points",
    "gps+gcp": "GPS positions and ground control points",
    "arbitrary": "Arbitrary: not to scale, not on the map"
  },
  "image_status": {
    "registered": "Placed",
    "placed again": "Placed again after a misfit",
    "not registered": "Not placed"
  },
  "gcp_role": {
    "control": "Control point",
    "tie": "Tie point (no known position)",
    "checkpoint": "Check point (held out)",
    "unused": "Not used (no marks on a placed photo)"
  },
  "photo_issue": {
    "blurred": "Blurred",
    "under_exposed": "Too dark",
    "over_exposed": "Too bright",
    "no_gps": "No GPS position",
    "duplicate": "Same picture as another photo",
    "size_mismatch": "Other size than the flight's photos",
    "not_checked": "Not checked"
  },
  "convention": {
    "distort_ideal": "Distorts the ideal projection (OpenCV's)",
    "restore_ideal": "Restores the ideal projection from the observed"
  },
  "camera_parameter": {
    "focal_px_original": "Focal length (px of the full-size photo)",
    "k1": "Radial distortion k1",
    "k2": "Radial distortion k2"
  },
  "eta_basis": {
    "measured": "measured on this job",
    "history": "from earlier jobs",
    "defaults": "from typical rates",
    "weights": "from the usual share of each step",
    "done": "finished"
  }
});

/** The display name of `value` in `category` (e.g. label("stage", "detect_features")). */
export function label(category, value) {
  const names = LABELS[category] || {};
  return Object.prototype.hasOwnProperty.call(names, value) ? names[value] : String(value ?? "");
}
