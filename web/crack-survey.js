/* Crack surveys: the list (#/crack-surveys) and one survey (#/crack-surveys/<id>).
 *
 * A survey's page follows the job like every job page (job.js), then shows each load step's rectified
 * specimen on a Leaflet map in CRS.Simple (the load step's own tiles), with its cracks drawn over it in their
 * status colour; a slider picks the load step, a table lists its cracks (a row shows its crack on the map),
 * and the control points' residuals say how well each photo was oriented. (The report and the options still
 * name the load steps `stages`, each a `stage`.)
 *
 * The report gives crack paths in mm on the rectification plane (a plate's X right, Y down; a mesh model's
 * plane, `report.plane`, with its origin and axes in model mm) with raster pixel (col, row) centred on
 * (x, y) / mm_per_px; on the tile grid that pixel spans [col, col + 1], and CRS.Simple shows the grid with y
 * negated. On a mesh, lengths and widths are measured along its surface, not on the plane.
 */

import {
  api,
  apiUrl,
  dataTable,
  downloadList,
  factList,
  filename,
  formatDate,
  formatNumber,
  formatVector,
  h,
  jobOutputs,
  list,
  onAbort,
  statusBadge,
  warningAlerts,
} from "./lib.js";
import { renderJobPage, showLoadError } from "./job.js";
import { JobKind } from "./kinds.js";
import { createMosaicMap } from "./result-map.js";

// The colours of the load-step overlay PNGs the worker draws (write_crack_report.STATUS_BGR), as RGB.
const STATUS_COLOURS = { first: "#ffc800", new: "#ff0000", grown: "#ff00ff", unchanged: "#00c800" };
const STATUS_TEXT = { first: "first seen", new: "new", grown: "grown", unchanged: "unchanged" };

// -- List ------------------------------------------------------------------------------------------

export async function renderCrackSurveyList(view, root) {
  document.title = "Crack surveys · Fotoskhema";
  const body = h("p", { class: "muted" }, "Loading crack surveys…");
  root.append(
    h("div", { class: "page-head row spread" },
      h("div", {}, h("h1", {}, "Crack surveys"),
        h("p", { class: "muted" }, "Photograph a specimen at each load step; get its cracks measured in mm and compared load step by load step.")),
      h("a", { class: "btn primary", href: "#/crack-surveys/new", "data-testid": "new-crack-survey" }, "New crack survey")),
    h("section", { class: "card", "aria-label": "All crack surveys" }, body),
  );
  const jobs = (await api("GET", "/api/jobs", { signal: view.signal })).filter((job) => job.kind === JobKind.CRACK_SURVEY)
    .sort((a, b) => b.id - a.id);
  if (view.signal.aborted) return;
  body.replaceWith(dataTable({
    caption: "Crack surveys",
    columns: [{ label: "Survey" }, { label: "Specimen" }, { label: "Load steps" }, { label: "Status" }, { label: "Created" }],
    rows: jobs.map((job) => {
      const options = job.options || {};
      return { attrs: { "data-testid": "survey-row" }, cells: [
        h("a", { class: "strong", href: `#/crack-surveys/${job.id}` }, `Survey #${job.id}`),
        specimenSize(options.specimen),
        list(options.stages).map((step) => step.label).join(", ") || "–",
        statusBadge(job.status),
        formatDate(job.created_at),
      ] };
    }),
    empty: "No crack surveys yet: start one with “New crack survey”.",
    scroll: false,
  }));
}

// -- One survey ------------------------------------------------------------------------------------

export async function renderCrackSurvey(view, root, jobId) {
  const { job } = await api("GET", `/api/crack-surveys/${jobId}`, { signal: view.signal }); // 404 for a job of any other kind
  if (view.signal.aborted) return;
  const result = h("section", { class: "card result", "aria-labelledby": "result-heading", hidden: true });
  const residuals = h("section", { class: "card", "aria-labelledby": "residuals-heading", "data-testid": "residuals", hidden: true });
  renderJobPage(view, root, job, {
    crumbs: [["Crack surveys", "#/crack-surveys"], [`Survey #${jobId}`]],
    cards: [result, residuals],
    listHref: "#/crack-surveys",
    onSucceeded: () => showSurvey(view, jobId, result, residuals).catch(showLoadError(view, result, "survey")),
  });
}

