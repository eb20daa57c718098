/* The layers of a result map and their switcher (Leaflet's own L.control.layers): the basemap (OpenStreetMap by
 * default while the browser is online, another one ops set, or none), the mosaic, frame footprints coloured by
 * each photo's residual with a legend (click one: its photo and figures), camera centres with their GPS
 * residuals, ground control points with theirs, and cut lines.
 *
 * L.control.layers writes each layer's name as HTML: only the constant names below go there, never a photo's
 * or a point's name. Those are set as text in tooltips and cards (nodes built with h()). */

import { apiUrl, factList, formatMetres, formatNumber, h, onAbort, signedUrl } from "./lib.js";
import { label } from "./labels.js";

const OSM_ATTRIBUTION = '&copy; <a href="https://www.openstreetmap.org/copyright">OpenStreetMap</a> contributors';
const NO_BASEMAP = "No basemap";
// pane name -> z-index: above the basemap (tilePane 200), around the vector overlays (400), below tooltips (650)
const PANES = { mosaic: 250, compare: 260, cameras: 610, gcps: 620 };
const RAMP = ["#1a9850", "#91cf60", "#fee08b", "#fc8d59", "#d73027"]; // small residual -> large
const NO_VALUE = "#9ca3af";
const FOOTPRINT = { weight: 1.5, opacity: 0.95, fillOpacity: 0.08 };
const CUTLINE = { color: "#e11d48", weight: 1.2, opacity: 0.95, fill: false, dashArray: "4 3" };

/** Create the panes the layers go in (once per map). */
export function createPanes(map) {
  for (const [name, z] of Object.entries(PANES)) {
    if (!map.getPane(name)) map.createPane(name).style.zIndex = String(z);
  }
}

/**
 * The base layers: `{ layers: { name: layer }, initial }`. The operator's basemap (config.basemap_url, from
 * /api/config: OpenStreetMap unless set otherwise, "" when turned off) is shown first while the browser is
 * online; offline, or without one, none.
 */
export function basemaps(config, maxZoom) {
  const layers = {};
  const url = config && typeof config.basemap_url === "string" ? config.basemap_url : "";
  let initial = NO_BASEMAP;
  if (url) {
    const osm = config.basemap_name === "OpenStreetMap";
    const name = osm ? "OpenStreetMap" : "Basemap (set by the operator)";
    // The attribution is HTML: OpenStreetMap's is a constant; another's is its host as the browser parsed it
    // (a hostname cannot hold a "<"), the operator's setting, not a user's.
    layers[name] = L.tileLayer(url, { maxZoom, attribution: osm ? OSM_ATTRIBUTION : `Basemap: ${hostOf(url)}` });
    if (navigator.onLine !== false) initial = name;
  }
  layers[NO_BASEMAP] = L.layerGroup();
  return { layers, initial };
}

function hostOf(url) {
  try {
    return new URL(url).hostname;
  } catch {
    return "external";
  }
}

/**
 * Leaflet's layer switcher over `bases` and `overlays` ({ name: layer }), open on the map; each input gets the
 * test id `testids[name]` (the footprints' and cut lines' keep the ids of the checkboxes they replaced).
 */
export function layerSwitcher(map, bases, overlays, testids) {
  const control = L.control.layers(bases, overlays, { collapsed: false, position: "topright", sortLayers: false }).addTo(map);
  const container = control.getContainer();
  container.setAttribute("data-testid", "layer-switcher");
  container.setAttribute("aria-label", "Layers");
  for (const labelNode of container.querySelectorAll("label")) {
    const name = labelNode.textContent.trim();
    const input = labelNode.querySelector("input");
    if (input && testids[name]) input.setAttribute("data-testid", testids[name]);
  }
  return control;
}

// -- Footprints ------------------------------------------------------------------------------------------------

/** What the footprints can be coloured by, from the properties write_report gives them. */
function colourings(mode) {
  return [
    { key: "rms_px", label: mode === "ortho" ? "Reprojection RMS" : "Tie-point RMS", unit: "px", digits: 2 },
    { key: "gps_residual_m", label: "GPS residual", unit: "m", digits: 2 },
    ...(mode === "strip" ? [{ key: "corner_sigma_m", label: "Precision", unit: "m", digits: 2 }] : []),
    { key: "", label: "One colour" },
  ];
}

