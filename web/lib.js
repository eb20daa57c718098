/* Shared helpers of the viewer: DOM building, formatting, progress bars and the JSON API client.
 *
 * The DOM is built with createElement and textContent, never innerHTML, so names and file names
 * typed by users cannot inject markup.
 */

export const ACTIVE = new Set(["queued", "running"]);
export const TERMINAL = new Set(["succeeded", "failed", "cancelled"]);

// -- DOM and formatting helpers ------------------------------------------------------------------

/** Create an element: attributes (on* = listeners, text = textContent) and children. */
export function h(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (key === "class") node.className = value;
    else if (key === "text") node.textContent = value;
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else node.setAttribute(key, value === true ? "" : String(value));
  }
  for (const child of children.flat(Infinity)) {
    if (child === null || child === undefined || child === false) continue;
    node.append(child instanceof Node ? child : String(child));
  }
  return node;
}

export function formatBytes(n) {
  if (n === null || n === undefined) return "–";
  const units = ["B", "KB", "MB", "GB", "TB"];
  let value = n;
  let unit = 0;
  while (value >= 1000 && unit < units.length - 1) {
    value /= 1000;
    unit += 1;
  }
  return `${value.toFixed(unit === 0 || value >= 100 ? 0 : 1)} ${units[unit]}`;
}

export function formatDate(iso) {
  if (!iso) return "–";
  // The server stores UTC; SQLite hands datetimes back without their zone, so say it is UTC.
  const zoned = /T\d{2}:\d{2}(:\d{2}(\.\d+)?)?$/.test(iso) ? `${iso}Z` : iso;
  const date = new Date(zoned);
  if (Number.isNaN(date.getTime())) return iso;
  return date.toLocaleString(undefined, { dateStyle: "medium", timeStyle: "short" });
}

/** The objects of an array from a report (anything else in it, or a missing array: none). */
export function list(value) {
  return Array.isArray(value) ? value.filter((item) => item && typeof item === "object") : [];
}

/** A number with `digits` decimals and an optional unit; "–" when it is missing or not finite. */
export function formatNumber(value, digits = 2, unit = "") {
  if (typeof value !== "number" || !Number.isFinite(value)) return "–";
  return unit ? `${value.toFixed(digits)} ${unit}` : value.toFixed(digits);
}

/** A ground distance in metres: cm below 1 m, m above; "–" when missing. */
export function formatMetres(m) {
  if (typeof m !== "number" || !Number.isFinite(m)) return "–";
  return Math.abs(m) < 1 ? `${(m * 100).toFixed(1)} cm` : `${m.toFixed(2)} m`;
}

/** A value and its standard deviation: "536.12 ± 0.41"; the ± part only when the sigma is known. */
export function formatPlusMinus(value, sigma, digits = 2, unit = "") {
  const text = formatNumber(value, digits);
  if (text === "–") return text;
  const tail = unit ? ` ${unit}` : "";
  return typeof sigma === "number" && Number.isFinite(sigma) ? `${text} ± ${sigma.toFixed(digits)}${tail}` : `${text}${tail}`;
}

export function formatSeconds(s) {
  if (typeof s !== "number" || !Number.isFinite(s)) return "";
  if (s < 1) return `${Math.round(s * 1000)} ms`;
  if (s < 60) return `${s.toFixed(1)} s`;
  return `${Math.floor(s / 60)} min ${Math.round(s % 60)} s`;
}

/** "detect_features" -> "Detect features". */
export function humanize(name) {
  const text = String(name || "").replace(/_/g, " ");
  return text.charAt(0).toUpperCase() + text.slice(1);
}

export function statusBadge(status, attrs) {
  return h("span", Object.assign({ class: `badge status-${status}` }, attrs || {}), status);
}

/** A labelled progress bar; `set(null)` shows an indeterminate (animated) bar. */
export function progressBar(label, attrs) {
  const fill = h("div", { class: "progress-fill" });
  const node = h(
    "div",
    Object.assign(
      { class: "progress", role: "progressbar", "aria-label": label, "aria-valuemin": 0, "aria-valuemax": 100 },
      attrs || {},
    ),
    fill,
  );
  function set(percent) {
    const indeterminate = percent === null || percent === undefined;
    node.classList.toggle("indeterminate", indeterminate);
    if (indeterminate) {
      node.removeAttribute("aria-valuenow");
      fill.style.width = "";
      return;
    }
    const clamped = Math.max(0, Math.min(100, percent));
    node.setAttribute("aria-valuenow", String(Math.round(clamped)));
    fill.style.width = `${clamped}%`;
  }
  function tone(name) {
    node.dataset.tone = name || "";
  }
  set(0);
  return { node, set, tone };
}

