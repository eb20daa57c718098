/* The coordinate system a job's raster is in ("EPSG:32615"), for the cursor's coordinates and the grid figures
 * of a measurement: a UTM zone on WGS 84 (what mosaics and DSMs are written in) through proj4js (the global
 * `proj4`, vendored at set-up). Another code is named, and only longitude and latitude are shown. */

const UTM = /^EPSG:(32[67])(\d{2})$/; // 326zz north, 327zz south, zones 01-60

/** `{ code, name, project([lon, lat]) -> [x, y] }` for a UTM code; `{ code, name, project: null }` for another
 * code; null without one. */
export function projectionOf(code) {
  if (typeof code !== "string" || !code) return null;
  const match = UTM.exec(code.trim().toUpperCase());
  if (!match) return { code, name: code, project: null };
  const zone = Number(match[2]);
  if (zone < 1 || zone > 60) return { code, name: code, project: null };
  const south = match[1] === "327";
  const definition = `+proj=utm +zone=${zone}${south ? " +south" : ""} +datum=WGS84 +units=m +no_defs`;
  const converter = typeof proj4 === "function" ? proj4("EPSG:4326", definition) : null;
  return {
    code,
    name: `WGS 84 / UTM zone ${zone}${south ? "S" : "N"}`,
    project: converter ? (lonlat) => converter.forward(lonlat) : null,
  };
}

/** "271 034.52 E, 3 294 012.07 N": a UTM position, metres to the centimetre, thousands spaced. */
export function formatEastNorth([east, north]) {
  return `${spaced(east)} E, ${spaced(north)} N`;
}

function spaced(value) {
  const [whole, decimals] = value.toFixed(2).split(".");
  return `${whole.replace(/\B(?=(\d{3})+(?!\d))/g, " ")}.${decimals}`;
}
