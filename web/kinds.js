/* The job kinds and statuses, as the API names them (the Python side's; a test checks they match). */

export const JobKind = Object.freeze({ MOSAIC: "mosaic", CALIBRATION: "calibration", STEREO_CALIBRATION: "stereo_calibration", CRACK_SURVEY: "crack_survey", STEREO_DEM: "stereo_dem" });

export const JobStatus = Object.freeze({ QUEUED: "queued", RUNNING: "running", SUCCEEDED: "succeeded", FAILED: "failed", CANCELLED: "cancelled" });
