/* A finished mosaic's "Quality" card, read from its report.json: frames used and rejected, tie-point
 * and reprojection RMS, GSD, GPS residuals and, for ortho jobs, the photo-triangulation's cameras and
 * ground control points; the report's pictures (overlap, positions and residual arrows, tie points, residuals
 * per photo: the SVG outputs report.html shows too) and a link to the printable report. Every field may be
 * missing (older reports, planar jobs): it then shows "–". Identifiers are shown by their display names
 * (labels.js), never as they are spelt in the JSON.
 */

import {
  api,
  apiUrl,
  dataTable,
  factList,
  filename,
  formatCount,
  formatMetres,
  formatNumber,
  formatParam,
  formatVector,
  h,
  list,
  warningAlerts,
} from "./lib.js";
import { label } from "./labels.js";

// The report's pictures (outputs of write_report), in the order report.html shows them.
const FIGURES = [
  ["report-overlap.svg", "Overlap: how many photos see each part of the mosaic"],
  ["report-positions.svg", "Camera positions, with arrows to their GPS fixes and ground control residuals"],
  ["report-tie-points.svg", "Tie points, coloured by how well they agree"],
  ["report-residuals.svg", "Residuals per photo"],
];

/** Fill `card` from the job's report.json, if it has one; `outputs` is the job's outputs list, `reportPromise`
 * (optional) the report already asked for. */
export async function showQuality(view, outputs, card, reportPromise) {
  const entry = (outputs || []).find((o) => o.name === "report.json");
  const url = entry && apiUrl(entry.url); // read from this service only
  if (!url) return;
  card.hidden = false;
  card.replaceChildren(heading(), h("p", { class: "muted" }, "Loading the report…"));
  const report = await (reportPromise || api("GET", url, { signal: view.signal }));
  if (view.signal.aborted) return;
  // replaceChildren writes a null as the text "null": every block that may be absent is filtered out
  card.replaceChildren(...[heading(report && report.mode, outputs), ...qualityBody(report || {}), pictures(outputs)]
    .filter(Boolean));
}

function heading(mode, outputs) {
  const page = apiUrl(((outputs || []).find((o) => o.name === "report.html") || {}).url); // this service's only
  return h("div", { class: "row spread" }, h("h2", { id: "quality-heading" }, "Quality"),
    h("span", { class: "row" },
      page ? h("a", { href: page, target: "_blank", rel: "noopener", class: "btn small", "data-testid": "report-html" },
        "Full report (printable)") : null,
      mode ? h("span", { class: "badge", "data-testid": "quality-mode" }, label("mode", mode)) : null));
}

/** The report's pictures, as images of its SVG outputs (signed URLs: an image cannot send the token). */
function pictures(outputs) {
  const byName = Object.fromEntries((outputs || []).map((o) => [o.name, o]));
  const shown = FIGURES.map(([name, caption]) => [apiUrl((byName[name] || {}).url), caption, name]).filter(([url]) => url);
  if (!shown.length) return null;
  return h("div", { class: "quality-block", "data-testid": "quality-pictures" },
    h("h3", {}, "Pictures"),
    h("div", { class: "quality-figures" }, shown.map(([url, caption, name]) =>
      h("figure", { class: "quality-figure" },
        h("a", { href: url, target: "_blank", rel: "noopener" },
          h("img", { src: url, alt: caption, loading: "lazy", "data-testid": `figure-${name.replace(/\.svg$/, "")}` })),
        h("figcaption", { class: "muted small" }, caption)))));
}