async function showSurvey(view, jobId, card, residualCard) {
  const heading = () => h("h2", { id: "result-heading" }, "Cracks");
  card.hidden = false;
  card.replaceChildren(heading(), h("p", { class: "muted" }, "Loading the survey…"));
  const { signal } = view;
  const tilejsons = new Map(); // load step -> promise of its TileJSON, asked for once
  const stepTiles = (s) => {
    if (!tilejsons.has(s)) tilejsons.set(s, api("GET", `/tiles/${jobId}/load-steps/${s}/tilejson.json`, { signal }));
    return tilejsons.get(s);
  };
  const [data, outputs, tilejson] = await Promise.all([
    api("GET", `/api/crack-surveys/${jobId}`, { signal }),
    jobOutputs(jobId, { signal }),
    stepTiles(0),
  ]);
  if (signal.aborted) return;
  // Links are the outputs list's signed URLs (a link cannot send the token), of this service only.
  const outputUrls = new Map(outputs.map((o) => [o.name, apiUrl(o.url)]));
  const report = data && data.result;
  const steps = list(report && report.stages);
  if (!steps.length) {
    card.replaceChildren(heading(), h("p", { class: "alert error", role: "alert" }, "The job finished but wrote no report."));
    return;
  }
  const mapNode = h("div", { class: "map specimen-map", "data-testid": "map", role: "region", "aria-label": "Specimen map" });
  const stepPanel = h("div", { class: "control" });
  const legend = h("div", { class: "control" });
  const tableBox = h("div", { class: "crack-table" });
  const plane = meshPlane(report);
  card.replaceChildren(
    h("div", { class: "row spread" }, heading(), h("span", { class: "muted small", "data-testid": "specimen" },
      `Specimen ${specimenSize(report.specimen)} · ${formatNumber(report.mm_per_px, 3)} mm/px`)),
    // replaceChildren would print a null
    ...(plane ? [h("p", { class: "muted small", "data-testid": "mesh-note" }, `The mesh model is shown rectified onto ${plane.how}; `
      + "crack lengths and widths are measured along its surface, so a crack on a curve is longer than it looks here.")] : []),
    ...warningAlerts(report.warnings, "survey-warning"),
    h("div", { class: "result-grid" }, mapNode, h("div", { class: "map-controls" }, stepPanel, legend)),
    tableBox,
    h("div", { class: "quality-block survey-downloads" }, downloadList(outputs, outputLabel(steps))),
  );
  const { map, mosaic } = createMosaicMap(mapNode, tilejson, null, "Specimen: Fotoskhema");
  onAbort(signal, () => map.remove());
  const table = { node: null, select: () => {} }; // the current load step's, replaced by show()
  const cracks = crackLayer(map, report.mm_per_px, (id) => table.select(id, true));
  const slider = stepSlider(steps, (s) => show(s));
  let current = 0;

  function show(s) {
    current = s;
    const step = steps[s];
    stepPanel.replaceChildren(slider, stepFacts(step, steps[s - 1], outputUrls, plane, report));
    legend.replaceChildren(...legendList(list(step.cracks)));
    cracks.draw(list(step.cracks));
    Object.assign(table, crackTable(step, (id) => cracks.select(id)));
    tableBox.replaceChildren(table.node);
    stepTiles(s).then((tiles) => {
      if (!signal.aborted && current === s) mosaic.setUrl(tiles.tiles[0]);
    }).catch(showLoadError(view, card, `tiles of ${step.label}`));
  }
  show(0);
  residualCard.hidden = false;
  residualCard.replaceChildren(...residualSection(list(report.photos), steps));
}

function stepSlider(steps, onStep) {
  const output = h("output", { for: "stage-slider", class: "muted small", "data-testid": "stage-number" });
  const slider = h("input", {
    id: "stage-slider", type: "range", min: 0, max: steps.length - 1, step: 1, value: 0,
    "data-testid": "stage-slider", disabled: steps.length < 2,
  });
  const label = () => {
    const s = Number(slider.value);
    output.textContent = `${s + 1} of ${steps.length}`;
    slider.setAttribute("aria-valuetext", `Load step ${s + 1}: ${steps[s].label}`);
  };
  slider.addEventListener("input", () => {
    label();
    onStep(Number(slider.value));
  });
  label();
  return h("div", {}, h("label", { for: "stage-slider" }, "Load step ", output), slider);
}

/** The load step's name, load and figures (and a mesh's rectification plane), and what changed since the load
 * step before; a link to its overlay PNG when the outputs list (`outputUrls`: name -> signed URL) has it.
 * `report` gives the contrast its smallest detectable width is for. */