/** A definition list of [term, value, attrs?] rows (value: text or node). */
export function factList(rows, attrs) {
  return h("dl", Object.assign({ class: "facts" }, attrs || {}),
    rows.map(([term, value, ddAttrs]) => [h("dt", {}, term), h("dd", ddAttrs || {}, value)]));
}

/**
 * A table in a scrolling box. `columns`: [{ label, num }] (num: right-aligned figures); `rows`: arrays
 * of cells (text or nodes), or { cells, attrs } to give the row attributes. An empty list shows `empty`.
 */
export function dataTable({ caption, columns, rows, attrs, empty, scroll = true }) {
  if (!rows.length) return h("p", { class: "empty small" }, empty || "None.");
  const cls = (col) => (col.num ? "num" : null);
  const table = h(
    "table",
    Object.assign({ class: "table compact" }, attrs || {}),
    caption ? h("caption", { class: "visually-hidden" }, caption) : null,
    h("thead", {}, h("tr", {}, columns.map((col) => h("th", { scope: "col", class: cls(col) }, col.label)))),
    h("tbody", {}, rows.map((row) => {
      const { cells, attrs: rowAttrs } = Array.isArray(row) ? { cells: row, attrs: {} } : row;
      return h("tr", rowAttrs, cells.map((cell, i) => h("td", { class: cls(columns[i] || {}) }, cell)));
    })),
  );
  return scroll ? h("div", { class: "table-scroll" }, table) : table;
}

/** "Downloads": a link per job output ({name, url, size_bytes}), named by `labelOf(name)`; [heading, list]. */
export function downloadList(outputs, labelOf = (name) => name) {
  const link = (o) => h("a", { href: o.url, download: o.name, "data-testid": `download-${o.name.replace(/\.[^.]+$/, "")}` },
    labelOf(o.name), h("span", { class: "muted small" }, ` ${o.name} · ${formatBytes(o.size_bytes)}`));
  return [
    h("h3", {}, "Downloads"),
    outputs.length ? h("ul", { class: "plain downloads" }, outputs.map((o) => h("li", {}, link(o))))
      : h("p", { class: "muted small" }, "No downloads."),
  ];
}

// -- API -----------------------------------------------------------------------------------------

export class ApiError extends Error {
  constructor(status, detail) {
    super(detail);
    this.status = status;
  }
}

/** The `detail` of an error answer; FastAPI's validation errors are a list of {loc, msg}. */
export function detailOf(data, status, statusText) {
  const detail = data && data.detail;
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) {
    return detail
      .map((d) => (d && d.msg ? `${(d.loc || []).slice(1).join(".") || "request"}: ${d.msg}` : JSON.stringify(d)))
      .join("; ");
  }
  return `${status} ${statusText || "error"}`.trim();
}

export function parseJson(text) {
  if (!text) return null;
  try {
    return JSON.parse(text);
  } catch (_err) {
    return null;
  }
}

export async function api(method, path, body) {
  const init = { method, headers: { Accept: "application/json" } };
  if (body !== undefined) {
    init.headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  const response = await fetch(path, init);
  const data = parseJson(await response.text());
  if (!response.ok) throw new ApiError(response.status, detailOf(data, response.status, response.statusText));
  return data;
}

/** Send a multipart form (file uploads) and answer the JSON, like `api`. */
export async function apiForm(method, path, form) {
  const response = await fetch(path, { method, body: form, headers: { Accept: "application/json" } });
  const data = parseJson(await response.text());
  if (!response.ok) throw new ApiError(response.status, detailOf(data, response.status, response.statusText));
  return data;
}

export function messageOf(err) {
  if (err instanceof ApiError) return err.message;
  return `Could not reach the server (${err && err.message ? err.message : err}).`;
}

let configPromise = null;
export function getConfig() {
  configPromise = configPromise || api("GET", "/api/config").catch(() => ({ basemap_url: "" }));
  return configPromise;
}

export function breadcrumb(...items) {
  const list = h("ol", {});
  items.forEach((item, i) => {
    const last = i === items.length - 1;
    // An item without a link (a section with no page of its own) is plain text.
    const node = last ? h("span", { "aria-current": "page" }, item[0]) : item[1] ? h("a", { href: item[1] }, item[0]) : h("span", {}, item[0]);
    list.append(h("li", {}, node));
  });
  return h("nav", { class: "breadcrumb", "aria-label": "Breadcrumb" }, list);
}
