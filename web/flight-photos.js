/* A flight's photos before processing: where they were taken on a map, a preview of each, and what the upload
 * check found (blurred, too dark or bright, no GPS, the same picture twice, another size) with why, so a bad
 * photo can be deleted before a job starts. Read from GET /api/flights/<id> (its photos carry `position`,
 * `issues` and a signed `preview_url`); DELETE /api/flights/<id>/images/<image> deletes one. */

import { api, apiUrl, formatBytes, h, messageOf, onAbort, plural } from "./lib.js";
import { label } from "./labels.js";
import { basemaps, layerSwitcher } from "./map-layers.js";

const SOUND = { radius: 6, color: "#ffffff", weight: 1.5, fillColor: "#1d4e89", fillOpacity: 1 };
const FLAGGED = { ...SOUND, fillColor: "#dc2626", radius: 7 };

/**
 * The Photos card's body: a map of the photos' positions (when any has one), the check's summary, and the table
 * of photos with their previews, findings and a Delete button. `onDeleted(imageId)` runs after a deletion.
 * Answers { node, show(images) }.
 */
export function photoPanel(view, flightId, { config, onDeleted }) {
  const summary = h("div", { class: "check-summary", "data-testid": "check-summary", role: "status" });
  const onlyFlagged = h("input", { type: "checkbox", id: "only-flagged", "data-testid": "only-flagged" });
  const table = h("div", {});
  const mapNode = h("div", { class: "map photo-map", "data-testid": "photo-map", role: "region", "aria-label": "Where the photos were taken", hidden: true });
  const error = h("p", { class: "form-error", role: "alert", "data-testid": "photo-delete-error" });
  let images = [];
  let map = null;
  let markers = null;
  const rows = new Map();

  function show(next) {
    images = next;
    summary.replaceChildren(...summaryNodes(images));
    drawTable();
    drawMap();
  }

  function drawTable() {
    rows.clear();
    const shown = onlyFlagged.checked ? images.filter((i) => (i.issues || []).length) : images;
    table.replaceChildren(photoTable(shown, images.length, rows, remove));
  }

  function drawMap() {
    const placed = images.filter((i) => i.position && Number.isFinite(i.position.lat) && Number.isFinite(i.position.lon));
    mapNode.hidden = !placed.length;
    if (!placed.length) return;
    if (!map) {
      map = L.map(mapNode, { maxZoom: 22 });
      onAbort(view.signal, () => map.remove());
      const { layers, initial } = basemaps(config, 22);
      layers[initial].addTo(map);
      markers = L.featureGroup().addTo(map);
      layerSwitcher(map, layers, { "Photo positions": markers }, { "Photo positions": "layer-photos", OpenStreetMap: "basemap-osm",
        "Basemap (set by the operator)": "basemap-ops", "No basemap": "basemap-none" });
      L.control.scale({ imperial: false }).addTo(map);
    }
    markers.clearLayers();
    for (const image of placed) {
      const issues = image.issues || [];
      const marker = L.circleMarker([image.position.lat, image.position.lon], issues.length ? FLAGGED : SOUND);
      // A node, not a string: Leaflet sets a string tooltip as HTML, and the file name is the user's.
      marker.bindTooltip(h("span", {}, h("strong", {}, image.filename),
        image.gps_source === "side_file" ? " (position from the GPS file)" : "",
        issues.map((i) => h("span", { class: "tooltip-issue" }, ` · ${label("photo_issue", i.code)}`))));
      marker.on("click", () => {
        const row = rows.get(image.id);
        if (row) {
          row.scrollIntoView({ block: "center" });
          row.classList.add("picked");
          setTimeout(() => row.classList.remove("picked"), 1500);
        }
      });
      marker.addTo(markers);
    }
    map.fitBounds(markers.getBounds(), { padding: [24, 24], maxZoom: 19 });
  }

  async function remove(image, button) {
    if (!window.confirm(`Delete the photo “${image.filename}” from this flight? This cannot be undone.`)) return;
    button.disabled = true;
    error.textContent = "";
    try {
      await api("DELETE", `/api/flights/${flightId}/images/${image.id}`); // not aborted by leaving: it was asked for
      if (!view.signal.aborted) onDeleted(image.id);
    } catch (err) {
      if (view.signal.aborted) return;
      button.disabled = false;
      error.textContent = `Could not delete ${image.filename}: ${messageOf(err)}`;
    }
  }

  onlyFlagged.addEventListener("change", drawTable);
  const node = h("div", {},
    mapNode,
    summary,
    h("label", { class: "check small", for: "only-flagged" }, onlyFlagged, " Only photos the check flags"),
    error,
    table);
  return { node, show };
}

