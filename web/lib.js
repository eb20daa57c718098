/* Shared helpers of the viewer: DOM building, formatting, progress bars and the JSON API client.
 *
 * The DOM is built with createElement and textContent, never innerHTML, so names and file names
 * typed by users cannot inject markup (web/eslint.config.js forbids innerHTML and its kin). Leaflet
 * sets a string tooltip, popup or divIcon as HTML: give it a node built with `h()` instead. A URL
 * attribute (href, src) is only set to an http(s) or blob: URL (`safeUrl`), and a link to a job's
 * output only to one of this service's own /api/ paths (`apiUrl`).
 *
 * Every request to the API goes through `api` or `apiForm` here (the photo upload, an XMLHttpRequest for its
 * progress, adds `authHeaders()` itself): they send the signed-in user's token as `Authorization: Bearer`.
 * The token lives in sessionStorage only (never a cookie, never localStorage): it goes with the tab, and
 * another site's page cannot make the browser send it. An answer 401 calls the handler set with
 * `onUnauthorized` (sign-in.js shows the sign-in form). Image tags, Leaflet tiles and EventSource cannot send
 * a header: they take the URLs the API signs (TileJSON tiles, outputs' `url`), or a job's `signature`
 * appended with `signedUrl`.
 */

import { JobStatus } from "./kinds.js";

export const ACTIVE = new Set([JobStatus.QUEUED, JobStatus.RUNNING]);
export const TERMINAL = new Set([JobStatus.SUCCEEDED, JobStatus.FAILED, JobStatus.CANCELLED]);

// -- DOM and formatting helpers ------------------------------------------------------------------

// Attributes the browser follows as URLs: a `javascript:` URL there runs script when the link is followed.
const URL_ATTRIBUTES = new Set(["href", "src", "action", "formaction"]);
const URL_SCHEMES = new Set(["http:", "https:", "blob:"]);

/**
 * Create an element: attributes (on* = listeners, text = textContent) and children. Strings, numbers and
 * anything else that is not a Node become text nodes, never markup; a URL attribute whose URL is not http(s)
 * or blob: (`safeUrl`) is left out.
 */
export function h(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (key === "class") node.className = value;
    else if (key === "text") node.textContent = value;
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else if (URL_ATTRIBUTES.has(key.toLowerCase())) {
      const url = safeUrl(value);
      if (url !== null) node.setAttribute(key, url);
    } else node.setAttribute(key, value === true ? "" : String(value));
  }
  for (const child of children.flat(Infinity)) {
    if (child === null || child === undefined || child === false) continue;
    node.append(child instanceof Node ? child : String(child));
  }
  return node;
}

/** `value` if it is an http(s) or blob: URL, or a path or `#/...` route (which resolve to one); else null. */
export function safeUrl(value) {
  const text = String(value);
  try {
    // Parsed as the browser would follow it: "java\tscript:" and " javascript:" are javascript: URLs too.
    return URL_SCHEMES.has(new URL(text, document.baseURI).protocol) ? text : null;
  } catch {
    return null;
  }
}

