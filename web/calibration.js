/* Result of a calibration job (one camera: chessboards, marks or plumb lines) or of a stereo rig, and
 * measuring with a rig. Read from GET /api/calibrations/<id> or /api/stereo-rigs/<id>; every field may
 * be missing (a plumb-line fit has no views, a given camera no RMS): it then shows "–".
 */

import {
  api,
  dataTable,
  downloadList,
  factList,
  filename,
  formatCount,
  formatNumber,
  formatParam,
  formatPlusMinus,
  formatVector,
  h,
  humanize,
  jobOutputs,
  jobSignature,
  list,
  messageOf,
} from "./lib.js";
import { calibrationPhotos } from "./calibration-marks.js";
import { label } from "./labels.js";
import { JobKind } from "./kinds.js";

export const CALIBRATION_KINDS = new Set([JobKind.CALIBRATION, JobKind.STEREO_CALIBRATION]);
const CAMERA_PARAMS = ["fx", "fy", "cx", "cy", "k1", "k2", "k3", "t1", "t2"];
const PIXEL_PARAMS = new Set(["fx", "fy", "cx", "cy"]); // in pixels; the distortion terms are unitless

/** Fill `card` with the calibration of `job` (which has succeeded). */
export async function showCalibration(view, job, card) {
  const stereo = job.kind === JobKind.STEREO_CALIBRATION;
  card.hidden = false;
  card.replaceChildren(h("h2", { id: "result-heading" }, "Result"), h("p", { class: "muted" }, "Loading the calibration…"));
  const { signal } = view;
  const [data, outputs, signature] = await Promise.all([
    api("GET", stereo ? `/api/stereo-rigs/${job.id}` : `/api/calibrations/${job.id}`, { signal }),
    jobOutputs(job.id, { signal }),
    typeof job.signature === "string" ? job.signature : jobSignature(job.id, { signal }).catch(() => ""),
  ]);
  if (signal.aborted) return;
  const result = data && data.result;
  if (!result) {
    card.replaceChildren(h("h2", { id: "result-heading" }, "Result"),
      h("p", { class: "alert error", role: "alert" }, "The job finished but wrote no calibration."));
    return;
  }
  const body = stereo ? stereoBody(job, result) : cameraBody(result);
  const label = (name) => (name === "calibration.json" ? "Calibration (camera JSON)" : name);
  const photos = await calibrationPhotos(view, job, { stereo, result, signature, editable: true }).catch((err) => ({
    node: h("p", { class: "muted small", "data-testid": "calibration-photos" }, `The photos could not be listed: ${messageOf(err)}`),
    start: () => {},
  }));
  if (signal.aborted) return;
  // replaceChildren would print a null
  card.replaceChildren(...body.filter(Boolean), photos.node, h("div", { class: "quality-block" }, downloadList(outputs, label)));
  photos.start(); // once in the page: the map needs its size
}

// -- One camera ----------------------------------------------------------------------------------

function cameraBody(result) {
  const camera = result.camera || {};
  const views = list(result.views);
  const plumb = result.method === "plumb_line";
  return [
    h("div", { class: "row spread" }, h("h2", { id: "result-heading" }, "Camera"),
      h("span", { class: "muted small" }, result.method ? `Method: ${humanize(result.method)}` : "")),
    factList([
      ["RMS reprojection", formatNumber(result.rms_px, 3, "px"), { "data-testid": "calibration-rms" }],
      plumb ? ["Lines", String(list(result.lines).length)] : ["Photos used", String(views.length), { "data-testid": "views-used" }],
      ["Photos left out", String(strings(result.left_out).length)],
      ["Image size", sizeText(camera)],
      ["Distortion convention", camera.convention ? label("convention", camera.convention) : "–"],
    ], { class: "facts wide headline" }),
    result.note ? h("p", { class: "muted small" }, result.note) : null,
    h(
      "div",
      { class: "calib-grid" },
      h("div", { class: "quality-block" }, h("h3", {}, "Parameters"), paramTable(camera, result.std || {})),
      h(
        "div",
        { class: "quality-block" },
        plumb ? linesTable(result.lines) : worstTable(result.worst_points),
        leftOut(result.left_out),
      ),
    ),
    plumb ? null : viewSection(views),
  ];
}

function paramTable(camera, std) {
  return dataTable({
    caption: "Camera parameters with their standard deviations",
    columns: [{ label: "Parameter" }, { label: "Value", num: true }, { label: "Std. dev.", num: true }],
    rows: CAMERA_PARAMS.map((name) => ({
      attrs: { "data-param": name },
      cells: [
        h("span", { class: "mono" }, name),
        h("span", { "data-testid": `param-${name}` }, paramText(name, camera[name])),
        paramText(name, std[name]),
      ],
    })),
    attrs: { "data-testid": "camera-params" },
    scroll: false,
  });
}

function paramText(name, value) {
  return formatParam(value, PIXEL_PARAMS.has(name));
}

function sizeText(camera) {
  return Number.isFinite(camera.width) && Number.isFinite(camera.height) ? `${camera.width} × ${camera.height} px` : "–";
}