/** A colour of RAMP for `t` in [0, 1]. */
export function rampColour(t) {
  const x = Math.max(0, Math.min(1, t)) * (RAMP.length - 1);
  const i = Math.min(RAMP.length - 2, Math.floor(x));
  const mix = (a, b) => Math.round(a + (b - a) * (x - i));
  const [r1, g1, b1] = rgb(RAMP[i]);
  const [r2, g2, b2] = rgb(RAMP[i + 1]);
  return `rgb(${mix(r1, r2)}, ${mix(g1, g2)}, ${mix(b1, b2)})`;
}

function rgb(hex) {
  return [1, 3, 5].map((k) => parseInt(hex.slice(k, k + 2), 16));
}

/**
 * The footprints layer (an L.geoJSON filled once `url` answers) with its side-panel block: colour by a residual,
 * the legend, and the photo card a click (or the photo list) opens. `photoUrl(index)` is the signed preview of a
 * frame; `tools.active()` says a measurement is under way (a click is then a point, not a photo).
 */
export function footprintLayer(view, { url, mode, photoUrl, tools }) {
  const choices = colourings(mode);
  const select = h("select", { id: "colour-by", "data-testid": "colour-by" },
    choices.map((c) => h("option", { value: c.key }, c.label)));
  const legend = h("div", { class: "ramp", "data-testid": "footprint-legend" });
  const note = h("p", { class: "muted small", "data-testid": "footprint-note" }, "Loading the footprints…");
  const pick = h("select", { id: "photo-pick", "data-testid": "photo-pick", disabled: true },
    h("option", { value: "" }, "Choose a photo…"));
  const card = h("div", { class: "photo-card", "data-testid": "photo-detail", hidden: true });
  let features = [];
  let chosen = null;
  const byIndex = new Map();

  const layer = L.geoJSON(null, {
    style: () => ({ ...FOOTPRINT, color: NO_VALUE }),
    onEachFeature: (feature, featureLayer) => {
      const props = feature.properties || {};
      // A node, not a string: Leaflet sets a string tooltip as HTML, and the name is the photo's file name.
      featureLayer.bindTooltip(h("span", { class: "footprint-tooltip" }, `Frame ${props.index ?? "?"}`,
        props.name ? `: ${props.name}` : ""), { sticky: true });
      featureLayer.on("click", () => {
        if (!tools || !tools.active()) show(props.index);
      });
      byIndex.set(props.index, featureLayer);
    },
  });

  function colour() {
    const choice = choices.find((c) => c.key === select.value) || choices[0];
    const values = features.map((f) => (f.properties || {})[choice.key]).filter((v) => typeof v === "number" && Number.isFinite(v));
    const top = values.length ? Math.max(...values) : 0;
    layer.setStyle((feature) => {
      const value = (feature.properties || {})[choice.key];
      const colourOf = choice.key && typeof value === "number" && top > 0 ? rampColour(value / top)
        : choice.key && typeof value === "number" ? RAMP[0] : choice.key ? NO_VALUE : "#f59e0b";
      const selected = chosen !== null && (feature.properties || {}).index === chosen;
      return { ...FOOTPRINT, color: selected ? "#111827" : colourOf, fillColor: colourOf, weight: selected ? 3.5 : 1.5 };
    });
    legend.replaceChildren(...legendNodes(choice, top, values.length, features.length));
  }

  function show(index) {
    const feature = features.find((f) => (f.properties || {}).index === index);
    if (!feature) return;
    chosen = index;
    pick.value = String(index);
    colour();
    card.hidden = false;
    card.replaceChildren(...photoCard(feature.properties || {}, photoUrl, mode));
    const shown = byIndex.get(index);
    if (shown && shown.bringToFront) shown.bringToFront();
  }

  select.addEventListener("change", colour);
  pick.addEventListener("change", () => (pick.value === "" ? null : show(Number(pick.value))));
  const loaded = fetch(url, { signal: view.signal })
    .then((response) => (response.ok ? response.json() : Promise.reject(new Error(`${response.status}`))))
    .then((geojson) => {
      if (view.signal.aborted) return [];
      features = Array.isArray(geojson.features) ? geojson.features : [];
      layer.addData(geojson);
      colour();
      pick.disabled = !features.length;
      pick.append(...features.map((f) => {
        const p = f.properties || {};
        return h("option", { value: p.index }, `Frame ${p.index}${p.name ? `: ${p.name}` : ""}`);
      }));
      note.textContent = `${features.length} frames. Click a footprint, or choose a photo, to see it and its figures.`;
      return features;
    })
    .catch((err) => {
      if (!view.signal.aborted) note.textContent = `Footprints unavailable (${err.message}).`;
      return [];
    });
  const node = h("div", { class: "control", "data-testid": "footprint-block" },
    h("h3", {}, "Photos"),
    h("div", { class: "control-row" }, h("label", { for: "colour-by" }, "Colour footprints by"), select),
    legend,
    note,
    h("div", { class: "control-row" }, h("label", { for: "photo-pick" }, "Photo"), pick),
    card);
  return { layer, node, loaded, show };
}

