/* A finished job's mosaic on a Leaflet map (global `L`, loaded before the modules), with its downloads. */

import { api, apiUrl, downloadList, factList, getConfig, h, jobOutputs, onAbort } from "./lib.js";

// -- Result: map and downloads ------------------------------------------------------------------

/** Fill `card` with the mosaic map; `outputs` (optional) is a promise of the job's outputs list. */
export async function showResult(view, job, card, outputs) {
  card.hidden = false;
  card.replaceChildren(h("h2", { id: "result-heading" }, "Result"), h("p", { class: "muted" }, "Loading the mosaic…"));
  const { signal } = view;
  const [tilejson, outputList, config] = await Promise.all([
    api("GET", `/tiles/${job.id}/tilejson.json`, { signal }),
    outputs || jobOutputs(job.id, { signal }),
    getConfig(),
  ]);
  if (signal.aborted) return;
  const byName = Object.fromEntries(outputList.map((o) => [o.name, o]));
  const georeferenced = tilejson.georeferenced !== false;

  const mapNode = h("div", { class: "map", id: "map", "data-testid": "map", role: "region", "aria-label": "Mosaic map" });
  const controls = h("div", { class: "map-controls" });
  card.replaceChildren(
    h("div", { class: "row spread" }, h("h2", { id: "result-heading" }, "Result"),
      h("span", { class: "muted small" }, georeferenced ? "Georeferenced (WGS 84 / Web Mercator)" : "Not georeferenced: shown in mosaic pixels")),
    h("div", { class: "result-grid" }, mapNode, controls),
  );
  const { map, mosaic } = createMosaicMap(mapNode, tilejson, georeferenced ? config.basemap_url : "");
  onAbort(view.signal, () => map.remove());

  controls.append(opacityControl(mosaic));
  const footprints = apiUrl((byName["footprints.geojson"] || {}).url); // fetched from this service only
  controls.append(georeferenced && footprints ? footprintControl(view, map, footprints) : footprintUnavailable(georeferenced));
  const cutlines = apiUrl((byName["cutlines.geojson"] || {}).url); // a multiband mosaic's seams only
  if (georeferenced && cutlines) controls.append(cutlineControl(view, map, cutlines));
  controls.append(mosaicDownloads(byName), mosaicFacts(tilejson, georeferenced));
}

/** The tile layer's bounds, pulled in by a hair: a tile that only touches the mosaic's edge would
 * otherwise be requested, answered 404 by the tile route, and logged as an error by the browser. */
function insetBounds(west, south, east, north) {
  const dx = (east - west) * 1e-6;
  const dy = (north - south) * 1e-6;
  return L.latLngBounds([south + dy, west + dx], [north - dy, east - dx]);
}

/** A Leaflet map of a TileJSON's layer: on the Earth (over an optional basemap) when it is georeferenced,
 * in Leaflet's CRS.Simple (one map unit per raster pixel, y negated) otherwise. Answers { map, mosaic }. */
export function createMosaicMap(node, tilejson, basemapUrl, attribution = "Mosaic: Fotoskhema") {
  const [west, south, east, north] = tilejson.bounds;
  const bounds = L.latLngBounds([south, west], [north, east]);
  const minzoom = Number.isFinite(tilejson.minzoom) ? tilejson.minzoom : 0;
  const maxzoom = Number.isFinite(tilejson.maxzoom) ? tilejson.maxzoom : 22;
  const layerOptions = {
    bounds: insetBounds(west, south, east, north),
    noWrap: true,
    tileSize: 256,
    attribution,
  };
  // Whole zoom levels only (Leaflet's default zoomSnap): at a fractional zoom the tiles are scaled and
  // hairline seams show between them; whole levels also show the mosaic's pixels one to one.
  let map;
  if (tilejson.georeferenced === false) {
    // Local pixel grid: Leaflet's CRS.Simple has 1 map unit per screen pixel at zoom 0, and the tile
    // grid has 1 mosaic pixel per tile pixel at maxzoom, so map zoom 0 is tile zoom `maxzoom`.
    map = L.map(node, { crs: L.CRS.Simple, minZoom: minzoom - maxzoom - 2, maxZoom: 3 });
    Object.assign(layerOptions, { zoomOffset: maxzoom, minNativeZoom: minzoom - maxzoom, maxNativeZoom: 0, minZoom: minzoom - maxzoom - 2, maxZoom: 3 });
  } else {
    map = L.map(node, { minZoom: Math.max(0, minzoom - 3), maxZoom: maxzoom + 2 });
    Object.assign(layerOptions, { minNativeZoom: minzoom, maxNativeZoom: maxzoom, maxZoom: maxzoom + 2 });
    if (basemapUrl) {
      // Leaflet shows an attribution as HTML; a parsed URL's hostname cannot hold a "<" (a forbidden host
      // code point), so this one cannot open a tag. The basemap URL is the operator's setting, not a user's.
      L.tileLayer(basemapUrl, { maxZoom: maxzoom + 2, attribution: `Basemap: ${hostOf(basemapUrl)}` }).addTo(map);
    }
    L.control.scale({ imperial: false }).addTo(map);
  }
  const mosaic = L.tileLayer(tilejson.tiles[0], layerOptions).addTo(map);
  map.fitBounds(bounds, { padding: [12, 12] });
  return { map, mosaic };
}

