/* The processing options a user needs before starting a mosaic (output resolution, working size, features,
 * blending), each with its default for the chosen mode, from /api/config's `mosaic_options` (the API reads them
 * off its option model, so they are the defaults a job gets). Only options changed from the mode's default are
 * sent; the rest stay the service's. */

import { h } from "./lib.js";
import { label } from "./labels.js";

// How each option is named and its values shown (labels.js holds the values' display names)
const FIELDS = {
  output_resolution: { text: "Output resolution", values: "resolution", ortho: "Ortho mode composes at the working size." },
  working_max_px: { text: "Working size (longest side, px)" },
  feature_type: { text: "Features", values: "feature_type" },
  blend: { text: "Blending", values: "blend" },
};

/** The options fieldset for `specs` (config.mosaic_options); `options(mode)` answers what to send. */
export function optionsForm(specs, initialMode) {
  const fields = (Array.isArray(specs) ? specs : []).filter((s) => s && FIELDS[s.name]).map((spec) => field(spec));
  let mode = initialMode;
  function setMode(next) {
    mode = next;
    for (const f of fields) f.setMode(mode);
  }
  setMode(mode);
  const node = h("fieldset", { class: "job-options", "data-testid": "job-options" },
    h("legend", {}, "Options"),
    fields.length ? fields.map((f) => f.node) : h("p", { class: "muted small" }, "The service's defaults."),
    h("p", { class: "muted small" }, "Each starts at its default for the mode; the API takes every other option too (see the API docs)."));
  return {
    node,
    setMode,
    options: () => Object.fromEntries(fields.map((f) => f.changed()).filter(Boolean)),
  };
}

function field(spec) {
  const meta = FIELDS[spec.name];
  const id = `option-${spec.name}`;
  const choices = Array.isArray(spec.choices) ? spec.choices : null;
  const input = choices
    ? h("select", { id, "data-testid": id }, choices.map((value) => h("option", { value }, label(meta.values, value))))
    : h("input", { id, "data-testid": id, type: "number", step: 1, min: spec.minimum, max: spec.maximum, class: "narrow-input" });
  const note = h("span", { class: "muted small", "data-testid": `${id}-default` });
  const error = h("span", { class: "form-error small" });
  let touched = false;
  let mode = "planar";
  const defaultOf = () => (spec.default || {})[mode];
  input.addEventListener("change", () => {
    touched = true;
    check();
  });
  function check() {
    if (choices) return true;
    const value = Number(input.value);
    const ok = Number.isInteger(value) && value >= spec.minimum && value <= spec.maximum;
    error.textContent = ok ? "" : `a whole number from ${spec.minimum} to ${spec.maximum}`;
    return ok;
  }
  return {
    node: h("div", { class: "option-row" }, h("label", { for: id }, meta.text), input, note, error),
    setMode(next) {
      mode = next;
      const fallback = defaultOf();
      if (!touched && fallback !== undefined) input.value = String(fallback);
      note.textContent = fallback === undefined ? "" : `default: ${choices ? label(meta.values, fallback) : fallback}`;
      input.disabled = Boolean(meta.ortho) && mode === "ortho";
      if (input.disabled) note.textContent = meta.ortho;
    },
    changed() {
      if (input.disabled || !check()) return null;
      const value = choices ? input.value : Number(input.value);
      return value === defaultOf() ? null : [spec.name, value];
    },
  };
}
