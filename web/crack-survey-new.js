/* New crack survey (#/crack-surveys/new): the camera, the specimen and the load steps with their photos.
 *
 * On each photo a click adds a control point; a point is dragged (or moved with the arrow keys) to place
 * it, and its position on the specimen is typed beside it: model X, Y in mm on a plate (Z = 0), X, Y, Z on a
 * mesh model, where the point selected in the table can also take the coordinates of the vertex clicked in
 * the mesh's plan view. Pixels follow the API: (0, 0) is the centre of the photo's first pixel. Everything
 * (photos, and the mesh as `model`) is sent as one multipart request to POST /api/crack-surveys; a refusal
 * (422) is shown next to the button and nothing entered is lost.
 */

import { FieldError, specimenFields } from "./crack-survey-specimen.js";
import { formatMm, planView } from "./mesh-plan.js";
import { JobKind, JobStatus } from "./kinds.js";
import { api, apiForm, breadcrumb, formatDate, h, messageOf, onAbort, plural } from "./lib.js";

let lastId = 0;
const uid = (prefix) => `${prefix}-${++lastId}`;

export function renderNewCrackSurvey(view, root) {
  document.title = "New crack survey · Fotoskhema";
  const camera = cameraFields(view);
  const specimen = specimenFields();
  const steps = stepList(view, specimen);
  const error = h("p", { class: "form-error", role: "alert", "data-testid": "survey-error" });
  const status = h("p", { class: "muted small", role: "status", "aria-live": "polite" });
  const submit = h("button", { type: "submit", class: "btn primary", "data-testid": "submit-survey" }, "Start the survey");
  const form = h("form", { class: "form survey-form", novalidate: true, "aria-label": "New crack survey" },
    h("div", { class: "survey-top" }, camera.node, specimen.node),
    steps.node,
    h("section", { class: "card submit-card" }, error, h("div", { class: "row" }, submit, status)));

  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    error.textContent = "";
    let options;
    try {
      options = { ...camera.read(), ...specimen.read(), stages: steps.read() }; // the API's name of the load steps
    } catch (err) {
      if (!(err instanceof FieldError)) throw err;
      error.textContent = err.message;
      err.field.focus();
      return;
    }
    const body = new FormData();
    for (const file of steps.files()) body.append("files", file, file.name);
    const model = specimen.modelFile();
    if (model) body.append("model", model, model.name);
    body.append("options", JSON.stringify(options));
    submit.disabled = true;
    status.textContent = model ? "Uploading the photos and the model…" : "Uploading the photos…";
    try {
      const job = await apiForm("POST", "/api/crack-surveys", body);
      if (!view.signal.aborted) window.location.hash = `#/crack-surveys/${job.id}`;
    } catch (err) {
      if (view.signal.aborted) return;
      error.textContent = `Not started: ${messageOf(err)}`;
      status.textContent = "";
    } finally {
      submit.disabled = false;
    }
  });

  root.append(
    breadcrumb(["Crack surveys", "#/crack-surveys"], ["New survey"]),
    h("div", { class: "page-head" }, h("h1", {}, "New crack survey"),
      h("p", { class: "lead" }, "For each load step, add its photos and click control points on each (at least four on a plate, six on a mesh model): points of the specimen whose position you know in the model's mm.")),
    form,
  );
}

// -- Camera ----------------------------------------------------------------------------------------

