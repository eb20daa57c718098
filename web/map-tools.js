/* Tools on a georeferenced result map: measure a distance or an area on the ground, and, over a DSM, the volume
 * above a base; the cursor's coordinates in longitude/latitude and in the raster's CRS.
 *
 * Distances and areas are geodesic on the WGS 84 ellipsoid (GeographicLib's `geodesic.Geodesic.WGS84`, the
 * global of the vendored geographiclib-geodesic: Karney's algorithms, exact to the nanometre), so they are the
 * lengths on the ground whatever the map's projection; the same figure on the grid of the raster's CRS (a UTM
 * zone: its scale factor makes it differ by up to a few parts in 10 000) is shown beside it. A click on a ground
 * control point or a camera centre (`tools.pick`) puts the vertex exactly there. */

import { api, formatNumber, h, messageOf, onAbort } from "./lib.js";
import { formatEastNorth } from "./crs.js";

const LINE = { color: "#2563eb", weight: 3, opacity: 0.95, dashArray: "6 4", interactive: false };
const AREA = { ...LINE, fillColor: "#2563eb", fillOpacity: 0.12 };
const VERTEX = { radius: 4, color: "#ffffff", weight: 2, fillColor: "#2563eb", fillOpacity: 1, interactive: false };

// -- Geodesy ---------------------------------------------------------------------------------------------------

function ellipsoid() {
  return geodesic.Geodesic.WGS84;
}

/** Length in metres of the geodesic polyline through `points` (Leaflet LatLngs). */
export function geodesicLength(points) {
  let total = 0;
  for (let i = 1; i < points.length; i += 1) {
    total += ellipsoid().Inverse(points[i - 1].lat, points[i - 1].lng, points[i].lat, points[i].lng).s12;
  }
  return total;
}

/** `{ area, perimeter }` (m², m) of the geodesic polygon through `points`. */
export function geodesicArea(points) {
  const polygon = ellipsoid().Polygon(false);
  for (const p of points) polygon.AddPoint(p.lat, p.lng);
  const result = polygon.Compute(false, true);
  return { area: Math.abs(result.area), perimeter: result.perimeter };
}

/** Length (m) of the polyline on the grid of `projection` (crs.js), or null without one. */
export function gridLength(points, projection) {
  const xy = projected(points, projection);
  if (!xy) return null;
  let total = 0;
  for (let i = 1; i < xy.length; i += 1) total += Math.hypot(xy[i][0] - xy[i - 1][0], xy[i][1] - xy[i - 1][1]);
  return total;
}

/** Area (m²) of the polygon on the grid of `projection` (the shoelace formula), or null without one. */
export function gridArea(points, projection) {
  const xy = projected(points, projection);
  if (!xy) return null;
  let twice = 0;
  for (let i = 0; i < xy.length; i += 1) {
    const [x1, y1] = xy[i];
    const [x2, y2] = xy[(i + 1) % xy.length];
    twice += x1 * y2 - x2 * y1;
  }
  return Math.abs(twice) / 2;
}

function projected(points, projection) {
  return projection && projection.project ? points.map((p) => projection.project([p.lng, p.lat])) : null;
}

/** "12.34 m", "1 234.57 m (1.235 km)". */
export function formatLength(m) {
  if (!Number.isFinite(m)) return "–";
  const metres = `${grouped(m.toFixed(2))} m`;
  return m >= 1000 ? `${metres} (${(m / 1000).toFixed(3)} km)` : metres;
}

/** "123.4 m²", "12 345.6 m² (1.2346 ha)". */
export function formatArea(m2) {
  if (!Number.isFinite(m2)) return "–";
  const square = `${grouped(m2.toFixed(1))} m²`;
  return m2 >= 10000 ? `${square} (${(m2 / 10000).toFixed(4)} ha)` : square;
}

function grouped(text) {
  const [whole, decimals] = text.split(".");
  return `${whole.replace(/\B(?=(\d{3})+(?!\d))/g, " ")}${decimals ? `.${decimals}` : ""}`;
}

// -- Measuring ------------------------------------------------------------------------------------------------

/**
 * The "Measure" block of a map's side panel: distance, area and, with `dsm` ({ jobId }), volume above a base.
 * `projection` (crs.js) names the raster's CRS for the grid figures. Answers { node, pick(latlng) -> bool,
 * active() }: `pick` adds a vertex at a point a layer was clicked at (a GCP, a camera centre) while measuring.
 */