function worstTable(points) {
  return [
    h("h3", {}, "Worst marks"),
    dataTable({
      caption: "Marks with the largest reprojection error",
      columns: [{ label: "Photo" }, { label: "Mark", num: true }, { label: "Error px", num: true }],
      rows: list(points).map((p) => [filename(p.image), formatCount(p.index), formatNumber(p.error_px, 3)]),
      attrs: { "data-testid": "worst-points" },
      empty: "No marks in the result.",
      scroll: false,
    }),
  ];
}

function linesTable(lines) {
  return [
    h("h3", {}, "Lines"),
    dataTable({
      caption: "Residuals of each straight line",
      columns: [{ label: "Line", num: true }, { label: "Points", num: true }, { label: "RMS px", num: true }],
      rows: list(lines).map((l) => [formatCount(l.index), formatCount(l.points), formatNumber(l.rms_px, 3)]),
      attrs: { "data-testid": "plumb-lines" },
      empty: "No lines in the result.",
      scroll: false,
    }),
  ];
}

function leftOut(items) {
  const names = strings(items);
  return h(
    "div",
    { class: "left-out", "data-testid": "left-out" },
    h("h3", {}, `Left out (${names.length})`),
    names.length ? h("ul", { class: "reasons" }, names.map((text) => h("li", {}, text)))
      : h("p", { class: "muted small" }, "Every photo was used."),
  );
}

/** The per-photo table and, below it, every mark of one photo picked from a list. */
function viewSection(views) {
  const pick = h("select", { id: "view-pick", "data-testid": "view-pick" },
    views.map((v, i) => h("option", { value: i }, v.image || `photo ${i + 1}`)));
  const marks = h("div", { "data-testid": "view-points" });
  const showMarks = () => marks.replaceChildren(pointTable(views[Number(pick.value)] || {}));
  pick.addEventListener("change", showMarks);
  if (views.length) showMarks();
  return h(
    "section",
    { class: "quality-block", "aria-labelledby": "views-heading" },
    h("h3", { id: "views-heading" }, "Per photo"),
    dataTable({
      caption: "Reprojection error per photo",
      columns: [{ label: "Photo" }, { label: "Source" }, { label: "Marks", num: true }, { label: "RMS px", num: true },
        { label: "Max px", num: true }],
      rows: views.map((v) => {
        const errors = list(v.points).map((p) => p.error_px).filter(Number.isFinite);
        return { attrs: { "data-testid": "view-row" },
          cells: [filename(v.image), v.source || "–", String(list(v.points).length), formatNumber(v.rms_px, 3),
            errors.length ? formatNumber(Math.max(...errors), 3) : "–"] };
      }),
      attrs: { "data-testid": "view-residuals" },
      empty: "No photo views in the result.",
    }),
    views.length ? h("div", { class: "control-row" }, h("label", { for: "view-pick" }, "Marks of photo"), pick) : null,
    marks,
  );
}

function pointTable(view) {
  return dataTable({
    caption: `Marks of ${view.image || "the photo"}`,
    columns: [{ label: "Mark", num: true }, { label: "Image x, y", num: true }, { label: "Board x, y, z", num: true },
      { label: "Residual dx, dy", num: true }, { label: "Error px", num: true }],
    rows: list(view.points).map((p) => [formatCount(p.index), formatVector(p.image_xy, 2), formatVector(p.board_xyz, 1),
      formatVector(p.residual_px, 3), formatNumber(p.error_px, 3)]),
    empty: "No marks for this photo.",
  });
}

// -- Stereo rig ----------------------------------------------------------------------------------

function stereoBody(job, result) {
  const cameras = result.cameras || {};
  return [
    h("h2", { id: "result-heading" }, "Stereo rig"),
    factList([
      ["Baseline", formatPlusMinus(result.baseline_mm, result.baseline_std_mm, 2, "mm"), { "data-testid": "baseline" }],
      ["Rotation between cameras", formatNumber(result.rotation_deg, 3, "°"), { "data-testid": "rotation" }],
      ["RMS reprojection", formatNumber(result.rms_px, 3, "px"), { "data-testid": "calibration-rms" }],
      ["Pairs used", String(list(result.pairs).length)],
      ["Units", result.units || "–"],
    ], { class: "facts wide headline" }),
    h(
      "div",
      { class: "calib-grid" },
      h("div", { class: "quality-block" }, h("h3", {}, "Cameras"), rigCameraTable(cameras.left || {}, cameras.right || {})),
      h(
        "div",
        { class: "quality-block" },
        h("h3", {}, "Per pair"),
        dataTable({
          caption: "Reprojection error per photo pair",
          columns: [{ label: "Left" }, { label: "Right" }, { label: "RMS px", num: true }],
          rows: list(result.pairs).map((p) => ({ attrs: { "data-testid": "pair-row" },
            cells: [filename(p.left), filename(p.right), formatNumber(p.rms_px, 3)] })),
          attrs: { "data-testid": "pair-residuals" },
          empty: "No pairs in the result.",
        }),
        leftOut(result.left_out),
      ),
    ),
    Array.isArray(result.worst_points) ? h("div", { class: "quality-block" }, worstTable(result.worst_points)) : null,
    measureForm(job.id),
  ];
}