function cameraFields(view) {
  const fromJob = h("input", { type: "radio", name: "camera-source", id: "camera-from-job", value: "job", checked: true, "data-testid": "camera-from-job" });
  const fromJson = h("input", { type: "radio", name: "camera-source", id: "camera-from-json", value: "json", "data-testid": "camera-from-json" });
  const select = h("select", { id: "calibration-job", "data-testid": "calibration-job", "aria-label": "Calibration job" },
    h("option", { value: "" }, "Loading calibration jobs…"));
  const json = h("textarea", { id: "camera-json", rows: 5, class: "mono", spellcheck: "false", "data-testid": "camera-json",
    "aria-label": "Camera JSON", placeholder: '{"width": 4000, "height": 3000, "fx": 3100, "fy": 3100, "cx": 2000, "cy": 1500, "k1": -0.1}' });
  let touched = false;
  const sync = () => {
    select.disabled = !fromJob.checked;
    json.disabled = !fromJson.checked;
  };
  for (const radio of [fromJob, fromJson]) radio.addEventListener("change", () => { touched = true; sync(); });
  api("GET", "/api/jobs", { signal: view.signal }).then((jobs) => {
    if (view.signal.aborted) return;
    const done = jobs.filter((j) => j.kind === JobKind.CALIBRATION && j.status === JobStatus.SUCCEEDED).sort((a, b) => b.id - a.id);
    select.replaceChildren(...(done.length ? done.map((j) => h("option", { value: j.id }, `Calibration #${j.id} · ${formatDate(j.created_at)}`))
      : [h("option", { value: "" }, "No finished calibration job")]));
    if (!done.length && !touched) fromJson.checked = true;
    sync();
  }).catch((err) => {
    if (!view.signal.aborted) select.replaceChildren(h("option", { value: "" }, `Could not list the jobs: ${messageOf(err)}`));
  });
  sync();

  function read() {
    if (fromJob.checked) {
      if (!select.value) throw new FieldError(select, "Camera: pick a finished calibration job, or paste the camera JSON.");
      return { calibration_job: Number(select.value) };
    }
    let camera;
    try {
      camera = JSON.parse(json.value);
    } catch (err) {
      throw new FieldError(json, `Camera JSON: ${err.message}`);
    }
    if (!camera || typeof camera !== "object" || Array.isArray(camera)) {
      throw new FieldError(json, "Camera JSON: an object with width, height, fx, fy, cx, cy and the distortion terms.");
    }
    return { camera };
  }
  const node = h("fieldset", { class: "card", "data-testid": "camera" },
    h("legend", {}, "Camera"),
    h("p", { class: "muted small" }, "The calibrated camera that took every photo, at full size."),
    h("label", { class: "check" }, fromJob, " From a calibration job"), select,
    h("label", { class: "check" }, fromJson, " Paste the camera JSON"), json);
  return { node, read };
}

// -- Load steps ------------------------------------------------------------------------------------

function stepList(view, specimen) {
  const steps = [];
  const box = h("div", { class: "stage-list" });
  const add = h("button", { type: "button", class: "btn", "data-testid": "add-stage" }, "Add load step");
  const taken = (name) => steps.findIndex((step) => step.names().includes(name));
  function renumber() {
    steps.forEach((step, i) => step.number(i, steps.length));
  }
  function addStep() {
    const step = stepEditor(view, specimen, taken, () => {
      steps.splice(steps.indexOf(step), 1);
      step.node.remove();
      renumber();
    });
    steps.push(step);
    box.append(step.node);
    renumber();
  }
  add.addEventListener("click", addStep);
  addStep();
  const node = h("section", { class: "card", "aria-labelledby": "stages-heading" },
    h("h2", { id: "stages-heading" }, "Load steps"),
    h("p", { class: "muted small" }, "In load order: each load step's cracks are compared with those of the load step before."),
    box, add);
  return {
    node,
    read: () => steps.map((step) => step.read()),
    files: () => steps.flatMap((step) => step.files()),
  };
}