function valueText(choice, value) {
  return choice.unit === "m" ? formatMetres(value) : formatNumber(value, choice.digits, choice.unit);
}

function legendNodes(choice, top, measured, total) {
  if (!choice.key) return [h("p", { class: "muted small" }, "Every footprint in one colour.")];
  if (!measured) return [h("p", { class: "muted small" }, `No photo has a ${choice.label.toLowerCase()}.`)];
  const bar = h("div", { class: "ramp-bar", "data-testid": "legend-bar", role: "img",
    "aria-label": `${choice.label}: green 0 to red ${valueText(choice, top)}` });
  bar.style.background = `linear-gradient(to right, ${RAMP.join(", ")})`;
  return [
    bar,
    h("div", { class: "ramp-labels muted small" }, h("span", {}, valueText(choice, 0)),
      h("span", {}, valueText(choice, top / 2)), h("span", {}, valueText(choice, top))),
    measured < total ? h("p", { class: "muted small" }, h("span", { class: "swatch", style: `background:${NO_VALUE}` }), ` ${total - measured} without a value`) : null,
  ].filter(Boolean);
}

function photoCard(props, photoUrl, mode) {
  const lonlat = (v) => (Array.isArray(v) && v.length === 2 && v.every(Number.isFinite) ? `${v[1].toFixed(7)}, ${v[0].toFixed(7)}` : "–");
  const src = photoUrl(props.index);
  return [
    h("h4", {}, `Frame ${props.index ?? "?"}`, props.name ? `: ${props.name}` : ""),
    src ? h("img", { class: "photo-preview", src, alt: `Photo ${props.name || props.index}`, "data-testid": "photo-preview", loading: "lazy" }) : null,
    factList([
      [mode === "ortho" ? "Reprojection RMS" : "Tie-point RMS", formatNumber(props.rms_px, 2, "px"), { "data-testid": "photo-rms" }],
      ["GPS residual", formatMetres(props.gps_residual_m), { "data-testid": "photo-gps-residual" }],
      ...(typeof props.corner_sigma_m === "number"
        ? [["Corners known to (1σ)", formatMetres(props.corner_sigma_m), { "data-testid": "photo-corner-sigma" }]]
        : []),
      ["GPS fix (lat, lon)", lonlat(props.gps)],
      [mode === "ortho" ? "Camera (lat, lon)" : "Photo centre (lat, lon)", lonlat(props.camera)],
    ]),
  ].filter(Boolean);
}

// -- Camera centres and ground control points -------------------------------------------------------------------

