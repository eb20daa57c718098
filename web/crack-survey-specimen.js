/* The specimen of a new crack survey (#/crack-surveys/new): a plate (its width and height) or a mesh model
 * (OBJ, PLY or STL in mm) read in the browser, with the plane its surface is rectified onto (the mesh's
 * best-fit plane, or one through three model points), and the resolution of the rectified images.
 *
 * The photos' editors follow it (`subscribe`): a mesh asks for Z and six control points per photo, and its
 * plan view (mesh-plan.js) lets a point take a vertex's coordinates. A model that does not parse is said at
 * once and blocks the submit; nothing is uploaded before the submit.
 */

import { factList, formatNumber, h } from "./lib.js";
import { meshPlan } from "./mesh-plan.js";
import { MESH_SUFFIXES, MeshError, meshBounds, parseMesh } from "./mesh.js";

// Control points per photo, as the API asks (workers/config.py): a plane-to-photo mapping has 8 degrees of
// freedom; a pose from points on a curved surface 6 unknowns, and points off one plane to pin the depth.
const MIN_POINTS = { plate: 4, mesh: 6 };
const PLANE_POINTS = ["Origin", "Toward +x", "On the +y side"];

/** A problem with what was typed, found before sending: its message and the field to go to. */
export class FieldError extends Error {
  constructor(field, message) {
    super(message);
    this.field = field;
  }
}

/** A number typed into `input`, or a FieldError saying `what` is missing. */
function typedNumber(input, what) {
  const n = Number(input.value);
  if (input.value.trim() === "" || !Number.isFinite(n)) throw new FieldError(input, what);
  return n;
}

export function specimenFields() {
  const listeners = new Set();
  const changed = () => listeners.forEach((listener) => listener());
  const choice = (value, label, checked) => {
    const input = h("input", { type: "radio", name: "specimen-kind", value, checked, "data-testid": `specimen-${value}` });
    return { input, node: h("label", { class: "check" }, input, ` ${label}`) };
  };
  const plateChoice = choice("plate", "Plate", true);
  const meshChoice = choice("mesh", "Mesh model", false);
  const plate = plateFields();
  const model = modelFields(changed);
  const resolution = numberField("mm-per-px", "Output resolution, mm per pixel (optional)", { placeholder: "the photos' own" });
  const kind = () => (meshChoice.input.checked ? "mesh" : "plate");
  const sync = () => {
    plate.node.hidden = kind() !== "plate";
    model.node.hidden = kind() !== "mesh";
  };
  for (const { input } of [plateChoice, meshChoice]) {
    input.addEventListener("change", () => {
      sync();
      changed();
    });
  }
  sync();

  const node = h("fieldset", { class: "card", "data-testid": "specimen" },
    h("legend", {}, "Specimen"),
    h("div", { class: "row specimen-kind", role: "radiogroup", "aria-label": "Specimen model" }, plateChoice.node, meshChoice.node),
    plate.node, model.node, resolution.node,
    h("p", { class: "muted small" }, "Of the rectified images and overlays you download. Cracks are found at the photos' own sampling "
      + "whatever you choose; empty: the photos' own sampling."));
  return {
    node,
    kind,
    minPoints: () => MIN_POINTS[kind()],
    /** The mesh's plan (mesh-plan.js) while a parsed mesh is the specimen, else null. */
    plan: () => (kind() === "mesh" ? model.plan() : null),
    /** The model file to upload with the survey, or null for a plate. */
    modelFile: () => (kind() === "mesh" ? model.file() : null),
    read: () => ({
      specimen: kind() === "mesh" ? model.read() : plate.read(),
      ...(resolution.input.value.trim() === ""
        ? {}
        : { mm_per_px: typedNumber(resolution.input, "Specimen: the output resolution must be a number of mm per pixel.") }),
    }),
    /** Call `listener` whenever the specimen's kind or model changes; answers the function that stops it. */
    subscribe(listener) {
      listeners.add(listener);
      return () => listeners.delete(listener);
    },
  };
}

function numberField(id, label, attrs) {
  const input = h("input", Object.assign({ id, type: "number", step: "any", min: 0, "data-testid": id }, attrs));
  return { input, node: h("div", {}, h("label", { for: id }, label), input) };
}

function plateFields() {
  const width = numberField("specimen-width", "Width (X) mm", { placeholder: "e.g. 200" });
  const height = numberField("specimen-height", "Height (Y) mm", { placeholder: "e.g. 150" });
  const node = h("div", { "data-testid": "plate-fields" },
    h("p", { class: "muted small" }, "A plate: X to the right, Y down, from its top-left corner; Z = 0 on its face."),
    h("div", { class: "field-row" }, width.node, height.node));
  const read = () => ({
    width_mm: typedNumber(width.input, "Specimen: give its width in mm."),
    height_mm: typedNumber(height.input, "Specimen: give its height in mm."),
  });
  return { node, read };
}

