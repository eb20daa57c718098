/* Calibrations (#/calibrations): the user's camera calibrations and stereo rigs; starting one by dropping photos
 * of a chessboard (#/calibrations/new: POST /api/calibrations) or pairs of them from a rig's two cameras
 * (#/stereo-rigs/new: POST /api/stereo-rigs, left and right photos paired in name order). The job's page then
 * shows the corners found on each photo and, for a calibration, lets the user fix or remove them. */

import { ACTIVE, api, apiForm, breadcrumb, formatBytes, formatDate, h, messageOf, plural, statusBadge } from "./lib.js";
import { JobKind } from "./kinds.js";
import { label } from "./labels.js";

const KINDS = new Set([JobKind.CALIBRATION, JobKind.STEREO_CALIBRATION]);
const PHOTO_TYPES = "image/*,.jpg,.jpeg,.png,.tif,.tiff";

// -- The list ---------------------------------------------------------------------------------------------------

export async function renderCalibrationList(view, root) {
  document.title = "Calibrations · Fotoskhema";
  const jobs = await api("GET", "/api/jobs", { signal: view.signal });
  if (view.signal.aborted) return;
  const mine = (jobs || []).filter((j) => KINDS.has(j.kind)).sort((a, b) => b.id - a.id);
  root.append(
    breadcrumb(["Calibrations"]),
    h("div", { class: "page-head row" }, h("h1", {}, "Calibrations"),
      h("span", { class: "push-right row" },
        h("a", { class: "btn primary", href: "#/calibrations/new", "data-testid": "new-calibration" }, "New calibration"),
        h("a", { class: "btn", href: "#/stereo-rigs/new", "data-testid": "new-stereo-rig" }, "New stereo rig"))),
    h("section", { class: "card" },
      h("p", { class: "muted" }, "A camera's intrinsics and lens distortion from photos of a chessboard; a stereo rig's rotation and baseline from pairs of them."),
      mine.length ? h("ul", { class: "plain", "data-testid": "calibration-list" }, mine.map((job) => h("li", {},
        h("a", { href: `#/jobs/${job.id}`, class: "job-item", "data-testid": "job-item" },
          h("span", { class: "job-title" }, `${label("kind", job.kind)} #${job.id}`),
          statusBadge(job.status),
          h("span", { class: "muted small job-when" }, ACTIVE.has(job.status) ? `${Math.round(job.progress || 0)} %` : formatDate(job.created_at))))))
        : h("p", { class: "empty" }, "No calibrations yet.")),
  );
}

// -- A new one --------------------------------------------------------------------------------------------------

