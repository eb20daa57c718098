/* The plan view of a specimen mesh in the new-survey form: its edges and vertices projected onto the plane
 * of its two largest extents (X-Y for a panel), the first axis to the right and the second down, as a
 * plate's model frame is drawn. A click picks the nearest vertex (in the view) for the selected control
 * point; the points already placed are drawn with their numbers, as on the photo.
 *
 * One `meshPlan` per mesh (the projection and the drawn mesh, shared); one `planView` canvas per photo.
 */

import { h } from "./lib.js";
import { meshBounds } from "./mesh.js";

const WIDTH = 440; // CSS px: about the point panel's width
const MAX_HEIGHT = 340;
const MIN_HEIGHT = 120;
const MARGIN = [18, 22]; // CSS px beside and above/below the mesh: room for the points' labels and the axes
const MAX_EDGES_DRAWN = 400_000; // triangles; beyond, the vertices alone (drawing a million edges takes seconds)
const MAX_DOTS_DRAWN = 20_000; // vertices drawn as dots; beyond, the edges say enough
const AXIS_NAMES = ["X", "Y", "Z"];
const POINT_COLOUR = "#e11d48"; // as the photo's markers
const SELECTED_COLOUR = "#1d4e89"; // --primary

/** The projection of `mesh` ({ vertices, triangles }) and its drawing, for every photo's plan view. */
export function meshPlan(mesh) {
  const { min, max } = meshBounds(mesh.vertices);
  const extent = min.map((lo, a) => max[a] - lo);
  const [u, v] = [0, 1, 2].sort((a, b) => extent[b] - extent[a]).slice(0, 2).sort();
  const scale = Math.min((WIDTH - 2 * MARGIN[0]) / (extent[u] || 1), (MAX_HEIGHT - 2 * MARGIN[1]) / (extent[v] || 1));
  const height = Math.max(MIN_HEIGHT, Math.round(extent[v] * scale + 2 * MARGIN[1]));
  const offset = [(WIDTH - extent[u] * scale) / 2, (height - extent[v] * scale) / 2];
  const toView = (p) => [offset[0] + (p[u] - min[u]) * scale, offset[1] + (p[v] - min[v]) * scale];
  const count = mesh.vertices.length / 3;
  const xy = new Float32Array(2 * count); // every vertex in view CSS px
  for (let k = 0; k < count; k += 1) {
    [xy[2 * k], xy[2 * k + 1]] = toView(mesh.vertices.subarray(3 * k, 3 * k + 3));
  }
  let drawn = null;
  return {
    width: WIDTH,
    height,
    axes: `${AXIS_NAMES[u]}-${AXIS_NAMES[v]}`,
    toView,
    vertex: (k) => Array.from(mesh.vertices.subarray(3 * k, 3 * k + 3)),
    /** The vertex nearest to view point (x, y) CSS px. */
    nearest(x, y) {
      let best = 0;
      let bestD = Infinity;
      for (let k = 0; k < count; k += 1) {
        const d = (xy[2 * k] - x) ** 2 + (xy[2 * k + 1] - y) ** 2;
        if (d < bestD) [best, bestD] = [k, d];
      }
      return best;
    },
    /** The mesh drawn once at `ratio` device pixels per CSS px, for every view to copy. */
    image(ratio) {
      if (!drawn || drawn.ratio !== ratio) drawn = { ratio, canvas: drawMesh(mesh.triangles, xy, WIDTH, height, ratio, [u, v]) };
      return drawn.canvas;
    },
  };
}

function drawMesh(triangles, xy, width, height, ratio, [u, v]) {
  const canvas = h("canvas", { width: Math.round(width * ratio), height: Math.round(height * ratio) });
  const ctx = canvas.getContext("2d");
  ctx.scale(ratio, ratio);
  ctx.fillStyle = "#ffffff";
  ctx.fillRect(0, 0, width, height);
  if (triangles.length / 3 <= MAX_EDGES_DRAWN) {
    ctx.beginPath();
    for (let t = 0; t < triangles.length; t += 3) {
      const [a, b, c] = [triangles[t], triangles[t + 1], triangles[t + 2]];
      ctx.moveTo(xy[2 * a], xy[2 * a + 1]);
      ctx.lineTo(xy[2 * b], xy[2 * b + 1]);
      ctx.lineTo(xy[2 * c], xy[2 * c + 1]);
      ctx.closePath();
    }
    ctx.strokeStyle = "#c3ccd6";
    ctx.lineWidth = 0.6;
    ctx.stroke();
  }
  if (xy.length / 2 <= MAX_DOTS_DRAWN || triangles.length / 3 > MAX_EDGES_DRAWN) {
    ctx.fillStyle = "#6b7a8c";
    for (let k = 0; k < xy.length; k += 2) ctx.fillRect(xy[k] - 0.8, xy[k + 1] - 0.8, 1.6, 1.6);
  }
  ctx.fillStyle = "#5b6b7c";
  ctx.font = "600 11px system-ui, sans-serif";
  ctx.fillText(`${AXIS_NAMES[u]} →   ${AXIS_NAMES[v]} ↓`, 4, height - 5);
  return canvas;
}

