/* A calibration's (or a stereo rig's) photos with their board corners drawn on them: each mark coloured by its
 * reprojection error, and, for a finished job, fixed by dragging it, removed, or the whole photo left out, then
 * solved again (PUT /api/calibrations/<id>/markers or /api/stereo-rigs/<id>/markers: the marks of that photo
 * replace its detected corners; a rig's pair uses the marks both its photos have).
 *
 * The photo is a reduced JPEG (GET /api/jobs/<id>/photos/<index>/preview, signed) laid on a Leaflet map in
 * CRS.Simple over the photo's own pixels, so marks stay in full-size pixel coordinates whatever the preview's
 * size; OpenCV puts integer coordinates at pixel centres, hence the half pixel between a mark and the map. */

import { api, formatNumber, h, messageOf, onAbort, signedUrl } from "./lib.js";

const PREVIEW_PX = 2048; // the preview's longer side at most

/** Where a pixel (x, y) (OpenCV: integers at pixel centres) lies on the map, and back. */
const toMap = ([x, y]) => L.latLng(-(y + 0.5), x + 0.5);
const toPixel = (latlng) => [latlng.lng - 0.5, -latlng.lat - 0.5];

/** The section "Photos and marks" of a calibration's or rig's result card. `result` is the job's result (views
 * with their points); `editable`: a finished job, whose marks can be changed. */
export async function calibrationPhotos(view, job, { stereo, result, signature, editable }) {
  const data = await api("GET", `/api/${stereo ? "stereo-rigs" : "calibrations"}/${job.id}/photos`, { signal: view.signal });
  const photos = Array.isArray(data && data.photos) ? data.photos : [];
  const views = new Map((result && Array.isArray(result.views) ? result.views : []).map((v) => [v.image, v]));
  const pick = h("select", { id: "marks-photo", "data-testid": "marks-photo" },
    photos.map((p) => h("option", { value: p.index }, photoLabel(p, views.get(p.name), stereo))));
  const mapNode = h("div", { class: "map marks-map", "data-testid": "marks-map", role: "region", "aria-label": "The photo and its marks" });
  const readout = h("p", { class: "readout", "data-testid": "marks-readout", role: "status", "aria-live": "polite" });
  const status = h("p", { class: "muted small", "data-testid": "marks-status" });
  const error = h("p", { class: "form-error", role: "alert", "data-testid": "marks-error" });
  const editor = editable ? markEditor(view, job, { stereo, status, error }) : null;
  const map = L.map(mapNode, { crs: L.CRS.Simple, minZoom: -6, maxZoom: 4, zoomSnap: 0.25, attributionControl: false });
  onAbort(view.signal, () => map.remove());
  let layers = L.layerGroup().addTo(map);

  function show(index) {
    const photo = photos.find((p) => p.index === index);
    if (!photo) return;
    layers.remove();
    layers = L.layerGroup().addTo(map);
    const bounds = L.latLngBounds([-photo.height, 0], [0, photo.width]);
    const size = Math.min(PREVIEW_PX, Math.max(photo.width, photo.height));
    L.imageOverlay(signedUrl(`/api/jobs/${job.id}/photos/${photo.index}/preview?size=${size}`, signature), bounds,
      { alt: `Photo ${photo.name}` }).addTo(layers);
    map.fitBounds(bounds);
    const used = views.get(photo.name);
    const points = used ? used.points.map((p) => ({ index: p.index, xy: p.image_xy, board: p.board_xyz, error: p.error_px }))
      : (photo.corners || []).map((xy, i) => ({ index: i, xy, board: null, error: null }));
    const markers = points.map((point) => markerOf(point, layers, readout, editor));
    readout.textContent = points.length
      ? `${points.length} marks${used ? `, RMS ${formatNumber(used.rms_px, 3, "px")} (${used.source === "markers" ? "your marks" : "corners found"})`
        : stereo ? " found, not used by the solve (its pair is left out)" : " found, not used by the solve"}. Click one to see where it is.`
      : `No marks: ${photo.reason || photo.marks || "left out"}.`;
    if (editor) editor.photo(photo, points, markers, Boolean(used));
  }

  pick.addEventListener("change", () => show(Number(pick.value)));
  const node = h("section", { class: "quality-block", "aria-labelledby": "marks-heading", "data-testid": "calibration-photos" },
    h("h3", { id: "marks-heading" }, "Photos and marks"),
    h("div", { class: "control-row" }, h("label", { for: "marks-photo" }, "Photo"), pick),
    h("div", { class: "marks-grid" }, mapNode,
      h("div", {}, readout, legend(), editor ? editor.node : h("p", { class: "muted small" }, "Marks can be changed once the job has finished."),
      status, error)));
  return { node, start: () => (photos.length ? show(photos[0].index) : null) };
}

function photoLabel(photo, used, stereo) {
  const side = stereo ? `${photo.side} ${photo.pair + 1}: ` : "";
  const how = used ? `${used.points.length} marks, ${formatNumber(used.rms_px, 2, "px")}`
    : photo.marks === "removed" ? "left out by you"
      : stereo && photo.corners ? `${photo.corners.length} corners found` : stereo ? "no board found" : "not used";
  return `${side}${photo.name} (${how})`;
}

