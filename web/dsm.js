/* A job's elevation on its map: the legend of a DSM's (or disparity map's) colour ramp and the value under the
 * cursor, read from /tiles/<id>/{dsm,disparity}/point. Shared by a stereo DEM's page (stereo-dem.js) and an
 * ortho mosaic's, whose DSM is the surface its photos were projected onto (result-map.js). */

import { api, formatNumber, h, onAbort } from "./lib.js";

const POINT_DELAY_MS = 120; // ask for the value under the cursor once it has rested this long
const HEX_COLOUR = /^#[0-9a-f]{6}$/i; // a legend colour from the report, before it goes into a style

/** The value under the cursor, asked for once the cursor rests; one request at a time, the older aborted. */
export function followPointer(view, map, jobId, dsm, readout) {
  let timer = null;
  let pending = null;
  const ask = async (latlng) => {
    if (pending) pending.abort();
    pending = new AbortController();
    const query = dsm ? `lon=${latlng.lng.toFixed(8)}&lat=${latlng.lat.toFixed(8)}`
      : `x=${latlng.lng.toFixed(3)}&y=${(-latlng.lat).toFixed(3)}`; // CRS.Simple: one unit per pixel, y negated
    try {
      const point = await api("GET", `/tiles/${jobId}/${dsm ? "dsm" : "disparity"}/point?${query}`, { signal: pending.signal });
      if (!view.signal.aborted) readout.textContent = pointText(point, dsm);
    } catch (err) {
      if (err && err.name === "AbortError") return; // a newer position took over
      if (!view.signal.aborted) readout.textContent = "The value could not be read here.";
    }
  };
  map.on("mousemove", (event) => {
    clearTimeout(timer);
    timer = setTimeout(() => ask(event.latlng), POINT_DELAY_MS);
  });
  map.on("mouseout", () => clearTimeout(timer));
  onAbort(view.signal, () => {
    clearTimeout(timer);
    if (pending) pending.abort();
  });
}

function pointText(point, dsm) {
  if (dsm) {
    const where = `${formatNumber(point.lat, 6)}, ${formatNumber(point.lon, 6)}`;
    if (typeof point.elevation_m !== "number") return `No elevation at ${where}.`;
    return `${formatNumber(point.elevation_m, 2, "m")} (${point.state || "–"}) at ${where}`;
  }
  const where = `x ${formatNumber(point.x, 1)}, y ${formatNumber(point.y, 1)}`;
  if (typeof point.disparity_px !== "number") return `No disparity at ${where}.`;
  const filled = point.confidence === 0 ? "filled" : `confidence ${formatNumber(point.confidence, 2)}`;
  return `${formatNumber(point.disparity_px, 2, "px")} (${filled}) at ${where}`;
}

/** A colour bar of the ramp's stops and the values at its ends and middle; `datum` says what heights are above. */
export function legendNode(legend, datum = "Heights above the WGS 84 ellipsoid") {
  const stops = (legend && Array.isArray(legend.stops) ? legend.stops : [])
    .filter((s) => s && typeof s.value === "number" && typeof s.colour === "string" && HEX_COLOUR.test(s.colour));
  if (stops.length < 2) return h("p", { class: "muted small" }, "No legend in the report.");
  const units = legend.units === "px" ? "px" : "m";
  const bar = h("div", { class: "ramp-bar", "data-testid": "legend-bar", role: "img",
    "aria-label": `Colour ramp from ${formatNumber(stops[0].value, 1, units)} to ${formatNumber(stops[stops.length - 1].value, 1, units)}` });
  const span = stops[stops.length - 1].value - stops[0].value || 1;
  bar.style.background = `linear-gradient(to right, ${stops.map((s) => `${s.colour} ${(100 * (s.value - stops[0].value)) / span}%`).join(", ")})`;
  const middle = stops[0].value + span / 2;
  return h("div", { class: "ramp", "data-testid": "legend" }, bar,
    h("div", { class: "ramp-labels muted small" },
      [stops[0].value, middle, stops[stops.length - 1].value].map((v) => h("span", {}, formatNumber(v, 1, units)))),
    units === "m" ? h("p", { class: "muted small" }, `${datum}; relief shaded from the north-west.`) : null);
}