function stepFacts(step, previous, outputUrls, plane, report) {
  const cracks = list(step.cracks);
  const counts = countBy(cracks);
  let changes;
  if (previous) {
    const growth = (step.total_length_mm ?? NaN) - (previous.total_length_mm ?? NaN);
    const grownBy = cracks.reduce((sum, c) => sum + (c.status === "grown" && Number.isFinite(c.growth_mm) ? c.growth_mm : 0), 0);
    changes = [
      h("strong", {}, `Since ${previous.label}: `),
      `${counts.new || 0} new, ${counts.grown || 0} grown, ${counts.unchanged || 0} unchanged. `,
      `Total length ${signed(growth)} mm`, counts.grown ? ` (the grown cracks ${signed(grownBy)} mm)` : "", ".",
    ];
  } else {
    changes = [h("strong", {}, "First load step: "), `${cracks.length} crack(s), nothing to compare with.`];
  }
  return h("div", { class: "stage-facts" },
    h("p", { class: "stage-title strong", "data-testid": "stage-title" },
      step.label, Number.isFinite(step.load) ? h("span", { class: "muted" }, ` · load ${step.load}`) : null),
    h("p", { class: "small", "data-testid": "stage-changes" }, changes),
    factList([
      ["Cracks", String(cracks.length), { "data-testid": "stage-count" }],
      ["Total length", formatNumber(step.total_length_mm, 1, "mm")],
      ["Mean width", formatNumber(step.mean_width_mm, 2, "mm")],
      ["Max width", formatNumber(step.max_width_mm, 2, "mm")],
      ["Seen", formatNumber(100 * step.coverage, 0, "%")],
      ["Photo sampling", formatNumber(step.photo_mm_per_px, 3, "mm/px"), { "data-testid": "stage-photo-sampling" }],
      ["Detection raster", formatNumber(step.detection_mm_per_px, 3, "mm/px"), { "data-testid": "stage-detection-raster" }],
      ["Smallest detectable width", formatNumber(step.smallest_detectable_width_mm, 2, "mm"),
        { "data-testid": "stage-smallest-width", title: "The narrowest crack the detector finds reliably here" }],
      ...(plane ? plane.rows : []),
    ]),
    detectability(step, report),
    step.overlay && outputUrls.get(step.overlay) ? h("p", { class: "small" }, h("a", {
      href: outputUrls.get(step.overlay), download: step.overlay, "data-testid": "stage-overlay",
    }, "This load step with its cracks drawn (PNG)")) : null);
}

function legendList(cracks) {
  const counts = countBy(cracks);
  return [
    h("h3", {}, "Crack status"),
    h("ul", { class: "plain legend", "data-testid": "legend" }, Object.keys(STATUS_COLOURS).map((status) =>
      h("li", { "data-status": status }, swatch(status), ` ${STATUS_TEXT[status]} `,
        h("span", { class: "muted small" }, `(${counts[status] || 0})`)))),
  ];
}

/** The cracks of one load step as polylines over the tiles; `select(id)` highlights one and zooms to it. */
function crackLayer(map, mmPerPx, onClick) {
  const group = L.featureGroup().addTo(map);
  const lines = new Map();
  const toLatLng = ([x, y]) => [-(y / mmPerPx + 0.5), x / mmPerPx + 0.5];
  function draw(cracks) {
    group.clearLayers();
    lines.clear();
    for (const crack of cracks) {
      const paths = list(crack.paths_mm).map((path) => path.filter(isPoint).map(toLatLng)).filter((p) => p.length > 1);
      if (!paths.length) continue;
      const known = Object.hasOwn(STATUS_COLOURS, crack.status);
      const line = L.polyline(paths, { color: known ? STATUS_COLOURS[crack.status] : "#888888", weight: 3, opacity: 0.95,
        className: known ? `crack crack-${crack.status}` : "crack" });
      // A node, not a string: Leaflet sets a string tooltip as HTML.
      line.bindTooltip(h("span", { class: "crack-tooltip" },
        `Crack ${crack.id}: ${statusText(crack.status)}, ${formatNumber(crack.length_mm, 1, "mm")}`), { sticky: true });
      line.on("click", () => onClick(crack.id));
      group.addLayer(line);
      lines.set(crack.id, line);
    }
  }
  function select(id) {
    for (const [key, line] of lines) {
      const chosen = key === id;
      line.setStyle(chosen ? { weight: 5, opacity: 1 } : { weight: 3, opacity: 0.45 });
      const path = line.getElement();
      if (path) path.classList.toggle("crack-selected", chosen);
      if (chosen) {
        line.bringToFront();
        map.fitBounds(line.getBounds(), { padding: [40, 40], maxZoom: 1 });
      }
    }
  }
  return { draw, select };
}