function stepEditor(view, specimen, taken, onRemove) {
  const legend = h("legend", {});
  const labelId = uid("stage-label");
  const loadId = uid("stage-load");
  const label = h("input", { id: labelId, type: "text", maxlength: 100, "data-testid": "stage-label" });
  const load = h("input", { id: loadId, type: "number", step: "any", placeholder: "optional", "data-testid": "stage-load" });
  const files = h("input", { type: "file", accept: "image/*", multiple: true, class: "visually-hidden", "data-testid": "stage-photos" });
  const pick = h("label", { class: "btn small" }, files, "Add photos…");
  const remove = h("button", { type: "button", class: "btn small danger", "data-testid": "remove-stage" }, "Remove load step");
  const note = h("p", { class: "form-error", role: "alert" });
  const photos = [];
  const photoBox = h("div", { class: "photo-list" });
  let index = 0;

  files.addEventListener("change", () => {
    note.textContent = "";
    for (const file of files.files) {
      const owner = taken(file.name);
      if (owner >= 0) {
        note.textContent = `${file.name} is already in load step ${owner + 1}: each photo belongs to one load step.`;
        continue;
      }
      const photo = photoEditor(view, file, specimen, () => {
        photos.splice(photos.indexOf(photo), 1);
        photo.node.remove();
      });
      photos.push(photo);
      photoBox.append(photo.node);
    }
    files.value = ""; // the same file can be added again after it was removed
  });
  remove.addEventListener("click", () => {
    photos.forEach((photo) => photo.dispose());
    onRemove();
  });

  function number(i, count) {
    if (!label.value || label.value === `Load step ${index + 1}`) label.value = `Load step ${i + 1}`; // not a typed label
    index = i;
    legend.textContent = `Load step ${i + 1}`;
    remove.disabled = count < 2;
  }
  function read() {
    const where = `Load step ${index + 1}`;
    if (!label.value.trim()) throw new FieldError(label, `${where}: give it a label.`);
    if (!photos.length) throw new FieldError(files, `${where}: add at least one photo.`);
    const step = { label: label.value.trim(), photos: photos.map((photo) => photo.read(where)) };
    if (load.value.trim() !== "") step.load = Number(load.value);
    return step;
  }
  const node = h("fieldset", { class: "stage-editor", "data-testid": "stage" },
    legend,
    h("div", { class: "field-row" },
      h("div", {}, h("label", { for: labelId }, "Label"), label),
      h("div", {}, h("label", { for: loadId }, "Load ", h("span", { class: "muted" }, "(optional, your unit)")), load)),
    h("div", { class: "row stage-actions" }, pick, remove),
    note, photoBox);
  return { node, number, read, files: () => photos.map((p) => p.file), names: () => photos.map((p) => p.file.name) };
}

// -- One photo and its control points --------------------------------------------------------------

