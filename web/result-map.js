/* A finished job's mosaic on a Leaflet map (global `L`, loaded before the modules), with its layers and their
 * switcher (map-layers.js), the measuring tools and cursor coordinates (map-tools.js), a side-by-side comparison
 * with another job of the flight (swipe.js), and its downloads. An ortho job's DSM (dsm.tif: the surface its photos
 * were projected onto) is one more layer, with its legend, the elevation under the cursor and volumes (dsm.js). */

import { api, apiUrl, downloadList, factList, getConfig, h, jobOutputs, jobSignature, onAbort } from "./lib.js";
import { projectionOf } from "./crs.js";
import { basemaps, cameraLayer, createPanes, cutlineLayer, footprintLayer, framePreviewUrl, gcpLayer, layerSwitcher } from "./map-layers.js";
import { coordinatesControl, measureTool } from "./map-tools.js";
import { followPointer, legendNode } from "./dsm.js";
import { swipeControl } from "./swipe.js";

// -- Result: map and downloads ------------------------------------------------------------------

// The switcher's overlay names (constants: L.control.layers writes them as HTML) and their inputs' test ids
const LAYER_IDS = {
  Mosaic: "layer-mosaic",
  "DSM (shaded relief)": "layer-dsm",
  "Frame footprints": "footprints-toggle",
  "Camera centres": "layer-cameras",
  "Ground control points": "layer-gcps",
  "Cut lines (seams)": "cutlines-toggle",
  OpenStreetMap: "basemap-osm",
  "Basemap (set by the operator)": "basemap-ops",
  "No basemap": "basemap-none",
};

/** Fill `card` with the mosaic map; `outputs` and `report` (optional) are promises of the job's outputs list and
 * of its report.json (the Quality card reads them too). */
export async function showResult(view, job, card, outputs, report) {
  card.hidden = false;
  card.replaceChildren(h("h2", { id: "result-heading" }, "Result"), h("p", { class: "muted" }, "Loading the mosaic…"));
  const { signal } = view;
  const [tilejson, outputList, config, reportData, signature] = await Promise.all([
    api("GET", `/tiles/${job.id}/tilejson.json`, { signal }),
    outputs || jobOutputs(job.id, { signal }),
    getConfig(),
    Promise.resolve(report).catch(() => null),
    typeof job.signature === "string" ? job.signature : jobSignature(job.id, { signal }).catch(() => ""),
  ]);
  if (signal.aborted) return;
  const byName = Object.fromEntries(outputList.map((o) => [o.name, o]));
  const georeferenced = tilejson.georeferenced !== false;
  // an ortho job's surface as a DSM: shown when its tiles answer (a job without one has no dsm.tif)
  const dsmTiles = georeferenced && byName["dsm.tif"]
    ? await api("GET", `/tiles/${job.id}/dsm/tilejson.json`, { signal }).catch(() => null) : null;
  if (signal.aborted) return;
  const projection = georeferenced ? projectionOf(reportData && reportData.crs) : null;

  const mapNode = h("div", { class: "map", id: "map", "data-testid": "map", role: "region", "aria-label": "Mosaic map" });
  const controls = h("div", { class: "map-controls" });
  card.replaceChildren(
    h("div", { class: "row spread" }, h("h2", { id: "result-heading" }, "Result"),
      h("span", { class: "muted small", "data-testid": "map-crs" }, georeferenced
        ? `Mosaic in ${projection ? `${projection.code} (${projection.name})` : "map coordinates"}, shown on WGS 84 / Web Mercator`
        : "Not georeferenced: shown in mosaic pixels")),
    h("div", { class: "result-grid" }, mapNode, controls),
  );
  const { map, mosaic, bases } = createMosaicMap(mapNode, tilejson, georeferenced ? config : null);
  onAbort(view.signal, () => map.remove());
  controls.append(opacityControl(mosaic));
  if (georeferenced) {
    const dsm = dsmTiles ? { tilejson: dsmTiles, report: (reportData && reportData.dsm) || {} } : null;
    controls.append(...mapLayers(view, map, { job, byName, mosaic, bases, projection, signature, dsm, mode: reportData && reportData.mode }));
  } else {
    controls.append(footprintUnavailable(false));
  }
  controls.append(mosaicDownloads(byName), mosaicFacts(tilejson, georeferenced));
}