function qualityBody(report) {
  const used = list(report.frames_used);
  const rejected = list(report.frames_rejected);
  const known = Array.isArray(report.frames_used) || Array.isArray(report.frames_rejected);
  const nodes = [
    ...warningAlerts(report.warnings, "quality-warning"), // frames left out or placed again, GPS misfits
    factList([
      ["Mode", report.mode ? label("mode", report.mode) : "–", { "data-testid": "quality-mode-text" }],
      ["Frames used", known ? `${used.length} of ${used.length + rejected.length}` : "–", { "data-testid": "frames-used" }],
      ["Tie-point RMS", rmsText(report.tie_point_rms_px, report.tie_point_rms_px_original), { "data-testid": "tie-point-rms" }],
      ["GSD of the photos", formatMetres(report.gsd_original_m), { "data-testid": "gsd-original" }],
      ["GSD of the mosaic", formatMetres(report.gsd_m), { "data-testid": "gsd" }],
      ["GPS residual RMS", formatMetres(report.gps_residual_rms_m), { "data-testid": "gps-residual-rms" }],
      ...(typeof report.gps_drift_m === "number"
        ? [["GPS drift along the route", formatMetres(report.gps_drift_m), { "data-testid": "gps-drift" }]]
        : []),
      ...(report.corner_precision && typeof report.corner_precision.max_m === "number"
        ? [["Frame corners known to (1σ)", precisionText(report.corner_precision), { "data-testid": "corner-precision" }]]
        : []),
    ], { class: "facts wide", "data-testid": "quality-facts" }),
    reasons("Rejected frames", rejected, "frames-rejected", "No frame was rejected."),
  ];
  if (report.triangulation && typeof report.triangulation === "object") nodes.push(triangulationSection(report.triangulation));
  if (report.ortho_surface && typeof report.ortho_surface === "object") nodes.push(surfaceFacts(report.ortho_surface));
  return nodes;
}

/** "35.0 cm median, 72.0 cm at strip_000.tif": the adjustment's standard errors of the frames' corners. */
function precisionText(p) {
  const where = typeof p.worst_frame === "string" ? ` at ${p.worst_frame}` : "";
  return `${formatMetres(p.median_m)} median, ${formatMetres(p.max_m)}${where}`;
}

/** "0.42 px (1.31 px at full resolution)": the working-scale RMS and the one in the photos' pixels. */
function rmsText(working, original) {
  const a = formatNumber(working, 2, "px");
  if (typeof original !== "number" || !Number.isFinite(original)) return a;
  return `${a} (${formatNumber(original, 2, "px")} at full resolution)`;
}

/** A short list of {name, reason}; nothing when `empty` is null and the list is empty. */
function reasons(title, items, testid, empty) {
  if (!items.length && empty === null) return null;
  return h(
    "div",
    { class: "quality-block", "data-testid": testid },
    h("h3", {}, `${title} (${items.length})`),
    items.length
      ? h("ul", { class: "reasons" }, items.map((item) =>
        h("li", {}, h("span", { class: "filename" }, item.name || `frame ${item.index ?? "?"}`), ": ", item.reason || "no reason given")))
      : h("p", { class: "muted small" }, empty),
  );
}