function photoEditor(view, file, specimen, onRemove) {
  const url = URL.createObjectURL(file);
  onAbort(view.signal, () => URL.revokeObjectURL(url));
  const img = h("img", { src: url, alt: `Photo ${file.name}: click to add a control point`, draggable: "false", "data-testid": "photo-image" });
  const markers = h("div", { class: "markers" });
  const frame = h("div", { class: "photo-frame" }, img, markers);
  const size = h("span", { class: "muted small" });
  const count = h("p", { class: "point-count", "data-testid": "point-count", "aria-live": "polite" });
  const rows = h("tbody", {});
  const table = h("table", { class: "table compact points" },
    h("caption", { class: "visually-hidden" }, `Control points of ${file.name}`),
    h("thead", {}, h("tr", {}, ["Point", "Pixel x, y", "X mm", "Y mm", "Z mm", ""].map((t) => h("th", { scope: "col", class: t === "Z mm" ? "z" : null }, t)))),
    rows);
  const planBox = h("div", { class: "plan-box" });
  const actual = h("input", { type: "checkbox", "data-testid": "actual-size" });
  const remove = h("button", { type: "button", class: "btn small danger", "data-testid": "remove-photo" }, "Remove photo");
  const points = []; // { x, y (photo pixels), X, Y, Z (typed mm, as text), marker, row, inputs, pixelText }
  let selected = null; // the point a click on the plan view fills
  let plan = null; // the mesh's plan and this photo's view of it
  let shown; // the plan `planBox` shows (null: the hint to choose a model)

  img.addEventListener("load", () => { size.textContent = ` ${img.naturalWidth} × ${img.naturalHeight} px`; });
  img.addEventListener("click", (event) => {
    if (!img.naturalWidth) return;
    const point = { ...pixelAt(img, event.clientX, event.clientY), X: "", Y: "", Z: "" };
    points.push(point);
    selected = point;
    render();
    point.inputs.X.focus({ preventScroll: true });
  });
  actual.addEventListener("change", () => frame.classList.toggle("actual", actual.checked));
  const stopFollowing = specimen.subscribe(followSpecimen);
  const dispose = () => {
    URL.revokeObjectURL(url);
    stopFollowing();
  };
  remove.addEventListener("click", () => {
    dispose();
    onRemove();
  });

  function place(point) {
    point.marker.style.left = `${((point.x + 0.5) / img.naturalWidth) * 100}%`;
    point.marker.style.top = `${((point.y + 0.5) / img.naturalHeight) * 100}%`;
    point.pixelText.textContent = `${point.x.toFixed(1)}, ${point.y.toFixed(1)}`;
  }
  function select(point) {
    if (!points.includes(point) || point === selected) return; // a deleted row's click still bubbles here
    selected = point;
    showSelection();
  }
  function showSelection() {
    for (const point of points) {
      point.row.classList.toggle("selected", point === selected);
      point.marker.classList.toggle("selected", point === selected);
    }
    if (plan) plan.view.redraw();
  }
  function render() {
    if (!points.includes(selected)) selected = null;
    markers.replaceChildren(...points.map((point, k) => {
      point.marker = marker(img, point, k, place, () => select(point));
      return point.marker;
    }));
    rows.replaceChildren(...points.map((point, k) => pointRow(point, k, {
      onDelete: () => {
        points.splice(k, 1);
        render();
      },
      onSelect: () => select(point),
      onInput: () => plan && plan.view.redraw(),
    })));
    points.forEach(place);
    showSelection();
    countPoints();
  }
  function countPoints() {
    const n = points.length;
    const needed = specimen.minPoints();
    count.textContent = `${plural(n, "control point")}${n < needed ? `: at least ${needed} are needed` : ""}`;
    count.classList.toggle("warn", n < needed);
  }
  function followSpecimen() {
    const mesh = specimen.kind() === "mesh";
    node.classList.toggle("mesh", mesh);
    table.classList.toggle("with-z", mesh);
    planBox.hidden = !mesh;
    const meshPlan = specimen.plan();
    if (meshPlan !== shown) {
      shown = meshPlan;
      plan = meshPlan && { of: meshPlan, view: planView(meshPlan, { name: file.name, points: planPoints, onPick: pick }) };
      planBox.replaceChildren(plan ? plan.view.node
        : h("p", { class: "muted small" }, "Choose the mesh model under Specimen to pick the points' X, Y, Z on it."));
    }
    countPoints();
  }
  function planPoints() {
    const typed = (text) => (String(text).trim() === "" ? NaN : Number(text));
    return points.map((point, k) => ({ label: String(k), model: [typed(point.X), typed(point.Y), typed(point.Z)], selected: point === selected }));
  }
  function pick(vertex) {
    if (!selected) {
      plan.view.say("Select a control point first: click its row in the table.");
      return;
    }
    const xyz = plan.of.vertex(vertex).map(formatMm);
    ["X", "Y", "Z"].forEach((axis, a) => {
      selected[axis] = xyz[a];
      selected.inputs[axis].value = xyz[a];
    });
    plan.view.say(`Point ${points.indexOf(selected)} ← vertex ${vertex}: ${xyz.join(", ")} mm`);
    plan.view.redraw();
  }
  render();

  function read(where) {
    const mesh = specimen.kind() === "mesh";
    return {
      image: file.name,
      control_points: points.map((point, k) => {
        const mm = (axis) => {
          const value = point[axis];
          if (String(value).trim() === "" || !Number.isFinite(Number(value))) {
            throw new FieldError(point.inputs[axis], `${where}, ${file.name}, point ${k}: give its model ${axis} in mm.`);
          }
          return Number(value);
        };
        const round = (v) => Math.round(v * 100) / 100;
        return { pixel: [round(point.x), round(point.y)], model: [mm("X"), mm("Y"), mesh ? mm("Z") : 0] };
      }),
    };
  }
  const node = h("div", { class: "photo-editor", "data-testid": "photo", "data-name": file.name },
    h("div", { class: "row spread photo-head" },
      h("span", {}, h("span", { class: "filename strong" }, file.name), size),
      h("span", { class: "row" }, h("label", { class: "check small" }, actual, " Actual size"), remove)),
    h("div", { class: "photo-grid" },
      h("div", { class: "photo-scroll" }, frame),
      h("div", { class: "point-panel" }, count, table,
        h("p", { class: "muted small" }, "Click the photo to add a point; drag a point, or focus it and use the arrow keys, to move it.",
          h("span", { class: "mesh-only" }, " To take a vertex's X, Y, Z: click the point's row, then the vertex in the plan view.")),
        planBox)));
  followSpecimen();
  return { node, file, read, dispose };
}