/** `url` (from an API answer, e.g. an output's `url`) if it names a path of this service's API, else null. */
export function apiUrl(url) {
  if (typeof url !== "string" || !url) return null;
  try {
    const parsed = new URL(url, document.baseURI);
    const own = parsed.origin === window.location.origin && parsed.pathname.startsWith("/api/");
    return own ? parsed.href : null;
  } catch {
    return null;
  }
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
/** The report's warnings (strings only) as alerts, each with `data-testid` `testid`. */
export function warningAlerts(items, testid) {
  return (Array.isArray(items) ? items : []).filter((text) => typeof text === "string")
    .map((text) => h("p", { class: "alert warning", role: "status", "data-testid": testid }, text));
}

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

/** A count ("12"); "–" when it is missing or not finite. */
export function formatCount(n) {
  return Number.isFinite(n) ? String(n) : "–";
}

/** "3 photos", "1 photo" ("? photos" for a missing count). */
export function plural(n, word) {
  return `${n ?? "?"} ${word}${n === 1 ? "" : "s"}`;
}

/** "1.00, 2.50, 3.00": the numbers of `v` (exactly `length` of them, if given); "–" when any is missing. */
export function formatVector(v, digits, length) {
  const ok = Array.isArray(v) && v.length > 0 && (length === undefined || v.length === length) && v.every(Number.isFinite);
  return ok ? v.map((x) => x.toFixed(digits)).join(", ") : "–";
}

/** A camera parameter: 2 decimals when `fixed` (pixels) or it is large, else 4 significant digits. */
export function formatParam(value, fixed = false) {
  if (typeof value !== "number" || !Number.isFinite(value)) return "–";
  return fixed || Math.abs(value) >= 10 ? value.toFixed(2) : value.toPrecision(4);
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

/** A file name in a table cell ("–" when missing), its whole name in the tooltip. */
export function filename(name) {
  return h("span", { class: "filename", title: name || "" }, name || "–");
}

/**
 * "Downloads": a link per job output ({name, url, size_bytes}), named by `labelOf(name)`, its test id
 * `testidOf(name)`; an output without a url of this service's API (`apiUrl`) is shown "(not available)".
 * Answers [heading, list].
 */
export function downloadList(outputs, labelOf = (name) => name, testidOf = (name) => `download-${String(name).replace(/\.[^.]+$/, "")}`) {
  const link = (o, href) => h("a", { href, download: o.name, "data-testid": testidOf(o.name) },
    labelOf(o.name), h("span", { class: "muted small" }, ` ${o.name} · ${formatBytes(o.size_bytes)}`));
  const item = (o) => {
    const href = apiUrl(o.url);
    return h("li", {}, href ? link(o, href) : h("span", { class: "muted" }, `${labelOf(o.name)} (not available)`));
  };
  return [
    h("h3", {}, "Downloads"),
    outputs.length ? h("ul", { class: "plain downloads" }, outputs.map(item))
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
  } catch {
    return null;
  }
}

// -- Sign-in token -------------------------------------------------------------------------------

const TOKEN_KEY = "fotoskhema.token";
let unauthorizedHandler = () => {};

/** The signed-in user's API token ("" when none): sessionStorage only, never a cookie. */
export function storedToken() {
  try {
    return window.sessionStorage.getItem(TOKEN_KEY) || "";
  } catch {
    return ""; // storage disabled: nobody is signed in
  }
}

export function storeToken(token) {
  window.sessionStorage.setItem(TOKEN_KEY, token);
}

export function forgetToken() {
  window.sessionStorage.removeItem(TOKEN_KEY);
}

/** `{ Authorization: "Bearer <token>" }` for `token` (default: the stored one); `{}` when there is none. */
export function authHeaders(token = storedToken()) {
  return token ? { Authorization: `Bearer ${token}` } : {};
}

/** Call `handler({ sentToken, detail })` when an API answer is 401 (no token, or one the server refuses). */
export function onUnauthorized(handler) {
  unauthorizedHandler = handler;
}

/** Tell the sign-in that a request sent with `sentToken` ("" for none) was answered 401. */
export function reportUnauthorized(sentToken, detail) {
  try {
    unauthorizedHandler({ sentToken, detail });
  } catch (err) {
    console.warn("the sign-in handler failed", err);
  }
}

/** `path` with a job's `signature` (the `exp=...&sig=...` of GET /api/jobs/<id>) appended, if there is one. */
export function signedUrl(path, signature) {
  if (!signature) return path;
  return `${path}${path.includes("?") ? "&" : "?"}${signature}`;
}

/** The `signature` that opens job `jobId`'s tiles, downloads and event stream without a token ("" if none). */
export async function jobSignature(jobId, { signal } = {}) {
  const job = await api("GET", `/api/jobs/${jobId}`, { signal });
  return (job && typeof job.signature === "string" && job.signature) || "";
}

// -- Requests ------------------------------------------------------------------------------------

/** The JSON of an answer; an ApiError for an error answer. A 401 is reported unless `quiet`. */
async function answer(response, sentToken, quiet) {
  const data = parseJson(await response.text());
  if (!response.ok) {
    const error = new ApiError(response.status, detailOf(data, response.status, response.statusText));
    if (response.status === 401 && !quiet) reportUnauthorized(sentToken, error.message);
    throw error;
  }
  return data;
}

/**
 * Ask the JSON API with the stored token; `body` (optional) is sent as JSON. `signal` (an AbortSignal, e.g.
 * the view's) aborts the request: the promise then rejects with the signal's reason, an AbortError. `token`
 * (optional) sends that token instead, and a 401 is then only the ApiError (the sign-in checks a token so).
 */
export async function api(method, path, { body, signal, token } = {}) {
  const sent = token === undefined ? storedToken() : token;
  const init = { method, headers: { Accept: "application/json", ...authHeaders(sent) }, signal };
  if (body !== undefined) {
    init.headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  return answer(await fetch(path, init), sent, token !== undefined);
}

/** Send a multipart form (file uploads) and answer the JSON, like `api`. */
export async function apiForm(method, path, form, { signal } = {}) {
  const sent = storedToken();
  const headers = { Accept: "application/json", ...authHeaders(sent) };
  return answer(await fetch(path, { method, body: form, headers, signal }), sent, false);
}

/** A job's outputs list ([{ name, url, size_bytes }]). */
export function jobOutputs(jobId, { signal } = {}) {
  return api("GET", `/api/jobs/${jobId}/outputs`, { signal }).then((data) => (data && data.outputs) || []);
}

/** Run `cleanup` when `signal` is aborted (at once if it already is); a failing cleanup is logged. */
export function onAbort(signal, cleanup) {
  const run = () => {
    try {
      cleanup();
    } catch (err) {
      console.warn("cleanup failed", err);
    }
  };
  if (signal.aborted) run();
  else signal.addEventListener("abort", run, { once: true });
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