function legend() {
  return h("p", { class: "muted small marks-legend" },
    h("span", { class: "mark-dot ok" }), " under 0.5 px ", h("span", { class: "mark-dot warn" }), " under 1.5 px ",
    h("span", { class: "mark-dot bad" }), " more ", h("span", { class: "mark-dot none" }), " not solved");
}

function grade(error) {
  if (typeof error !== "number") return "none";
  return error < 0.5 ? "ok" : error < 1.5 ? "warn" : "bad";
}

/** One mark: a small circle (a divIcon: draggable), its error in the readout when clicked. */
function markerOf(point, layers, readout, editor) {
  const icon = L.divIcon({ className: `mark-icon ${grade(point.error)}`, iconSize: [12, 12], iconAnchor: [6, 6] });
  const marker = L.marker(toMap(point.xy), { icon, keyboard: false, title: `Mark ${point.index}` }).addTo(layers);
  marker.on("click", () => {
    const [x, y] = toPixel(marker.getLatLng());
    readout.textContent = `Mark ${point.index} at x ${x.toFixed(2)}, y ${y.toFixed(2)}`
      + (typeof point.error === "number" ? `: reprojection error ${formatNumber(point.error, 3, "px")}` : "");
    if (editor) editor.select(point, marker);
  });
  return marker;
}

/** The editing controls of a finished calibration's (or rig's) marks. */
function markEditor(view, job, { stereo, status, error }) {
  const edit = h("input", { type: "checkbox", id: "marks-edit", "data-testid": "marks-edit" });
  const removeMark = h("button", { type: "button", class: "btn small", "data-testid": "mark-remove", disabled: true }, "Remove this mark");
  const save = h("button", { type: "button", class: "btn small primary", "data-testid": "marks-save", disabled: true }, "Save the marks and solve again");
  const leaveOut = h("button", { type: "button", class: "btn small danger", "data-testid": "photo-leave-out" }, "Leave this photo out");
  const restore = h("button", { type: "button", class: "btn small", "data-testid": "photo-restore", hidden: true }, "Use the corners found again");
  let current = null; // { photo, points, markers, removed: Set }
  let selected = null;

  function changed() {
    save.disabled = !current || !current.dirty;
    status.textContent = current && current.dirty ? "Changed: save to solve again with these marks." : "";
  }
  edit.addEventListener("change", () => {
    for (const m of current ? current.markers : []) (edit.checked ? m.dragging.enable() : m.dragging.disable());
  });
  removeMark.addEventListener("click", () => {
    if (!current || !selected) return;
    current.removed.add(selected.point.index);
    selected.marker.remove();
    selected = null;
    removeMark.disabled = true;
    current.dirty = true;
    changed();
  });
  save.addEventListener("click", () => {
    const kept = current.points.map((p, i) => ({ p, m: current.markers[i] })).filter(({ p }) => !current.removed.has(p.index));
    send([{ image: current.photo.name, image_points: kept.map(({ m }) => toPixel(m.getLatLng())), board_points: kept.map(({ p }) => p.board) }],
      `Solving again with ${kept.length} marks on ${current.photo.name}…`);
  });
  leaveOut.addEventListener("click", () => send([{ image: current.photo.name, remove: true }], `Solving again without ${current.photo.name}…`));
  restore.addEventListener("click", () => send([{ image: current.photo.name }], `Solving again with the corners found in ${current.photo.name}…`));

  async function send(markers, saying) {
    error.textContent = "";
    status.textContent = saying;
    for (const b of [save, leaveOut, restore, removeMark]) b.disabled = true;
    try {
      await api("PUT", `/api/${stereo ? "stereo-rigs" : "calibrations"}/${job.id}/markers`, { body: { markers } });
      if (!view.signal.aborted) window.dispatchEvent(new HashChangeEvent("hashchange")); // the page again: it follows the new solve
    } catch (err) {
      if (view.signal.aborted) return;
      error.textContent = `Not saved: ${messageOf(err)}`;
      status.textContent = "";
      leaveOut.disabled = false;
      restore.disabled = false;
      changed();
    }
  }

  return {
    node: h("div", { class: "marks-editor", "data-testid": "marks-editor" },
      h("label", { class: "check small", for: "marks-edit" }, edit, " Move marks (drag them)"),
      h("div", { class: "row wrap" }, removeMark, save),
      h("div", { class: "row wrap" }, leaveOut, restore),
      h("p", { class: "muted small" }, stereo
        ? "A photo's saved marks replace the corners found in it. A pair uses the marks both its photos have; against"
          + " the corners found in the other photo, a removed mark also leaves out the one opposite it on the board."
        : "A photo's saved marks replace the corners found in it; the other photos keep theirs.")),
    photo(photo, points, markers, used) {
      current = { photo, points, markers, removed: new Set(), dirty: false };
      selected = null;
      removeMark.disabled = true;
      const hasBoard = points.every((p) => Array.isArray(p.board));
      edit.disabled = !used || !hasBoard; // a photo left out has no board points to go with moved corners
      for (const m of markers) {
        if (edit.checked && !edit.disabled) m.dragging.enable();
        m.on("dragend", () => {
          current.dirty = true;
          changed();
        });
      }
      leaveOut.hidden = !used;
      leaveOut.disabled = false;
      restore.hidden = photo.marks === null;
      restore.disabled = false;
      changed();
    },
    select(point, marker) {
      selected = { point, marker };
      removeMark.disabled = !edit.checked || edit.disabled;
    },
  };
}