/** The crack table of one load step; `select(id, scroll)` marks a row (and scrolls to it for a map click). */
function crackTable(step, onSelect) {
  const rows = new Map();
  const cracks = list(step.cracks);
  function select(id, scroll) {
    for (const [key, row] of rows) row.classList.toggle("selected", key === id);
    const row = rows.get(id);
    if (row && scroll) row.scrollIntoView({ block: "nearest" });
    onSelect(id);
  }
  const node = h("div", {},
    h("h3", { id: "crack-table-heading" }, `Cracks of ${step.label} (${cracks.length})`),
    dataTable({
      caption: `Cracks of ${step.label}`,
      columns: [{ label: "Crack" }, { label: "Status" }, { label: "Length mm", num: true }, { label: "Width mm", num: true },
        { label: "Mean width mm", num: true }, { label: "Max width mm", num: true }, { label: "Orientation", num: true },
        { label: "Growth mm", num: true }],
      rows: cracks.map((crack) => ({
        attrs: { "data-testid": "crack-row", "data-crack": crack.id, "data-status": crack.status, class: "clickable" },
        cells: [
          h("button", { type: "button", class: "link-button", "aria-label": `Show crack ${crack.id} on the map` }, `#${crack.id}`),
          h("span", { class: "nowrap" }, swatch(crack.status), ` ${statusText(crack.status)}`),
          formatNumber(crack.length_mm, 1), widthText(crack),
          formatNumber(crack.mean_width_mm, 2), formatNumber(crack.max_width_mm, 2),
          degrees(crack.orientation_deg), crack.status === "grown" ? signed(crack.growth_mm) : "–",
        ],
      })),
      attrs: { "data-testid": "crack-table", "aria-labelledby": "crack-table-heading" },
      empty: "No crack found in this load step.",
    }));
  node.querySelectorAll('[data-testid="crack-row"]').forEach((row) => {
    rows.set(Number(row.dataset.crack), row);
    row.addEventListener("click", () => select(Number(row.dataset.crack), false));
  });
  return { node, select };
}

function residualSection(photos, steps) {
  return [
    h("h2", { id: "residuals-heading" }, "Control points"),
    h("p", { class: "muted small" }, "How well each photo's control points fit its oriented camera: the root mean square of their residuals, in photo pixels and on the specimen."),
    dataTable({
      caption: "Control-point residuals per photo",
      columns: [{ label: "Photo" }, { label: "Load step" }, { label: "Points", num: true }, { label: "RMS px", num: true },
        { label: "RMS mm", num: true }, { label: "Worst point", num: true }],
      rows: photos.map((photo) => {
        const points = list(photo.points);
        const worst = points.reduce((a, b) => ((b.error_px ?? -1) > (a ? a.error_px ?? -1 : -1) ? b : a), null);
        return { attrs: { "data-testid": "residual-row" }, cells: [
          filename(photo.image),
          (steps[photo.stage] || {}).label || "–",
          String(points.length),
          formatNumber(photo.rms_px, 2),
          formatNumber(photo.rms_mm, 3),
          worst ? `#${worst.index}: ${formatNumber(worst.error_px, 2)} px` : "–",
        ] };
      }),
      attrs: { "data-testid": "residual-table" },
      empty: "No photo in the report.",
      scroll: false,
    }),
  ];
}

// -- Helpers ---------------------------------------------------------------------------------------

function outputLabel(steps) {
  const names = { "cracks.geojson": "Cracks (GeoJSON, specimen mm)", "cracks.csv": "Cracks (CSV)", "report.json": "Survey report (JSON)" };
  return (name) => {
    const m = /^stage_(\d+)_(rectified|overlay)\./.exec(name); // the worker's file names of a load step
    if (!m) return names[name] || name;
    const label = (steps[Number(m[1])] || {}).label || `load step ${Number(m[1]) + 1}`;
    return m[2] === "rectified" ? `${label}: rectified specimen (COG)` : `${label}: cracks drawn (PNG)`;
  };
}

/** "200 × 150 mm" for a plate, "mesh model beam.obj" for a mesh specimen. */
function specimenSize(specimen) {
  const sp = specimen || {};
  return sp.mesh ? `mesh model ${sp.mesh}` : `${formatNumber(sp.width_mm, 0)} × ${formatNumber(sp.height_mm, 0)} mm`;
}