/** The layers of a georeferenced mosaic, their switcher, and the side-panel blocks of the tools. */
function mapLayers(view, map, { job, byName, mosaic, bases, projection, signature, dsm, mode }) {
  const tools = measureTool(view, map, { projection, dsm: dsm ? { jobId: job.id } : null });
  coordinatesControl(map, projection);
  const overlays = { Mosaic: mosaic };
  const blocks = [tools.node];
  if (dsm) {
    overlays["DSM (shaded relief)"] = L.tileLayer(dsm.tilejson.tiles[0], overlayOptions(dsm.tilejson, "DSM: Fotoskhema"));
    blocks.push(elevationBlock(view, map, job, dsm.report));
  }
  const footprintsUrl = apiUrl((byName["footprints.geojson"] || {}).url); // fetched from this service only
  if (footprintsUrl) {
    const footprints = footprintLayer(view, { url: footprintsUrl, mode, photoUrl: framePreviewUrl(job.id, signature), tools });
    overlays["Frame footprints"] = footprints.layer.addTo(map);
    const cameras = L.layerGroup();
    overlays["Camera centres"] = cameras.addTo(map);
    footprints.loaded.then((features) => {
      if (!view.signal.aborted) cameraLayer(features, tools, footprints.show).addTo(cameras);
    });
    blocks.push(footprints.node);
  } else {
    blocks.push(footprintUnavailable(true));
  }
  const gcpsUrl = apiUrl((byName["gcps.geojson"] || {}).url);
  if (gcpsUrl) overlays["Ground control points"] = gcpLayer(view, gcpsUrl, tools).layer.addTo(map);
  const cutlinesUrl = apiUrl((byName["cutlines.geojson"] || {}).url); // a multiband mosaic's seams only: off at first
  if (cutlinesUrl) overlays["Cut lines (seams)"] = cutlineLayer(view, cutlinesUrl);
  layerSwitcher(map, bases, overlays, LAYER_IDS);
  blocks.push(swipeControl(view, map, job));
  return blocks;
}

/** An ortho job's DSM in the side panel: its legend, the elevation under the cursor, its cell and what was measured. */
function elevationBlock(view, map, job, report) {
  const readout = h("p", { class: "readout", "data-testid": "point-readout", role: "status", "aria-live": "polite" },
    "Move over the map to read the elevation.");
  followPointer(view, map, job.id, true, readout);
  const measured = typeof report.measured_share === "number" ? `${(100 * report.measured_share).toFixed(0)} % measured by stereo` : "";
  const cell = typeof report.resolution_m === "number" ? `DSM cell ${report.resolution_m.toFixed(2)} m` : "";
  return h("div", { class: "control", "data-testid": "elevation" }, h("h3", {}, "Elevation"),
    legendNode(report.legend, "Heights as the photos' GPS altitudes (or the control points) give them"), readout,
    h("p", { class: "muted small", "data-testid": "dsm-facts" }, [cell, measured].filter(Boolean).join(" · ")));
}

/** Leaflet options of a georeferenced overlay's tiles (a DSM over the mosaic): its bounds and zooms, off at first. */
function overlayOptions(tilejson, attribution) {
  const [west, south, east, north] = tilejson.bounds;
  const maxzoom = Number.isFinite(tilejson.maxzoom) ? tilejson.maxzoom : 22;
  return { bounds: insetBounds(west, south, east, north), noWrap: true, tileSize: 256, attribution, pane: "mosaic", zIndex: 2,
    minNativeZoom: Number.isFinite(tilejson.minzoom) ? tilejson.minzoom : 0, maxNativeZoom: maxzoom, maxZoom: maxzoom + 8 };
}

/** The tile layer's bounds, pulled in by a hair: a tile that only touches the mosaic's edge would
 * otherwise be requested, answered 404 by the tile route, and logged as an error by the browser. */
function insetBounds(west, south, east, north) {
  const dx = (east - west) * 1e-6;
  const dy = (north - south) * 1e-6;
  return L.latLngBounds([south + dy, west + dx], [north - dy, east - dx]);
}

/** A Leaflet map of a TileJSON's layer: on the Earth (over the basemap `config` names, from /api/config; none
 * when `config` is null) when it is georeferenced, in Leaflet's CRS.Simple (one map unit per raster pixel, y
 * negated) otherwise. Answers { map, mosaic, bases } (bases: the base layers for a layer switcher). */