/** The mesh model: its file, read and parsed here, what it holds, and the rectification plane. */
function modelFields(changed) {
  const input = h("input", { id: "specimen-model", type: "file", accept: MESH_SUFFIXES.join(","), class: "visually-hidden",
    "data-testid": "specimen-model" });
  const summary = h("div", { class: "mesh-summary", "data-testid": "mesh-summary", "aria-live": "polite" });
  const error = h("p", { class: "form-error", role: "alert", "data-testid": "mesh-error" });
  const plane = planeFields();
  const state = { file: null, mesh: null, plan: null, error: "", reading: false, token: 0 };

  input.addEventListener("change", async () => {
    const file = input.files[0];
    input.value = ""; // the same file can be read again after it was edited
    if (!file) return;
    const token = ++state.token;
    Object.assign(state, { file, mesh: null, plan: null, error: "", reading: true });
    show();
    try {
      const mesh = parseMesh(await file.arrayBuffer(), file.name);
      if (token === state.token) Object.assign(state, { mesh, plan: meshPlan(mesh) });
    } catch (err) {
      if (token !== state.token) return;
      state.error = err instanceof MeshError ? err.message : `${file.name}: the file could not be read (${err.message})`;
    } finally {
      if (token === state.token) {
        state.reading = false;
        show();
      }
    }
  });

  function show() {
    error.textContent = state.error ? `The model cannot be used: ${state.error}. Choose an OBJ, PLY or STL file in mm.` : "";
    summary.replaceChildren();
    if (state.reading) summary.append(h("p", { class: "muted small" }, `Reading ${state.file.name}…`));
    else if (state.mesh) summary.append(meshFacts(state.file.name, state.mesh, state.plan));
    changed();
  }
  function read() {
    if (state.reading) throw new FieldError(input, `Specimen: still reading ${state.file.name}; submit again in a moment.`);
    if (state.error) throw new FieldError(input, `Specimen: ${state.error}`);
    if (!state.mesh) throw new FieldError(input, "Specimen: choose the mesh model file (OBJ, PLY or STL, in mm).");
    return { mesh: state.file.name, plane: plane.read() };
  }
  const node = h("div", { class: "mesh-fields", "data-testid": "mesh-fields" },
    h("p", { class: "muted small" }, "A triangle mesh of the specimen's surface in mm. Control points take its model X, Y, Z; "
      + "cracks are measured along the surface."),
    h("div", { class: "row" }, h("label", { class: "btn small" }, input, "Choose the model…"),
      h("span", { class: "muted small" }, MESH_SUFFIXES.join(", "))),
    error, summary, plane.node);
  return { node, read, plan: () => state.plan, file: () => (state.mesh ? state.file : null) };
}

function meshFacts(name, mesh, plan) {
  const { min, max } = meshBounds(mesh.vertices);
  const range = (a) => `${formatNumber(min[a], 1)} to ${formatNumber(max[a], 1)} mm`;
  return factList([
    ["File", h("span", { class: "filename", "data-testid": "mesh-name" }, name)],
    ["Vertices", (mesh.vertices.length / 3).toLocaleString(), { "data-testid": "mesh-vertices" }],
    ["Triangles", (mesh.triangles.length / 3).toLocaleString(), { "data-testid": "mesh-triangles" }],
    ["X range", range(0), { "data-testid": "mesh-x" }],
    ["Y range", range(1), { "data-testid": "mesh-y" }],
    ["Z range", range(2), { "data-testid": "mesh-z" }],
    ["Plan view", `${plan.axes} (beside each photo)`],
  ], { class: "facts mesh-facts" });
}

/** The rectification plane: the mesh's best-fit plane (null), or three model points typed. */
function planeFields() {
  const bestFit = h("input", { type: "radio", name: "specimen-plane", value: "fit", checked: true, "data-testid": "plane-best-fit" });
  const through = h("input", { type: "radio", name: "specimen-plane", value: "points", "data-testid": "plane-points" });
  const inputs = PLANE_POINTS.map((label, r) => ["X", "Y", "Z"].map((axis) => h("input", {
    type: "number", step: "any", "aria-label": `Plane: ${label.toLowerCase()}, model ${axis} mm`,
    "data-testid": `plane-${r}-${axis.toLowerCase()}`,
  })));
  const table = h("table", { class: "table compact plane-points" },
    h("caption", { class: "visually-hidden" }, "Three model points of the rectification plane"),
    h("thead", {}, h("tr", {}, ["", "X mm", "Y mm", "Z mm"].map((t) => h("th", { scope: "col" }, t)))),
    h("tbody", {}, PLANE_POINTS.map((label, r) => h("tr", {}, h("th", { scope: "row" }, label), inputs[r].map((i) => h("td", {}, i))))));
  const sync = () => {
    table.hidden = !through.checked;
  };
  for (const radio of [bestFit, through]) radio.addEventListener("change", sync);
  sync();
  function read() {
    if (!through.checked) return null;
    return inputs.map((row, r) => row.map((input, a) => typedNumber(input,
      `Specimen: give the rectification plane's ${PLANE_POINTS[r].toLowerCase()} point, model ${"XYZ"[a]} in mm.`)));
  }
  const node = h("fieldset", { class: "plane-fields" },
    h("legend", {}, "Rectification plane ", h("span", { class: "muted" }, "(optional)")),
    h("label", { class: "check" }, bestFit, " The mesh's best-fit plane"),
    h("label", { class: "check" }, through, " Through three model points"),
    table,
    h("p", { class: "muted small" }, "The rectified images are the surface seen square to this plane: x along origin → toward +x, y toward the +y side."));
  return { node, read };
}