/** A mesh survey's rectification plane: how it was chosen and its fact rows; null for a plate. */
function meshPlane(report) {
  const specimen = report.specimen || {};
  const plane = report.plane;
  if (!specimen.mesh || !plane) return null;
  const vector = (v, digits) => {
    const text = formatVector(v, digits, 3);
    return text === "–" ? text : `(${text})`;
  };
  return {
    how: specimen.plane ? "the plane through the three points given" : "its best-fit plane",
    rows: [
      ["Plane origin", `${vector(plane.origin_mm, 1)} mm`, { "data-testid": "plane-origin" }],
      ["Plane x axis", vector(plane.x_axis, 3), { "data-testid": "plane-x-axis" }],
      ["Plane y axis", vector(plane.y_axis, 3), { "data-testid": "plane-y-axis" }],
    ],
  };
}

/** What the smallest detectable width is for: the contrast (this survey's widest cracks', or 30 % when none
 * was wide enough to tell), its range over the specimen (the photos sample it more finely nearer the camera),
 * and the width at lower contrasts. */
function detectability(step, report) {
  const contrast = report.detectability_contrast;
  if (typeof contrast !== "number" || !("smallest_detectable_width_mm" in step)) return null;
  const percent = (c) => `${formatNumber(100 * c, 0)} %`;
  const measured = typeof report.crack_contrast === "number";
  const range = Array.isArray(step.smallest_detectable_width_range_mm) ? step.smallest_detectable_width_range_mm : [];
  const parts = [`For cracks ${percent(contrast)} darker than the coating${measured ? ", as this survey's widest are" : " (assumed: no crack here was wide enough to tell)"}`];
  if (range.length === 2 && range.every((w) => typeof w === "number")) {
    parts.push(`: ${formatNumber(range[0], 2)}–${formatNumber(range[1], 2)} mm over the specimen`);
  }
  const fainter = list(step.detectable_width_by_contrast)
    .filter((r) => typeof r.contrast === "number" && r.contrast < contrast - 0.025 && [0.15, 0.2, 0.3].some((c) => Math.abs(c - r.contrast) < 1e-9));
  const shown = fainter.filter((r) => typeof r.width_mm === "number").reverse();
  if (shown.length) parts.push(`. At ${shown.map((r) => `${percent(r.contrast)}: ${formatNumber(r.width_mm, 2)} mm`).join(", ")}`);
  parts.push(`; fainter than ${percent(0.15)}, none reliably.`);
  return h("p", { class: "muted small", "data-testid": "stage-detectability" }, parts.join(""));
}

/** A crack's width with its uncertainty, or "≈ x (≤ y, below photo resolution)" where the photos cannot resolve
 * it: its equivalent width (its darkness over the coating's crack contrast) and the most it can be. */
function widthText(crack) {
  if (typeof crack.width_mm !== "number") return "–";
  if (crack.below_photo_resolution) {
    const bound = crack.width_mm + (crack.width_uncertainty_mm || 0);
    return h("span", { "data-testid": "below-resolution", title: "narrower than the photos resolve: its width from its darkness, if as dark as the wider cracks" },
      `≈ ${formatNumber(crack.width_mm, 2)} (≤ ${formatNumber(bound, 2)}, below photo resolution)`);
  }
  return `${formatNumber(crack.width_mm, 2)} ± ${formatNumber(crack.width_uncertainty_mm, 2)}`;
}

function degrees(value) {
  const text = formatNumber(value, 0);
  return text === "–" ? text : `${text}°`;
}

/** A crack status as the page words it (one it does not know: as the report gives it). */
function statusText(status) {
  return Object.hasOwn(STATUS_TEXT, status) ? STATUS_TEXT[status] : String(status);
}

function swatch(status) {
  // Only the page's own colours go into the style attribute, never the report's text.
  const colour = Object.hasOwn(STATUS_COLOURS, status) ? STATUS_COLOURS[status] : "#888888";
  return h("span", { class: "swatch", style: `background:${colour}`, "aria-hidden": "true" });
}

function countBy(cracks) {
  const counts = {};
  for (const crack of cracks) counts[crack.status] = (counts[crack.status] || 0) + 1;
  return counts;
}

function signed(value) {
  const text = formatNumber(value, 1);
  return text === "–" || value < 0 ? text : `+${text}`;
}

function isPoint(p) {
  return Array.isArray(p) && p.length >= 2 && Number.isFinite(p[0]) && Number.isFinite(p[1]);
}