function hostOf(url) {
  try {
    return new URL(url).hostname;
  } catch {
    return "external";
  }
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

function footprintControl(view, map, url) {
  return geojsonControl(view, map, url, {
    id: "footprints", label: " Frame footprints ", checked: true,
    style: { color: "#f59e0b", weight: 1.5, opacity: 0.9, fillOpacity: 0.04 },
  });
}

/** The regions each frame owns in a multiband mosaic: their borders are the seams. Off at first. */
function cutlineControl(view, map, url) {
  return geojsonControl(view, map, url, {
    id: "cutlines", label: " Cut lines (seams) ", checked: false,
    style: { color: "#e11d48", weight: 1.2, opacity: 0.95, fill: false, dashArray: "4 3" },
  });
}

/** A checkbox and a GeoJSON layer of per-frame polygons (properties index, name) fetched from `url`. */
function geojsonControl(view, map, url, { id, label, checked, style }) {
  const box = h("input", { id, type: "checkbox", checked, "data-testid": `${id}-toggle` });
  const note = h("span", { class: "muted small" });
  let layer = null;
  box.addEventListener("change", () => {
    if (!layer) return;
    if (box.checked) layer.addTo(map);
    else layer.remove();
  });
  fetch(url, { signal: view.signal })
    .then((response) => (response.ok ? response.json() : Promise.reject(new Error(`${response.status}`))))
    .then((geojson) => {
      if (view.signal.aborted) return;
      layer = L.geoJSON(geojson, {
        style,
        onEachFeature: (feature, featureLayer) => {
          // A node, not a string: Leaflet sets a string tooltip as HTML, and the name is the photo's file name.
          const props = feature.properties || {};
          featureLayer.bindTooltip(h("span", { class: "footprint-tooltip" }, `Frame ${props.index ?? "?"}`,
            props.name ? `: ${props.name}` : ""), { sticky: true });
        },
      });
      if (box.checked) layer.addTo(map);
      note.textContent = `${(geojson.features || []).length} frames`;
    })
    .catch((err) => {
      if (view.signal.aborted) return;
      box.disabled = true;
      note.textContent = `unavailable (${err.message})`;
    });
  return h("div", { class: "control" }, h("label", { class: "check" }, box, label), note);
}

function footprintUnavailable(georeferenced) {
  return h("div", { class: "control" }, h("p", { class: "muted small" },
    georeferenced ? "No frame footprints for this job." : "Frame footprints need GPS: this mosaic has none."));
}

// The mosaic's downloads, in this order; the footprints only when the job wrote them.
const DOWNLOADS = {
  "mosaic.tif": { label: "Mosaic (Cloud-Optimized GeoTIFF)", testid: "download-cog" },
  "report.json": { label: "Processing report", testid: "download-report" },
  "footprints.geojson": { label: "Frame footprints", testid: "download-footprints", optional: true },
  "cutlines.geojson": { label: "Cut lines (each frame's region)", testid: "download-cutlines", optional: true },
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
