/* A finished stereo DEM on its job page: the DSM as hillshaded, colour-ramped tiles over the basemap with
 * its legend, the elevation under the cursor, and the map tools (distance, area, the volume above a base,
 * coordinates in the DSM's UTM zone); a pair without RPCs (rectified, a rig, uncalibrated) shows
 * its disparity map the same way, in the rectified left view's pixels. Read from GET /api/stereo-dems/<id>
 * (the report: figures and legend), /tiles/<id>/{dsm,disparity}/tilejson.json and the point route
 * /tiles/<id>/{dsm,disparity}/point. Every report field may be missing: it then shows "–".
 */

import { api, downloadList, factList, formatCount, formatNumber, getConfig, h, humanize, jobOutputs, onAbort, warningAlerts } from "./lib.js";
import { projectionOf } from "./crs.js";
import { followPointer, legendNode } from "./dsm.js";
import { layerSwitcher } from "./map-layers.js";
import { coordinatesControl, measureTool } from "./map-tools.js";
import { createMosaicMap } from "./result-map.js";

const DOWNLOADS = {
  "dsm.tif": "DSM (Cloud-Optimized GeoTIFF, m)",
  "dsm_mask.tif": "DSM cells measured (1) or filled (2)",
  "disparity.tif": "Disparity map (left view, px)",
  "confidence.tif": "Confidence of each disparity (0: filled)",
  "depth.tif": "Depth map (the rig's units)",
  "report.json": "Processing report",
};
const MATCHERS = {
  sgbm: "Semi-global (OpenCV SGBM, checked)",
  local: "Local 2-D search, soft epipolar constraint",
};
const GEOMETRIES = {
  rpc: "RPC pair (satellite): rectified and triangulated through the RPCs",
  rig: "Calibrated stereo rig",
  uncalibrated: "Uncalibrated: rectified from matched features",
  rectified: "Already rectified",
};

/** Fill `card` with the stereo DEM of `job` (which has succeeded). */
export async function showStereoDem(view, job, card) {
  card.hidden = false;
  card.replaceChildren(h("h2", { id: "result-heading" }, "Result"), h("p", { class: "muted" }, "Loading the surface…"));
  const { signal } = view;
  const data = await api("GET", `/api/stereo-dems/${job.id}`, { signal });
  if (signal.aborted) return;
  const report = (data && data.result) || {};
  const surface = report.surface || {};
  const dsm = surface.surface === "dsm";
  const layer = dsm ? "dsm" : "disparity";
  const [tilejson, outputs, config] = await Promise.all([
    api("GET", `/tiles/${job.id}/${layer}/tilejson.json`, { signal }),
    jobOutputs(job.id, { signal }),
    getConfig(),
  ]);
  if (signal.aborted) return;

  const mapNode = h("div", { class: "map", id: "map", "data-testid": "map", role: "region",
    "aria-label": dsm ? "DSM map" : "Disparity map" });
  const readout = h("p", { class: "readout", "data-testid": "point-readout", role: "status", "aria-live": "polite" },
    dsm ? "Move over the map to read the elevation." : "Move over the map to read the disparity.");
  const legend = dsm ? surface.legend : (report.disparity || {}).legend;
  const controls = h("div", { class: "map-controls" },
    h("div", { class: "control" }, h("h3", {}, dsm ? "Elevation" : "Disparity"), legendNode(legend), readout),
    h("div", { class: "control" }, h("h3", {}, "Figures"), factList(facts(report, dsm))),
    h("div", { class: "control" }, downloadList(outputs.filter((o) => DOWNLOADS[o.name]), (name) => DOWNLOADS[name] || name)));
  card.replaceChildren(
    h("div", { class: "row spread" }, h("h2", { id: "result-heading" }, dsm ? "Surface model" : "Disparity"),
      h("span", { class: "muted small" }, dsm ? `DSM in EPSG:${surface.epsg ?? "–"}, shown on WGS 84 / Web Mercator`
        : "No camera model on the ground: shown in the rectified left view's pixels")),
    ...warningAlerts(report.warnings, "stereo-warning"),
    h("div", { class: "result-grid" }, mapNode, controls),
  );
  const attribution = dsm ? "DSM: Fotoskhema" : "Disparity: Fotoskhema";
  const { map, mosaic, bases } = createMosaicMap(mapNode, tilejson, dsm ? config : null, attribution);
  onAbort(signal, () => map.remove());
  followPointer(view, map, job.id, dsm, readout);
  if (dsm) { // on the ground: measure (and a volume over the DSM), coordinates, the basemap and the DSM's switcher
    const projection = projectionOf(Number.isInteger(surface.epsg) ? `EPSG:${surface.epsg}` : "");
    const tools = measureTool(view, map, { projection, dsm: { jobId: job.id } });
    coordinatesControl(map, projection);
    layerSwitcher(map, bases, { "DSM (shaded relief)": mosaic }, { "DSM (shaded relief)": "layer-dsm", OpenStreetMap: "basemap-osm",
      "Basemap (set by the operator)": "basemap-ops", "No basemap": "basemap-none" });
    controls.prepend(tools.node);
  }
}

function facts(report, dsm) {
  const surface = report.surface || {};
  const disparity = report.disparity || {};
  const rect = report.rectification || {};
  const share = (v) => (typeof v === "number" ? `${(100 * v).toFixed(1)} %` : "–");
  const range = Number.isFinite(disparity.min_disparity) && Number.isFinite(disparity.num_disparities)
    ? `${disparity.min_disparity} to ${disparity.min_disparity + disparity.num_disparities} px (${disparity.range_source || "–"})` : "–";
  const rows = [
    ["Geometry", GEOMETRIES[report.geometry] || report.geometry || "–", { "data-testid": "stereo-geometry" }],
    ["Matcher", MATCHERS[report.method] || humanize(report.method || "–")],
    ["Rows after rectification", formatNumber(rect.row_residual_px, 3, "px")],
    ["Disparities searched", range],
    ["Checked disparities", share(disparity.checked_share), { "data-testid": "checked-share" }],
    ["Filled disparities", share(disparity.filled_share)],
  ];
  if (dsm) {
    rows.push(
      ["DSM cell", formatNumber(surface.resolution_m, 3, "m"), { "data-testid": "dsm-resolution" }],
      ["DSM size", Array.isArray(surface.size) ? `${formatCount(surface.size[0])} × ${formatCount(surface.size[1])} cells` : "–"],
      ["Measured cells", share(surface.measured_share), { "data-testid": "measured-share" }],
      ["Filled cells", share(surface.filled_share)],
    );
  } else if (surface.surface === "depth") {
    rows.push(["Depth", Array.isArray(surface.depth_range)
      ? `${formatNumber(surface.depth_range[0], 1)} to ${formatNumber(surface.depth_range[1], 1)}` : "–"]);
  }
  return rows;
}