function rigCameraTable(left, right) {
  const l = left.camera || {};
  const r = right.camera || {};
  const rows = [
    ["Source", left.source || "–", right.source || "–"],
    ["RMS px", formatNumber(left.rms_px, 3), formatNumber(right.rms_px, 3)],
    ...CAMERA_PARAMS.map((name) => [h("span", { class: "mono" }, name), paramText(name, l[name]), paramText(name, r[name])]),
    ["Size", sizeText(l), sizeText(r)],
    ["Distortion convention", ...[l, r].map((c) => (c.convention ? label("convention", c.convention) : "–"))],
  ];
  return dataTable({
    caption: "Left and right camera",
    columns: [{ label: "Parameter" }, { label: "Left", num: true }, { label: "Right", num: true }],
    rows,
    attrs: { "data-testid": "rig-cameras" },
    scroll: false,
  });
}

/** "xl yl xr yr" per line (spaces, tabs or commas) -> {left, right}; throws naming the bad line. */
export function parsePixelPairs(text) {
  const left = [];
  const right = [];
  String(text).split(/\r?\n/).forEach((raw, i) => {
    const line = raw.split("#", 1)[0].trim();
    if (!line) return;
    const fields = line.split(/[\s,;]+/).filter(Boolean);
    const values = fields.map(Number);
    if (fields.length !== 4 || !values.every(Number.isFinite)) {
      throw new Error(`Line ${i + 1}: expected four numbers "xl yl xr yr", got "${line}".`);
    }
    left.push([values[0], values[1]]);
    right.push([values[2], values[3]]);
  });
  if (!left.length) throw new Error("Give at least one point: one line \"xl yl xr yr\" per point.");
  return { left, right };
}

function measureForm(jobId) {
  const input = h("textarea", {
    id: "measure-input", rows: 4, spellcheck: "false", class: "mono", "data-testid": "measure-input",
    "aria-describedby": "measure-hint", placeholder: "312.5 240.0 290.2 241.1\n410.0 180.5 388.7 181.0",
  });
  const submit = h("button", { type: "submit", class: "btn primary", "data-testid": "measure-submit" }, "Measure");
  const error = h("p", { class: "form-error", role: "alert", "data-testid": "measure-error" });
  const status = h("p", { class: "muted small", role: "status", "aria-live": "polite" });
  const output = h("div", { "data-testid": "measure-result" });
  const form = h(
    "form",
    { class: "form quality-block measure", "aria-labelledby": "measure-heading", "data-testid": "measure-form", novalidate: true },
    h("h3", { id: "measure-heading" }, "Measure"),
    h("label", { for: "measure-input" }, "Pixel pairs, one point per line: xl yl xr yr"),
    input,
    h("p", { id: "measure-hint", class: "muted small" },
      "The same point in the left and the right photo, in pixels. Answers each point's position in the left camera's frame and the distance between every two points."),
    submit,
    error,
    status,
    output,
  );
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    error.textContent = "";
    output.replaceChildren(); // never show the points of an earlier request under a new one's error
    let body;
    try {
      body = parsePixelPairs(input.value);
    } catch (err) {
      error.textContent = err.message;
      return;
    }
    submit.disabled = true;
    status.textContent = "Measuring…";
    try {
      const answer = await api("POST", `/api/stereo-rigs/${jobId}/measure`, { body });
      output.replaceChildren(...measureResult(answer || {}).filter(Boolean));
      status.textContent = `Measured ${list(answer && answer.points).length} point(s).`;
    } catch (err) {
      error.textContent = messageOf(err);
      status.textContent = "";
    } finally {
      submit.disabled = false;
    }
  });
  return form;
}

function measureResult(answer) {
  const points = list(answer.points);
  return [
    answer.units ? h("p", { class: "muted small" }, `Units: ${answer.units}`) : null,
    dataTable({
      caption: "Measured points",
      columns: [{ label: "Point", num: true }, { label: "x, y, z mm", num: true }, { label: "Std. dev. mm", num: true },
        { label: "Ray gap mm", num: true }],
      rows: points.map((p, i) => ({ attrs: { "data-testid": "measured-point" },
        cells: [String(i), formatVector(p.xyz, 2), formatNumber(p.sigma, 2), formatNumber(p.ray_gap, 3)] })),
      attrs: { "data-testid": "measured-points" },
      scroll: false,
    }),
    points.length > 1
      ? dataTable({
        caption: "Distances between the points",
        columns: [{ label: "Points" }, { label: "Distance mm", num: true }],
        rows: list(answer.distances).map((d) => ({ attrs: { "data-testid": "measured-distance" },
          cells: [`${d.from} – ${d.to}`, formatPlusMinus(d.distance, d.sigma, 2)] })),
        attrs: { "data-testid": "measured-distances" },
        scroll: false,
      })
      : null,
  ];
}

// -- Shared ----------------------------------------------------------------------------------------

function strings(value) {
  return Array.isArray(value) ? value.map(String) : [];
}