/** Photo pixel (x, y) at viewport point (clientX, clientY) over `img`: (0, 0) is the centre of its first pixel. */
function pixelAt(img, clientX, clientY) {
  const rect = img.getBoundingClientRect();
  return onPhoto(img, ((clientX - rect.left) * img.naturalWidth) / rect.width - 0.5,
    ((clientY - rect.top) * img.naturalHeight) / rect.height - 0.5);
}

function onPhoto(img, x, y) {
  const clamp = (v, n) => Math.min(Math.max(v, -0.5), n - 0.5);
  return { x: clamp(x, img.naturalWidth), y: clamp(y, img.naturalHeight) };
}

/** A draggable, keyboard-movable marker of control point `k` on `img`; `moved(point)` redraws it, `onSelect()`
 * makes it the selected point. */
function marker(img, point, k, moved, onSelect) {
  const node = h("button", { type: "button", class: "marker", "data-testid": "marker", "aria-label": `Control point ${k}: drag or use the arrow keys to move it` },
    h("span", {}, String(k)));
  node.addEventListener("focus", onSelect);
  node.addEventListener("pointerdown", (event) => {
    event.preventDefault();
    node.setPointerCapture(event.pointerId);
    onSelect();
  });
  node.addEventListener("pointermove", (event) => {
    if (!node.hasPointerCapture(event.pointerId)) return;
    Object.assign(point, pixelAt(img, event.clientX, event.clientY));
    moved(point);
  });
  node.addEventListener("keydown", (event) => {
    const step = event.shiftKey ? 10 : 1;
    const delta = { ArrowLeft: [-step, 0], ArrowRight: [step, 0], ArrowUp: [0, -step], ArrowDown: [0, step] }[event.key];
    if (!delta) return;
    event.preventDefault();
    Object.assign(point, onPhoto(img, point.x + delta[0], point.y + delta[1]));
    moved(point);
  });
  return node;
}

/** The table row of control point `k`: its pixel and its model X, Y, Z (the Z cell shown on a mesh only). */
function pointRow(point, k, { onDelete, onSelect, onInput }) {
  const input = (axis) => {
    const node = h("input", { type: "number", step: "any", value: point[axis], "aria-label": `Point ${k} model ${axis} mm`,
      "data-testid": `point-model-${axis.toLowerCase()}` });
    node.addEventListener("input", () => {
      point[axis] = node.value;
      onInput();
    });
    return node;
  };
  point.inputs = { X: input("X"), Y: input("Y"), Z: input("Z") };
  point.pixelText = h("span", { class: "mono" });
  point.row = h("tr", { "data-testid": "point-row", onclick: onSelect, onfocusin: onSelect },
    h("td", {}, String(k)), h("td", {}, point.pixelText), h("td", {}, point.inputs.X), h("td", {}, point.inputs.Y),
    h("td", { class: "z" }, point.inputs.Z),
    h("td", {}, h("button", { type: "button", class: "btn small", "aria-label": `Delete point ${k}`, "data-testid": "point-delete", onclick: onDelete }, "×")));
  return point.row;
}