/** Camera centres (each footprint's `camera`), each with a line to its GPS fix: the GPS residual, to scale. */
export function cameraLayer(features, tools, onPick) {
  const group = L.layerGroup();
  for (const f of features) {
    const p = f.properties || {};
    if (!validLonLat(p.camera)) continue;
    const at = L.latLng(p.camera[1], p.camera[0]);
    if (validLonLat(p.gps)) {
      L.polyline([at, L.latLng(p.gps[1], p.gps[0])], { pane: "cameras", color: "#7c3aed", weight: 1.5, opacity: 0.9, interactive: false }).addTo(group);
    }
    const marker = L.circleMarker(at, { pane: "cameras", radius: 4, color: "#ffffff", weight: 1.5, fillColor: "#7c3aed",
      fillOpacity: 1, bubblingMouseEvents: false });
    marker.bindTooltip(h("span", {}, `Camera of frame ${p.index ?? "?"}`, p.name ? `: ${p.name}` : "",
      typeof p.gps_residual_m === "number" ? `, ${formatMetres(p.gps_residual_m)} from its GPS fix` : ""));
    marker.on("click", () => {
      if (!tools.pick(at)) onPick(p.index);
    });
    marker.addTo(group);
  }
  return group;
}

/** Ground control points at their surveyed positions, each with a line to where the map puts it. */
export function gcpLayer(view, url, tools) {
  const group = L.layerGroup();
  const loaded = fetch(url, { signal: view.signal })
    .then((response) => (response.ok ? response.json() : Promise.reject(new Error(`${response.status}`))))
    .then((geojson) => {
      const points = (Array.isArray(geojson.features) ? geojson.features : []).filter((f) => f && f.geometry && validLonLat(f.geometry.coordinates));
      for (const f of points) addGcp(group, f, tools);
      return points;
    })
    .catch(() => []);
  onAbort(view.signal, () => group.clearLayers());
  return { layer: group, loaded };
}

function addGcp(group, feature, tools) {
  const p = feature.properties || {};
  const [lon, lat] = feature.geometry.coordinates;
  const at = L.latLng(lat, lon);
  if (validLonLat(p.mapped)) {
    L.polyline([at, L.latLng(p.mapped[1], p.mapped[0])], { pane: "gcps", color: "#dc2626", weight: 2, interactive: false }).addTo(group);
  }
  const checkpoint = p.role === "checkpoint";
  const marker = L.circleMarker(at, { pane: "gcps", radius: 7, color: checkpoint ? "#dc2626" : "#1d4ed8", weight: 2.5,
    fillColor: "#ffffff", fillOpacity: 0.9, bubblingMouseEvents: false, className: "gcp-marker" });
  const error = Array.isArray(p.error_m) && p.error_m.length >= 2
    ? `; the map has it ${formatMetres(p.error_horizontal_m)} away (east ${formatMetres(p.error_m[0])}, north ${formatMetres(p.error_m[1])})`
    : "";
  marker.bindTooltip(h("span", { class: "gcp-tooltip" }, "GCP ", h("strong", {}, String(p.id ?? "?")),
    ` (${label("gcp_role", p.role || "")})`, error));
  marker.on("click", () => tools.pick(at));
  marker.addTo(group);
}

function validLonLat(v) {
  return Array.isArray(v) && v.length >= 2 && Number.isFinite(v[0]) && Number.isFinite(v[1]) && Math.abs(v[0]) <= 180 && Math.abs(v[1]) <= 90;
}

/** A GeoJSON layer of per-frame polygons (cut lines), filled once `url` answers. */
export function cutlineLayer(view, url) {
  const layer = L.geoJSON(null, { style: CUTLINE, interactive: false });
  fetch(url, { signal: view.signal })
    .then((response) => (response.ok ? response.json() : Promise.reject(new Error(`${response.status}`))))
    .then((geojson) => {
      if (!view.signal.aborted) layer.addData(geojson);
    })
    .catch(() => {});
  return layer;
}

/** The signed URL of frame `index`'s preview (GET /api/jobs/<id>/photos/<index>/preview) of job `jobId`. */
export function framePreviewUrl(jobId, signature) {
  return (index) => (Number.isInteger(index) ? apiUrl(signedUrl(`/api/jobs/${jobId}/photos/${index}/preview?size=640`, signature)) : null);
}