/**
 * A canvas showing `plan` with the control points `points()` answers ([{ label, model: [X, Y, Z], selected }],
 * non-numbers for what is not typed yet), under it the hovered vertex and a status line (`say(text)`); a click
 * calls `onPick(vertex index)`. `redraw()` after a change.
 */
export function planView(plan, { name, points, onPick }) {
  const ratio = window.devicePixelRatio || 1;
  const canvas = h("canvas", {
    class: "plan-canvas", width: Math.round(plan.width * ratio), height: Math.round(plan.height * ratio),
    style: `aspect-ratio: ${plan.width} / ${plan.height}`, "data-testid": "mesh-plan",
    role: "img", "aria-label": `Plan view (${plan.axes}) of ${name}: click to fill the selected control point from the nearest vertex`,
  });
  const readout = h("span", { class: "mono", "aria-hidden": "true" });
  const status = h("span", { role: "status", "data-testid": "plan-status" });
  const ctx = canvas.getContext("2d");
  let hover = null;
  let frame = 0;

  const at = (event) => {
    const rect = canvas.getBoundingClientRect();
    return plan.nearest(((event.clientX - rect.left) * plan.width) / rect.width, ((event.clientY - rect.top) * plan.height) / rect.height);
  };
  canvas.addEventListener("pointermove", (event) => {
    const k = at(event);
    if (k === hover) return;
    hover = k;
    readout.textContent = `vertex ${k}: ${plan.vertex(k).map(formatMm).join(", ")} mm`;
    if (!frame) frame = requestAnimationFrame(() => { frame = 0; redraw(); });
  });
  canvas.addEventListener("pointerleave", () => {
    hover = null;
    readout.textContent = "";
    redraw();
  });
  canvas.addEventListener("click", (event) => onPick(at(event)));

  function redraw() {
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    ctx.drawImage(plan.image(ratio), 0, 0, plan.width, plan.height);
    for (const point of points()) {
      const [x, y] = plan.toView(point.model);
      if (Number.isFinite(x) && Number.isFinite(y)) pointMark(ctx, plan.width, [x, y], point.label, point.selected);
    }
    if (hover !== null) {
      const [x, y] = plan.toView(plan.vertex(hover));
      ring(ctx, x, y, 5, SELECTED_COLOUR, [2, 2]);
    }
  }
  redraw();
  const node = h("figure", { class: "mesh-plan" }, canvas, h("figcaption", { class: "small" }, status, " ", readout));
  return { node, redraw, say: (text) => { status.textContent = text; } };
}

/** A model coordinate as typed into the table: at most 4 decimals (0.1 µm), no trailing zeros. */
export function formatMm(value) {
  return String(Number(value.toFixed(4)));
}

function ring(ctx, x, y, r, colour, dash = []) {
  ctx.beginPath();
  ctx.arc(x, y, r, 0, 2 * Math.PI);
  ctx.setLineDash(dash);
  ctx.lineWidth = 1.5;
  ctx.strokeStyle = colour;
  ctx.stroke();
  ctx.setLineDash([]);
}

/** Control point `label` at view (x, y), its number above right of it (flipped where that leaves the view). */
function pointMark(ctx, width, [x, y], label, selected) {
  const colour = selected ? SELECTED_COLOUR : POINT_COLOUR;
  ring(ctx, x, y, 6, "#ffffff");
  ring(ctx, x, y, selected ? 7.5 : 6.5, colour);
  ctx.fillStyle = colour;
  ctx.fillRect(x - 1, y - 1, 2, 2);
  ctx.font = "600 11px system-ui, sans-serif";
  const w = ctx.measureText(label).width + 6;
  const left = x + 6 + w > width ? x - 6 - w : x + 6;
  const top = y - 20 < 0 ? y + 6 : y - 20;
  ctx.fillRect(left, top, w, 14);
  ctx.fillStyle = "#ffffff";
  ctx.fillText(label, left + 3, top + 11);
}