function summaryNodes(images) {
  if (!images.length) return [];
  const flagged = images.filter((i) => (i.issues || []).length);
  const counts = {};
  for (const image of flagged) for (const issue of image.issues) counts[issue.code] = (counts[issue.code] || 0) + 1;
  const withGps = images.filter((i) => i.gps_source).length;
  if (!flagged.length) {
    return [h("p", { class: "alert success small" }, `The check found nothing wrong with the ${plural(images.length, "photo")}`
      + ` (${withGps} with a position).`)];
  }
  return [h("p", { class: "alert warning small" }, `The check flags ${plural(flagged.length, "photo")} of ${images.length}: `,
    Object.entries(counts).map(([code, n], k) => `${k ? ", " : ""}${label("photo_issue", code).toLowerCase()} ${n}`).join(""),
    ". Look at them, and delete those that would spoil the mosaic before you start.")];
}

function photoTable(images, total, rows, remove) {
  if (!total) return h("p", { class: "empty" }, "No photos yet.");
  if (!images.length) return h("p", { class: "empty small" }, "No photo is flagged.");
  return h("div", { class: "table-scroll" },
    h("table", { class: "table compact photo-table", "data-testid": "image-list" },
      h("caption", { class: "visually-hidden" }, "Uploaded photos"),
      h("thead", {}, h("tr", {},
        ["", "#", "File", "Size", "Pixels", "Position", "Check"].map((text, k) => h("th", { scope: "col", class: [1, 3, 4].includes(k) ? "num" : null }, text)))),
      h("tbody", {}, images.map((image) => {
        const row = photoRow(image, remove);
        rows.set(image.id, row);
        return row;
      }))));
}

function photoRow(image, remove) {
  const issues = image.issues || [];
  // an <img> sends no token: only a signed preview URL (a resumable upload's answer has none until the reload)
  const preview = typeof image.preview_url === "string" && image.preview_url.includes("sig=") ? apiUrl(image.preview_url) : null;
  const removeButton = h("button", { type: "button", class: "btn danger small", "data-testid": "delete-photo",
    "aria-label": `Delete ${image.filename}` }, "Delete");
  removeButton.addEventListener("click", () => remove(image, removeButton));
  return h("tr", { "data-testid": "image-row", "data-image": image.id, class: issues.length ? "flagged" : null },
    h("td", { class: "thumb" }, preview ? h("img", { src: preview, alt: "", loading: "lazy", width: 64, height: 48, "data-testid": "photo-thumb" }) : null,
      removeButton),
    h("td", { class: "num muted" }, String(image.seq)),
    h("td", { class: "filename", title: image.filename }, image.filename),
    h("td", { class: "num nowrap" }, formatBytes(image.size_bytes)),
    h("td", { class: "num nowrap" }, `${image.width} × ${image.height}`),
    h("td", { class: "nowrap" }, positionCell(image)),
    h("td", { class: "check-cell", "data-testid": "photo-check" }, issues.length
      ? h("ul", { class: "plain issues" }, issues.map((issue) => h("li", { "data-issue": issue.code },
        h("span", { class: "tag no" }, label("photo_issue", issue.code)), " ", h("span", { class: "small" }, issue.message))))
      : h("span", { class: "tag yes" }, image.quality ? "OK" : "–")));
}

function positionCell(image) {
  const p = image.position;
  if (!p) return h("span", { class: "tag no" }, "no GPS");
  const alt = typeof p.alt === "number" ? ` · ${p.alt.toFixed(0)} m` : "";
  return [h("span", { class: "tag yes" }, image.gps_source === "side_file" ? "GPS file" : "GPS"), " ",
    h("span", { class: "muted small" }, `${p.lat.toFixed(5)}, ${p.lon.toFixed(5)}${alt}`)];
}