export function createMosaicMap(node, tilejson, config, attribution = "Mosaic: Fotoskhema") {
  const [west, south, east, north] = tilejson.bounds;
  const bounds = L.latLngBounds([south, west], [north, east]);
  const minzoom = Number.isFinite(tilejson.minzoom) ? tilejson.minzoom : 0;
  const maxzoom = Number.isFinite(tilejson.maxzoom) ? tilejson.maxzoom : 22;
  const layerOptions = {
    bounds: insetBounds(west, south, east, north),
    noWrap: true,
    tileSize: 256,
    attribution,
    pane: "mosaic",
  };
  // Whole zoom levels only (Leaflet's default zoomSnap): at a fractional zoom the tiles are scaled and
  // hairline seams show between them; whole levels also show the mosaic's pixels one to one.
  let map;
  let bases = {};
  if (tilejson.georeferenced === false) {
    // Local pixel grid: Leaflet's CRS.Simple has 1 map unit per screen pixel at zoom 0, and the tile
    // grid has 1 mosaic pixel per tile pixel at maxzoom, so map zoom 0 is tile zoom `maxzoom`.
    map = L.map(node, { crs: L.CRS.Simple, minZoom: minzoom - maxzoom - 2, maxZoom: 3 });
    Object.assign(layerOptions, { zoomOffset: maxzoom, minNativeZoom: minzoom - maxzoom, maxNativeZoom: 0, minZoom: minzoom - maxzoom - 2, maxZoom: 3 });
  } else {
    map = L.map(node, { minZoom: Math.max(0, minzoom - 3), maxZoom: maxzoom + 2 });
    Object.assign(layerOptions, { minNativeZoom: minzoom, maxNativeZoom: maxzoom, maxZoom: maxzoom + 2 });
    if (config) {
      const choice = basemaps(config, maxzoom + 2);
      bases = choice.layers;
      bases[choice.initial].addTo(map);
    }
    L.control.scale({ imperial: false }).addTo(map);
  }
  createPanes(map);
  const mosaic = L.tileLayer(tilejson.tiles[0], layerOptions).addTo(map);
  map.fitBounds(bounds, { padding: [12, 12] });
  return { map, mosaic, bases };
}

function opacityControl(layer) {
  const output = h("output", { for: "opacity", class: "muted small" }, "100 %");
  const slider = h("input", { id: "opacity", type: "range", min: 0, max: 100, step: 5, value: 100, "data-testid": "opacity" });
  slider.addEventListener("input", () => {
    layer.setOpacity(Number(slider.value) / 100);
    output.textContent = `${slider.value} %`;
  });
  return h("div", { class: "control" }, h("label", { for: "opacity" }, "Mosaic opacity ", output), slider);
}

function footprintUnavailable(georeferenced) {
  return h("div", { class: "control" }, h("p", { class: "muted small" },
    georeferenced ? "No frame footprints for this job." : "Frame footprints need GPS: this mosaic has none."));
}

// The mosaic's downloads, in this order; the footprints only when the job wrote them.
const DOWNLOADS = {
  "mosaic.tif": { label: "Mosaic (Cloud-Optimized GeoTIFF)", testid: "download-cog" },
  "dsm.tif": { label: "DSM, the surface the photos were projected onto (Cloud-Optimized GeoTIFF, m)", testid: "download-dsm", optional: true },
  "dsm_mask.tif": { label: "DSM cells measured (1) or interpolated (2)", testid: "download-dsm-mask", optional: true },
  "report.json": { label: "Processing report", testid: "download-report" },
  "footprints.geojson": { label: "Frame footprints", testid: "download-footprints", optional: true },
  "cutlines.geojson": { label: "Cut lines (each frame's region)", testid: "download-cutlines", optional: true },
  "gcps.geojson": { label: "Ground control points as the map has them", testid: "download-gcps", optional: true },
};

function mosaicDownloads(byName) {
  const shown = Object.entries(DOWNLOADS).filter(([name, d]) => byName[name] || !d.optional)
    .map(([name]) => byName[name] || { name }); // without a url: "(not available)"
  return h("div", { class: "control" }, downloadList(shown, (name) => DOWNLOADS[name].label, (name) => DOWNLOADS[name].testid));
}

function mosaicFacts(tilejson, georeferenced) {
  const [west, south, east, north] = tilejson.bounds;
  const rows = georeferenced
    ? [["West, south", `${west.toFixed(6)}, ${south.toFixed(6)}`], ["East, north", `${east.toFixed(6)}, ${north.toFixed(6)}`]]
    : [["Size", `${Math.round(east - west)} × ${Math.round(north - south)} px`]];
  rows.push(["Zoom levels", `${tilejson.minzoom} – ${tilejson.maxzoom}`]);
  return h("div", { class: "control" }, h("h3", {}, "Extent"),
    factList(rows));
}