function triangulationSection(t) {
  const registered = Number.isFinite(t.registered) && Number.isFinite(t.total) ? `${t.registered} / ${t.total}` : "–";
  return h(
    "section",
    { class: "quality-block", "aria-labelledby": "triangulation-heading", "data-testid": "triangulation" },
    h("h3", { id: "triangulation-heading" }, "Photo-triangulation"),
    factList([
      ["Cameras registered", registered, { "data-testid": "registered" }],
      ["RMS reprojection", rmsText(t.rms_px, t.rms_px_original), { "data-testid": "rms-reprojection" }],
      ["Datum", t.datum ? label("datum", t.datum) : "–", { "data-testid": "datum" }],
      ["Observations", formatCount(t.observations)],
      ["3D points", formatCount(t.points)],
      ["Outliers dropped", formatCount(t.outliers_dropped)],
      ["GPS residual RMS", formatMetres(t.gps_residual_rms_m)],
    ], { class: "facts wide" }),
    reasons("Not registered", list(t.not_registered), "not-registered", null),
    selfCalibration(t.self_calibration),
    h("h4", {}, "Per image"),
    dataTable({
      caption: "Reprojection residuals per image",
      columns: [{ label: "Image" }, { label: "Status" }, { label: "RMS px", num: true }, { label: "Observations", num: true },
        { label: "Tie points offered", num: true }, { label: "GPS residual", num: true }],
      rows: list(t.images).map((img) => ({
        attrs: { "data-testid": "image-residual-row", "data-status": typeof img.status === "string" ? img.status : "" },
        cells: [filename(img.name), typeof img.status === "string" ? label("image_status", img.status) : "–", formatNumber(img.rms_px, 2),
          formatCount(img.observations), formatCount(img.tie_points_offered), formatMetres(img.gps_residual_m)],
      })),
      attrs: { "data-testid": "image-residuals" },
      empty: "No per-image residuals in the report.",
    }),
    h("h4", {}, "Ground control points"),
    dataTable({
      caption: "Ground control point residuals",
      columns: [{ label: "GCP" }, { label: "Role" }, { label: "Obs.", num: true }, { label: "Residual px", num: true },
        { label: "Error dx, dy, dz", num: true }, { label: "Error 3D m", num: true }],
      rows: list(t.gcps).map((g) => ({
        attrs: { "data-testid": "gcp-row", "data-role": g.role || "" },
        cells: [g.id ?? "–", g.role ? label("gcp_role", g.role) : "–", formatCount(g.observations), formatNumber(g.residual_px, 2),
          errorVector(g.error_m), formatNumber(g.error_3d_m, 3)],
      })),
      attrs: { "data-testid": "gcp-residuals" },
      empty: "No ground control points were used.",
    }),
  );
}

/** What an ortho mosaic's frames were projected onto: the tie points' surface (its cell and heights) or a plane. */
const SURFACE_KINDS = {
  dense: "a surface from dense stereo between overlapping photos, the tie points' elsewhere",
  tie_points: "a surface gridded from the tie points",
  plane: "one plane",
};

function surfaceFacts(surface) {
  const kind = typeof surface.kind === "string" ? surface.kind : "";
  const range = Array.isArray(surface.height_range_m) ? surface.height_range_m : [];
  const share = typeof surface.coverage === "number" ? `${formatNumber(100 * surface.coverage, 0)} %` : "–";
  return h("div", { class: "quality-block", "data-testid": "ortho-surface" }, h("h3", {}, "Ortho surface"),
    factList([
      ["Projected onto", SURFACE_KINDS[kind] || "–", { "data-testid": "ortho-surface-kind" }],
      kind === "dense" ? ["Dense stereo", `${formatCount(surface.pairs)} pairs, ${formatCount(surface.dense_points)} points, `
        + `${share} of the ground two photos see`, { "data-testid": "ortho-surface-dense" }] : null,
      kind !== "plane" ? ["Tie points; grid cell", `${formatCount(surface.points)} points, ${formatMetres(surface.cell_m)} cells`] : null,
      typeof surface.why === "string" ? ["Why", surface.why] : null,
      kind !== "plane" ? ["Heights", `${formatNumber(range[0], 2, "m")} to ${formatNumber(range[1], 2, "m")}`] : null,
    ].filter(Boolean), { class: "facts wide" }));
}

function errorVector(v) {
  const text = formatVector(v, 3, 3);
  return text === "–" ? text : `${text} m`;
}

function selfCalibration(params) {
  if (!params || typeof params !== "object" || !Object.keys(params).length) return null;
  return h(
    "div",
    {},
    h("h4", {}, "Self-calibration"),
    dataTable({
      caption: "Camera parameters refined by the adjustment",
      columns: [{ label: "Parameter" }, { label: "Initial", num: true }, { label: "Adjusted", num: true }],
      // focal lengths read well with 2 decimals, distortion terms need more
      rows: Object.entries(params).map(([name, p]) => [label("camera_parameter", name), formatParam(p && p.initial),
        formatParam(p && p.adjusted)]),
      attrs: { "data-testid": "self-calibration" },
      scroll: false,
    }),
  );
}