/** #/calibrations/new (`stereo` false) or #/stereo-rigs/new (`stereo` true). */
export async function renderNewCalibration(view, root, stereo) {
  document.title = `${stereo ? "New stereo rig" : "New calibration"} · Fotoskhema`;
  const sides = stereo ? [["left", "Left camera"], ["right", "Right camera"]] : [["files", "Photos of the board"]];
  const zones = sides.map(([field, title]) => dropZone(field, title));
  const pairs = h("div", { "data-testid": "rig-pairs" });
  const columns = numberField("pattern-columns", "Inner corners across", 9, 2, 100);
  const rows = numberField("pattern-rows", "Inner corners down", 6, 2, 100);
  const square = numberField("square-mm", "Square edge (mm)", 25, 0.001, 10000, "any");
  const error = h("p", { class: "form-error", role: "alert", "data-testid": "calibration-error" });
  const submit = h("button", { type: "submit", class: "btn primary", "data-testid": "start-calibration" },
    stereo ? "Calibrate the rig" : "Calibrate the camera");
  const form = h("form", { class: "card form", novalidate: true, "data-testid": "calibration-form" },
    h("div", { class: stereo ? "two-zones" : "" }, zones.map((z) => z.node)),
    stereo ? pairs : null,
    h("fieldset", { class: "job-options" }, h("legend", {}, "The board"),
      h("div", { class: "row wrap" }, columns.node, rows.node, square.node),
      h("p", { class: "muted small" }, "A chessboard of 10 × 7 squares has 9 × 6 inner corners. Photograph it from several angles, filling much of the frame.")),
    h("div", { class: "start-row" }, submit, h("span", { class: "muted small" }, stereo
      ? "The photos of each camera are paired in name order." : "At least 3 photos; 10-20 from varied angles are better.")),
    error);
  const showPairs = () => {
    if (!stereo) return;
    const [left, right] = zones.map((z) => z.files());
    const n = Math.max(left.length, right.length);
    pairs.replaceChildren(n ? h("table", { class: "table compact" },
      h("thead", {}, h("tr", {}, h("th", { scope: "col" }, "Pair"), h("th", { scope: "col" }, "Left"), h("th", { scope: "col" }, "Right"))),
      h("tbody", {}, Array.from({ length: n }, (_, i) => h("tr", { "data-testid": "rig-pair" }, h("td", {}, String(i + 1)),
        h("td", { class: "filename" }, left[i] ? left[i].name : "–"), h("td", { class: "filename" }, right[i] ? right[i].name : "–"))))) : "");
  };
  for (const z of zones) z.onChange(showPairs);

  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    error.textContent = "";
    const options = { pattern: [columns.value(), rows.value()], square_mm: square.value() };
    if (!options.pattern.every(Number.isInteger) || !(options.square_mm > 0)) {
      error.textContent = "Give the board's inner corners (whole numbers) and its square's edge in mm.";
      return;
    }
    const body = new FormData();
    zones.forEach((z, k) => z.files().forEach((file) => body.append(sides[k][0], file, file.name)));
    body.append("options", JSON.stringify(options));
    submit.disabled = true;
    submit.textContent = "Uploading…";
    try {
      const job = await apiForm("POST", stereo ? "/api/stereo-rigs" : "/api/calibrations", body, { signal: view.signal });
      window.location.hash = `#/jobs/${job.id}`;
    } catch (err) {
      if (view.signal.aborted) return;
      error.textContent = messageOf(err);
      submit.disabled = false;
      submit.textContent = stereo ? "Calibrate the rig" : "Calibrate the camera";
    }
  });
  root.append(
    breadcrumb(["Calibrations", "#/calibrations"], [stereo ? "New stereo rig" : "New calibration"]),
    h("div", { class: "page-head" }, h("h1", {}, stereo ? "New stereo rig" : "New calibration")),
    form,
  );
}

function numberField(id, text, value, min, max, step = 1) {
  const input = h("input", { id, type: "number", min, max, step, value, class: "narrow-input", "data-testid": id, required: true });
  return { node: h("label", { for: id, class: "stack-label" }, text, input), value: () => Number(input.value) };
}

/** A drop zone (and file input) that keeps the photos chosen, in name order. */
function dropZone(field, title) {
  const id = `${field}-input`;
  const input = h("input", { id, type: "file", multiple: true, accept: PHOTO_TYPES, class: "visually-hidden", "data-testid": id });
  const list = h("p", { class: "muted small", "data-testid": `${field}-chosen` }, "No photos chosen.");
  let files = [];
  let listener = () => {};
  const take = (chosen) => {
    files = Array.from(chosen || []).sort((a, b) => a.name.localeCompare(b.name, undefined, { numeric: true }));
    const bytes = files.reduce((sum, f) => sum + f.size, 0);
    list.textContent = files.length ? `${plural(files.length, "photo")} (${formatBytes(bytes)}): ${files.map((f) => f.name).join(", ")}` : "No photos chosen.";
    listener();
  };
  const zone = h("div", { class: "drop-zone", "data-testid": `${field}-zone` },
    h("p", { class: "drop-title" }, title),
    h("p", { class: "muted" }, "Drag photos here, or ", h("label", { for: id, class: "btn small" }, "Choose photos…")),
    input, list);
  input.addEventListener("change", () => take(input.files));
  for (const type of ["dragenter", "dragover"]) {
    zone.addEventListener(type, (event) => {
      event.preventDefault();
      zone.classList.add("dragging");
    });
  }
  zone.addEventListener("dragleave", () => zone.classList.remove("dragging"));
  zone.addEventListener("drop", (event) => {
    event.preventDefault();
    zone.classList.remove("dragging");
    take(event.dataTransfer && event.dataTransfer.files);
  });
  return { node: zone, files: () => files, onChange: (fn) => { listener = fn; } };
}
