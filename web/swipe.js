/* Side by side: another job of the same flight (planar against ortho, feathered against multiband) on the right
 * of a divider the user drags, this job's mosaic on its left. Both layers are in panes of their own ("mosaic",
 * "compare"), clipped at the divider in the map's layer coordinates as leaflet-side-by-side clips its layers
 * (that plugin does not install from the registry: its build dependencies are gone), again on every pan and
 * zoom. */

import { api, h, onAbort } from "./lib.js";
import { JobKind, JobStatus } from "./kinds.js";
import { label } from "./labels.js";

const THUMB_PX = 28; // the divider's thumb width (style.css .swipe-range)

/**
 * The "Compare" block: a choice of the flight's other finished mosaics, and the divider on the map once one is
 * chosen. `job` is this job; `mosaicPane` holds its tiles.
 */
export function swipeControl(view, map, job) {
  const select = h("select", { id: "compare-with", "data-testid": "compare-with", disabled: true },
    h("option", { value: "" }, "Nothing (this job only)"));
  const status = h("p", { class: "muted small", "data-testid": "compare-status" }, "Looking for other mosaics of this flight…");
  const divider = h("input", { type: "range", min: 0, max: 100, step: 0.5, value: 50, class: "swipe-range",
    "aria-label": "Divider between the two mosaics (percent of the map's width)", "data-testid": "swipe-range" });
  const line = h("div", { class: "swipe-line", "aria-hidden": "true" });
  const leftTag = h("span", { class: "swipe-tag left" }, `Job #${job.id}`);
  const rightTag = h("span", { class: "swipe-tag right" });
  const overlay = h("div", { class: "swipe", "data-testid": "swipe", hidden: true }, line, leftTag, rightTag, divider);
  L.DomEvent.disableClickPropagation(overlay);
  L.DomEvent.disableScrollPropagation(overlay);
  map.getContainer().append(overlay);
  let compared = null;

  function clip() {
    const left = map.getPane("mosaic");
    const right = map.getPane("compare");
    if (!compared) {
      left.style.clip = "";
      right.style.clip = "";
      return;
    }
    const size = map.getSize();
    const nw = map.containerPointToLayerPoint([0, 0]);
    const se = map.containerPointToLayerPoint(size);
    // where the range's thumb is centred: half a thumb in from either end at 0 and 100 %
    const at = THUMB_PX / 2 + ((size.x - THUMB_PX) * Number(divider.value)) / 100;
    left.style.clip = `rect(${nw.y}px, ${nw.x + at}px, ${se.y}px, ${nw.x}px)`;
    right.style.clip = `rect(${nw.y}px, ${se.x}px, ${se.y}px, ${nw.x + at}px)`;
    line.style.left = `${at}px`;
    leftTag.style.right = `${size.x - at + 8}px`; // each job's name on its side of the divider
    rightTag.style.left = `${at + 8}px`;
  }

  async function compareWith(jobId) {
    if (compared) compared.remove();
    compared = null;
    overlay.hidden = true;
    if (!jobId) {
      clip();
      status.textContent = "Choose a mosaic to compare this one with.";
      return;
    }
    status.textContent = `Loading job #${jobId}…`;
    try {
      const tilejson = await api("GET", `/tiles/${jobId}/tilejson.json`, { signal: view.signal });
      if (view.signal.aborted || select.value !== String(jobId)) return;
      const [west, south, east, north] = tilejson.bounds;
      compared = L.tileLayer(tilejson.tiles[0], {
        pane: "compare", bounds: L.latLngBounds([south, west], [north, east]).pad(-1e-6), noWrap: true,
        minNativeZoom: tilejson.minzoom, maxNativeZoom: tilejson.maxzoom, maxZoom: map.getMaxZoom(),
        attribution: `Compared: job ${Number(jobId)}`,
      }).addTo(map);
      rightTag.textContent = `Job #${jobId}`;
      overlay.hidden = false;
      clip();
      status.textContent = `Left of the divider: job #${job.id}; right: job #${jobId}. Drag the divider.`;
    } catch (err) {
      if (!view.signal.aborted) status.textContent = `Job #${jobId} could not be shown: ${err.message}`;
    }
  }

  divider.addEventListener("input", clip);
  map.on("move zoom resize zoomend moveend", clip);
  select.addEventListener("change", () => compareWith(select.value ? Number(select.value) : null));
  onAbort(view.signal, () => overlay.remove());

  if (job.flight_id !== null && job.flight_id !== undefined) {
    api("GET", `/api/jobs?flight_id=${job.flight_id}`, { signal: view.signal })
      .then((jobs) => {
        if (view.signal.aborted) return;
        const others = (jobs || []).filter((j) => j.id !== job.id && j.kind === JobKind.MOSAIC && j.status === JobStatus.SUCCEEDED)
          .sort((a, b) => b.id - a.id);
        select.append(...others.map((j) => h("option", { value: j.id }, `Job #${j.id}${modeOf(j)}`)));
        select.disabled = !others.length;
        status.textContent = others.length ? "Choose a mosaic to compare this one with."
          : "No other finished mosaic of this flight to compare with.";
      })
      .catch(() => {
        if (!view.signal.aborted) status.textContent = "The flight's other jobs could not be listed.";
      });
  }
  return h("div", { class: "control", "data-testid": "compare-block" },
    h("h3", {}, "Compare"),
    h("div", { class: "control-row" }, h("label", { for: "compare-with" }, "Side by side with"), select),
    status);
}

function modeOf(job) {
  const mode = job.options && typeof job.options.mode === "string" ? job.options.mode : "planar";
  return ` (${label("mode", mode)})`;
}