export function measureTool(view, map, { projection, dsm } = {}) {
  const pane = map.getPane("measure") || map.createPane("measure");
  pane.style.zIndex = 640; // above the markers, below popups
  const drawn = L.layerGroup().addTo(map);
  const result = h("p", { class: "readout measure-result", "data-testid": "measure-result", role: "status", "aria-live": "polite" },
    "Choose a tool, then click on the map: each click is a point; double-click or Finish ends.");
  const buttons = {};
  const tool = (kind, text) => {
    buttons[kind] = h("button", { type: "button", class: "btn small", "data-testid": `measure-${kind}`, "aria-pressed": "false",
      onclick: () => start(kind) }, text);
    return buttons[kind];
  };
  const finish = h("button", { type: "button", class: "btn small primary", "data-testid": "measure-finish", disabled: true,
    onclick: () => end() }, "Finish");
  const clear = h("button", { type: "button", class: "btn small", "data-testid": "measure-clear", onclick: () => reset() }, "Clear");
  const base = dsm ? baseChoice() : null;
  let mode = null;
  let points = [];
  let pointer = null; // where the cursor is, while drawing: the next point, shown dashed

  function start(kind) {
    reset();
    mode = kind;
    buttons[kind].setAttribute("aria-pressed", "true");
    finish.disabled = false;
    map.doubleClickZoom.disable();
    map.getContainer().classList.add("measuring");
    result.textContent = kind === "distance" ? "Click the points of the line; double-click or Finish ends it."
      : "Click the corners of the area; double-click or Finish closes it.";
  }

  function reset() {
    mode = null;
    points = [];
    pointer = null;
    drawn.clearLayers();
    for (const b of Object.values(buttons)) b.setAttribute("aria-pressed", "false");
    finish.disabled = true;
    map.doubleClickZoom.enable();
    map.getContainer().classList.remove("measuring");
    result.textContent = "Choose a tool, then click on the map.";
  }

  function add(latlng) {
    points.push(L.latLng(latlng.lat, latlng.lng));
    redraw();
  }

  function redraw() {
    drawn.clearLayers();
    const shown = pointer ? [...points, pointer] : points;
    if (shown.length >= 2) {
      (mode === "distance" ? L.polyline(shown, { ...LINE, pane: "measure" }) : L.polygon(shown, { ...AREA, pane: "measure" })).addTo(drawn);
    }
    for (const p of points) L.circleMarker(p, { ...VERTEX, pane: "measure" }).addTo(drawn);
    if (mode) result.textContent = describe(shown);
  }

  function describe(shown) {
    const crs = projection ? projection.code : "";
    if (mode === "distance") {
      const grid = gridLength(shown, projection);
      return `Distance ${formatLength(geodesicLength(shown))} on the ground (geodesic, WGS 84)`
        + (grid !== null ? ` · ${formatLength(grid)} on the grid of ${crs}` : "")
        + ` · ${shown.length} points`;
    }
    if (shown.length < 3) return "Click at least three corners.";
    const { area, perimeter } = geodesicArea(shown);
    const grid = gridArea(shown, projection);
    return `Area ${formatArea(area)} on the ground (geodesic, WGS 84)`
      + (grid !== null ? ` · ${formatArea(grid)} on the grid of ${crs}` : "")
      + ` · perimeter ${formatLength(perimeter)}`;
  }

  async function end() {
    const kind = mode;
    if (!kind) return;
    pointer = null;
    redraw(); // the finished shape and its figures, while `mode` still says what it is
    const text = result.textContent;
    const done = points.slice();
    mode = null;
    map.doubleClickZoom.enable();
    map.getContainer().classList.remove("measuring");
    finish.disabled = true;
    for (const b of Object.values(buttons)) b.setAttribute("aria-pressed", "false");
    if (kind === "volume" && done.length >= 3) await volume(done, text);
  }

  async function volume(done, areaText) {
    result.textContent = `${areaText} · computing the volume…`;
    try {
      const answer = await api("POST", `/tiles/${dsm.jobId}/dsm/volume`,
        { body: { polygon: done.map((p) => [p.lng, p.lat]), base: base.value() }, signal: view.signal });
      if (!view.signal.aborted) result.textContent = `${areaText} · ${volumeText(answer)}`;
    } catch (err) {
      if (!view.signal.aborted) result.textContent = `${areaText} · no volume: ${messageOf(err)}`;
    }
  }

  map.on("click", (event) => {
    if (mode) add(event.latlng);
  });
  map.on("dblclick", () => {
    if (!mode) return;
    points.pop(); // the double-click's second click added the last point twice
    end();
  });
  map.on("mousemove", (event) => {
    if (!mode || !points.length) return;
    pointer = event.latlng;
    redraw();
  });
  const onKey = (event) => {
    if (event.key === "Escape" && mode) reset();
  };
  document.addEventListener("keydown", onKey);
  onAbort(view.signal, () => document.removeEventListener("keydown", onKey));

  const node = h("div", { class: "control", "data-testid": "measure-tool" },
    h("h3", {}, "Measure"),
    h("div", { class: "row wrap" }, tool("distance", "Distance"), tool("area", "Area"), dsm ? tool("volume", "Volume") : null,
      finish, clear),
    base ? base.node : null,
    result,
    projection && !projection.project ? h("p", { class: "muted small" }, `Grid figures need a UTM CRS; this raster is in ${projection.code}.`) : null);
  return {
    node,
    active: () => mode !== null,
    pick: (latlng) => {
      if (!mode) return false;
      add(latlng);
      return true;
    },
  };
}

/** The base a volume is measured from: a plane along the polygon's edge, its lowest point, or an elevation. */
function baseChoice() {
  const select = h("select", { id: "volume-base", "data-testid": "volume-base" },
    h("option", { value: "fit" }, "a plane along the edge"),
    h("option", { value: "lowest" }, "the lowest point of the edge"),
    h("option", { value: "elevation" }, "an elevation"));
  const elevation = h("input", { type: "number", step: "0.01", id: "volume-elevation", class: "narrow-input", hidden: true,
    "aria-label": "Base elevation, m", "data-testid": "volume-elevation", value: "0" });
  select.addEventListener("change", () => {
    elevation.hidden = select.value !== "elevation";
  });
  return {
    node: h("div", { class: "control-row" }, h("label", { for: "volume-base" }, "Volume above"), select, elevation),
    value: () => (select.value === "elevation" ? Number(elevation.value) || 0 : select.value),
  };
}

function volumeText(v) {
  const base = v.base || {};
  const from = base.kind === "fit" ? `a plane along the edge (${formatNumber(base.elevation_m, 2, "m")} at its centre, slope ${formatNumber(base.slope_percent, 2)} %)`
    : base.kind === "lowest" ? `the edge's lowest point, ${formatNumber(base.elevation_m, 2, "m")}` : `${formatNumber(base.elevation_m, 2, "m")}`;
  const cover = typeof v.with_value_share === "number" && v.with_value_share < 1 ? `; ${(100 * (1 - v.with_value_share)).toFixed(1)} % of it has no value` : "";
  return `volume above ${from}: ${grouped(formatNumber(v.volume_above_m3, 1))} m³, below: ${grouped(formatNumber(v.volume_below_m3, 1))} m³`
    + ` (${formatNumber(100 * v.measured_share, 1)} % of the cells measured, not filled${cover}; ${v.crs || "grid"} cells of ${formatNumber(v.cell_m, 2, "m")})`;
}

// -- Cursor coordinates ---------------------------------------------------------------------------------------

/** A map control (bottom left) with the cursor's latitude and longitude and, with a projection that has one, its
 * position in the raster's CRS. */
export function coordinatesControl(map, projection) {
  const text = h("span", {}, "Move over the map");
  const Control = L.Control.extend({
    onAdd: () => {
      const node = h("div", { class: "leaflet-control coords", "data-testid": "cursor-coords" }, text);
      L.DomEvent.disableClickPropagation(node);
      return node;
    },
  });
  new Control({ position: "bottomleft" }).addTo(map);
  map.on("mousemove", (event) => {
    const { lat, lng } = event.latlng;
    const geographic = `${lat.toFixed(7)}°, ${lng.toFixed(7)}° (lat, lon)`;
    text.textContent = projection && projection.project
      ? `${geographic} · ${formatEastNorth(projection.project([lng, lat]))} (${projection.code})` : geographic;
  });
}
