/* Flight page (#/flights/<id>): upload photos (drag and drop or file input); the photos on a map, with previews and
 * what the upload check found (flight-photos.js), to delete a bad one before starting; the mosaic mode and options
 * (job-options.js); its jobs. */

import {
  ACTIVE,
  ApiError,
  api,
  apiForm,
  authHeaders,
  breadcrumb,
  detailOf,
  formatBytes,
  formatDate,
  getConfig,
  h,
  humanize,
  messageOf,
  onAbort,
  parseJson,
  plural,
  progressBar,
  reportUnauthorized,
  statusBadge,
  storedToken,
} from "./lib.js";
import { JobKind } from "./kinds.js";
import { deleteControl } from "./delete.js";
import { photoPanel } from "./flight-photos.js";
import { optionsForm } from "./job-options.js";
import { byUploadKind, resumableUpload } from "./resumable-upload.js";

const JOB_POLL_MS = 3000; // how often the job list refreshes while a job is active

// -- Flight page ---------------------------------------------------------------------------------

export async function renderFlight(view, root, flightId) {
  const [flight, config] = await Promise.all([api("GET", `/api/flights/${flightId}`, { signal: view.signal }), getConfig()]);
  if (view.signal.aborted) return;
  document.title = `${flight.name} · Fotoskhema`;
  let images = flight.images || [];

  const countText = h("span", {});
  const jobs = jobsPanel(view, flightId, config);
  const photos = photoPanel(view, flightId, { config, onDeleted: () => reload() });
  const imagesBody = h("div", { class: "card-body" }, photos.node);
  function showImages() {
    countText.textContent = plural(images.length, "photo");
    photos.show(images);
    jobs.setImageCount(images.length);
  }
  // The check judges each photo against the others: read them all again once some came or went.
  let reloading = null;
  function reload() {
    reloading = reloading || api("GET", `/api/flights/${flightId}`, { signal: view.signal }).then((fresh) => {
      if (!view.signal.aborted) {
        images = fresh.images || [];
        showImages();
      }
    }).catch(() => {}).finally(() => {
      reloading = null;
    });
    return reloading;
  }
  const upload = uploadPanel(view, flightId, (added) => {
    images = images.concat(added.filter((a) => !images.some((i) => i.id === a.id)));
    showImages();
    reload();
  });

  const deletion = deleteControl({
    label: "Delete flight",
    testid: "delete-flight",
    question: `Delete the flight “${flight.name}” with its photos and all its jobs and their results? This cannot be undone.`,
    path: `/api/flights/${flightId}`,
    then: "#/",
  });
  root.append(
    breadcrumb(["Flights", "#/"], [flight.name]),
    h(
      "div",
      { class: "page-head" },
      h("div", { class: "head-title" }, h("h1", {}, flight.name), h("span", { class: "push-right" }, deletion.button)),
      flight.description ? h("p", { class: "lead" }, flight.description) : null,
      h("p", { class: "muted small" }, `Created ${formatDate(flight.created_at)} · `, countText),
      deletion.error,
    ),
    h(
      "div",
      { class: "layout sidebar-right" },
      h(
        "div",
        { class: "stack" },
        upload,
        h("section", { class: "card", "aria-labelledby": "images-heading" }, h("h2", { id: "images-heading" }, "Photos"), imagesBody),
      ),
      jobs.node,
    ),
  );
  showImages();
  await jobs.refresh();
}

function uploadPanel(view, flightId, onUploaded) {
  const input = h("input", {
    id: "file-input", type: "file", multiple: true, accept: "image/*,.jpg,.jpeg,.tif,.tiff",
    class: "visually-hidden", "data-testid": "file-input",
  });
  const bar = progressBar("Upload progress", { "data-testid": "upload-progress" });
  bar.node.hidden = true; // shown from the first upload on
  const status = h("p", { class: "upload-status", role: "status", "aria-live": "polite" });
  const zone = h(
    "div",
    { class: "drop-zone", "data-testid": "drop-zone" },
    h("div", { class: "drop-icon", "aria-hidden": "true" }),
    h("p", { class: "drop-title" }, "Drag photos here"),
    h("p", { class: "muted" }, "or ", h("label", { for: "file-input", class: "btn small" }, "Choose photos…")),
    input,
    h("p", { class: "muted small" }, "JPEG or TIFF frames, with EXIF GPS for a georeferenced map. Several files per upload."),
  );
  let xhr = null;
  let busy = false; // an upload is under way (a resumable one has no `xhr` of its own here)
  onAbort(view.signal, () => xhr && xhr.abort());

  function finish() {
    if (xhr) xhr.abort();
    xhr = null;
    busy = false;
    zone.classList.remove("busy");
    input.disabled = false;
    input.value = "";
  }
  // One request per batch: the server takes at most `max_files_per_request` parts and `max_request_bytes` in
  // one request, and stores each request's photos all or none.
  async function upload(fileList) {
    const files = Array.from(fileList || []);
    if (!files.length || xhr || busy) return;
    busy = true;
    const label = plural(files.length, "photo");
    const totalBytes = files.reduce((sum, f) => sum + f.size, 0);
    zone.classList.add("busy");
    input.disabled = true;
    bar.node.hidden = false;
    bar.tone("");
    bar.set(0);
    status.className = "upload-status";
    status.textContent = `Uploading ${label} (${formatBytes(totalBytes)})…`;
    let stored = 0;
    let sentBytes = 0;
    try {
      const limits = await api("GET", "/api/config", { signal: view.signal });
      const { small, large } = byUploadKind(files, limits);
      for (const batch of batches(small, limits)) {
        const batchBytes = batch.reduce((sum, f) => sum + f.size, 0);
        const answer = await sendBatch(batch, (loaded) => {
          const percent = totalBytes ? ((sentBytes + loaded) / totalBytes) * 100 : 100;
          bar.set(percent);
          status.textContent = `Uploading ${label}… ${Math.round(percent)} %`;
        });
        if (!answer.ok) {
          const kept = stored ? ` ${plural(stored, "photo")} of ${files.length} were stored before;` : "";
          throw new Error(`Upload failed,${kept} nothing of the last ${plural(batch.length, "photo")} was stored: ${answer.detail}`);
        }
        stored += answer.images.length;
        sentBytes += batchBytes;
        onUploaded(answer.images);
      }
      for (const file of large) { // one by one, resumable (tus): a network error resumes from the server's offset
        const image = await resumableUpload(file, {
          flightId,
          chunkBytes: limits.resumable_chunk_bytes,
          signal: view.signal,
          onProgress: (sent) => {
            const percent = totalBytes ? ((sentBytes + sent) / totalBytes) * 100 : 100;
            bar.set(percent);
            status.textContent = `Uploading ${label}… ${Math.round(percent)} %`;
          },
          onRetry: (attempt, delayMs) => {
            status.textContent = `Connection lost; resuming ${file.name} in ${Math.round(delayMs / 1000)} s (try ${attempt})…`;
          },
        }).catch((error) => {
          const kept = stored ? ` ${plural(stored, "photo")} of ${files.length} were stored before;` : "";
          throw new ApiError(error.status || 0, `Upload failed,${kept} ${messageOf(error)}`);
        });
        stored += 1;
        sentBytes += file.size;
        onUploaded([image]);
      }
      bar.tone("done");
      status.textContent = `Uploaded ${plural(stored, "photo")}.`;
    } catch (error) {
      if (view.signal.aborted) return;
      bar.tone("error");
      status.className = "upload-status error";
      status.textContent = messageOf(error);
    } finally {
      finish();
    }
  }

  /** POST one batch with an XMLHttpRequest (fetch reports no upload progress); it sends the token as `api` does. */
  function sendBatch(batch, onProgress) {
    return new Promise((resolve) => {
      const form = new FormData();
      for (const file of batch) form.append("files", file, file.name);
      const sentToken = storedToken();
      xhr = new XMLHttpRequest();
      xhr.open("POST", `/api/flights/${flightId}/images`);
      xhr.setRequestHeader("Accept", "application/json");
      for (const [name, value] of Object.entries(authHeaders(sentToken))) xhr.setRequestHeader(name, value);
      xhr.upload.onprogress = (event) => {
        if (event.lengthComputable) onProgress((event.loaded / event.total) * batch.reduce((s, f) => s + f.size, 0));
      };
      xhr.upload.onload = () => {
        status.textContent = `Reading metadata of ${plural(batch.length, "photo")}…`;
      };
      xhr.onload = () => {
        const request = xhr;
        xhr = null;
        const data = parseJson(request.responseText);
        if (request.status >= 200 && request.status < 300 && data && Array.isArray(data.images)) {
          resolve({ ok: true, images: data.images });
          return;
        }
        const detail = detailOf(data, request.status, request.statusText);
        if (request.status === 401) reportUnauthorized(sentToken, detail);
        resolve({ ok: false, detail });
      };
      xhr.onerror = () => {
        xhr = null;
        resolve({ ok: false, detail: "the server could not be reached" });
      };
      xhr.onabort = () => {
        xhr = null;
        resolve({ ok: false, detail: "the upload was stopped" });
      };
      xhr.send(form);
    });
  }

  input.addEventListener("change", () => upload(input.files));
  for (const type of ["dragenter", "dragover"]) {
    zone.addEventListener(type, (event) => {
      event.preventDefault();
      if (event.dataTransfer) event.dataTransfer.dropEffect = "copy";
      zone.classList.add("dragging");
    });
  }
  zone.addEventListener("dragleave", (event) => {
    if (!zone.contains(event.relatedTarget)) zone.classList.remove("dragging");
  });
  zone.addEventListener("drop", (event) => {
    event.preventDefault();
    zone.classList.remove("dragging");
    upload(event.dataTransfer && event.dataTransfer.files);
  });

  return h(
    "section",
    { class: "card", "aria-labelledby": "upload-heading" },
    h("h2", { id: "upload-heading" }, "Upload photos"),
    zone,
    h("div", { class: "upload-progress" }, bar.node, status),
  );
}

// The mosaic modes offered before starting a job, and the options each sends.
const MODES = [
  { value: "planar", label: "Planar", note: "flat ground, fastest", options: {} },
  { value: "ortho", label: "Ortho", note: "photo-triangulation + orthorectification", options: { mode: "ortho" } },
];

function modeChoice(onChange) {
  const radios = MODES.map((mode, i) => h("input", {
    type: "radio", name: "mosaic-mode", id: `mode-${mode.value}`, value: mode.value, checked: i === 0,
    "data-testid": `mode-${mode.value}`,
  }));
  const node = h(
    "fieldset",
    { class: "mode-choice" },
    h("legend", {}, "Mosaic mode"),
    MODES.map((mode, i) => h("label", { class: "check", for: `mode-${mode.value}` }, radios[i], " ",
      h("span", {}, h("strong", {}, mode.label), h("span", { class: "muted" }, ` (${mode.note})`)))),
  );
  const picked = () => MODES.find((mode, i) => radios[i].checked) || MODES[0];
  for (const radio of radios) radio.addEventListener("change", () => onChange(picked().value));
  return { node, options: () => ({ ...picked().options }), value: () => picked().value };
}

/** Upload a ground control point file (ODM gcp_list.txt or OpenSfM JSON); ortho jobs use it. */
function gcpUpload(view, flightId) {
  return sideFileUpload(view, {
    key: "gcp", route: `/api/flights/${flightId}/gcps`, accept: ".txt,.json,text/plain,application/json",
    title: "Ground control points ", what: "GCP file", summary: gcpSummary,
    hint: "Used by ortho jobs to tie the map to surveyed points: ODM gcp_list.txt or OpenSfM ground_control_points.json. A new file replaces the previous one.",
  });
}

/** Upload a GPS side file (ODM geo.txt or CSV name,lat,lon,alt[,accuracy]); later jobs take its positions. */
function gpsUpload(view, flightId) {
  return sideFileUpload(view, {
    key: "gps", route: `/api/flights/${flightId}/gps`, accept: ".txt,.csv,text/plain,text/csv",
    title: "GPS from a side file ", what: "GPS file", summary: gpsSummary,
    hint: "Positions from a navigation log instead of the photos' EXIF: ODM geo.txt or a CSV name,lat,lon,alt[,accuracy]. Jobs started afterwards use it; a new file replaces the previous one.",
  });
}

/** A file control that PUTs one side file to `spec.route` and says what the server made of it. */
function sideFileUpload(view, spec) {
  const key = spec.key;
  const input = h("input", {
    id: `${key}-input`, type: "file", accept: spec.accept, class: "visually-hidden",
    "data-testid": `${key}-input`, "aria-describedby": `${key}-hint`,
  });
  const status = h("p", { class: "muted small", role: "status", "aria-live": "polite", "data-testid": `${key}-status` });
  const error = h("p", { class: "form-error", role: "alert", "data-testid": `${key}-error` });
  input.addEventListener("change", async () => {
    const file = input.files && input.files[0];
    if (!file) return;
    const form = new FormData();
    form.append("file", file, file.name);
    input.disabled = true;
    error.textContent = "";
    status.textContent = `Checking ${file.name}…`;
    try {
      const summary = await apiForm("PUT", spec.route, form);
      if (view.signal.aborted) return;
      status.textContent = spec.summary(summary || {});
    } catch (err) {
      if (view.signal.aborted) return;
      status.textContent = "";
      error.textContent = `Not stored (the previous ${spec.what}, if any, is kept): ${messageOf(err)}`;
    } finally {
      input.disabled = false;
      input.value = "";
    }
  });

  return h(
    "div",
    { class: "gcp-upload", "data-testid": `${key}-upload` },
    h("h3", {}, spec.title, h("span", { class: "muted small" }, "(optional)")),
    h("p", { id: `${key}-hint`, class: "muted small" }, spec.hint),
    h("label", { for: `${key}-input`, class: "btn small" }, `Upload ${spec.what}…`),
    input,
    status,
    error,
  );
}

function gcpSummary(s) {
  const missing = Array.isArray(s.images_not_in_flight) ? s.images_not_in_flight : [];
  const tail = missing.length ? ` Not in this flight: ${missing.join(", ")}.` : "";
  return `Stored ${s.file || "the GCP file"}: ${plural(s.points, "point")} (${s.with_position ?? "?"} with a position), `
    + `${plural(s.observations, "observation")}.${tail}`;
}

function gpsSummary(s) {
  const missing = Array.isArray(s.images_not_in_flight) ? s.images_not_in_flight : [];
  const tail = missing.length ? ` Not in this flight: ${missing.join(", ")}.` : "";
  const src = s.gps_source || {};
  return `Stored ${s.file || "the GPS file"} (${s.crs ?? "?"}): ${plural(s.fixes, "position")}; `
    + `photos with GPS from the file: ${src.side_file ?? "?"}, from EXIF: ${src.exif ?? "?"}, none: ${src.none ?? "?"}.${tail}`;
}

function jobsPanel(view, flightId, config) {
  const hint = h("p", { id: "start-hint", class: "muted small" });
  const error = h("p", { class: "form-error", role: "alert" });
  const list = h("div", { class: "job-list" }, h("p", { class: "muted" }, "Loading jobs…"));
  const start = h("button", { type: "button", class: "btn primary", "data-testid": "start-job", "aria-describedby": "start-hint", disabled: true },
    "Start mosaic");
  const form = optionsForm(config.mosaic_options, "planar");
  const mode = modeChoice((value) => form.setMode(value));
  let timer = null;
  onAbort(view.signal, () => clearTimeout(timer));

  start.addEventListener("click", async () => {
    start.disabled = true;
    error.textContent = "";
    try {
      const options = { ...mode.options(), ...form.options() };
      const job = await api("POST", "/api/jobs", { body: { flight_id: flightId, kind: JobKind.MOSAIC, options } });
      window.location.hash = `#/jobs/${job.id}`;
    } catch (err) {
      error.textContent = messageOf(err);
      start.disabled = false;
    }
  });

  async function refresh() {
    clearTimeout(timer);
    let jobs;
    try {
      jobs = await api("GET", `/api/jobs?flight_id=${flightId}`, { signal: view.signal });
    } catch (err) {
      if (!view.signal.aborted) list.replaceChildren(h("p", { class: "form-error" }, messageOf(err)));
      return;
    }
    if (view.signal.aborted) return;
    list.replaceChildren(jobItems(jobs));
    if (jobs.some((job) => ACTIVE.has(job.status))) timer = setTimeout(refresh, JOB_POLL_MS);
  }

  function setImageCount(count) {
    start.disabled = count < 2;
    hint.textContent = count < 2
      ? "Upload at least 2 overlapping photos to start a mosaic."
      : `Mosaic all ${count} photos into one map.`;
  }

  const node = h(
    "section",
    { class: "card", "aria-labelledby": "jobs-heading" },
    h("h2", { id: "jobs-heading" }, "Jobs"),
    mode.node,
    form.node,
    h("div", { class: "start-row" }, start, hint),
    error,
    gcpUpload(view, flightId),
    gpsUpload(view, flightId),
    h("h3", { class: "jobs-list-heading" }, "Jobs of this flight"),
    list,
  );
  return { node, refresh, setImageCount };
}

function jobItems(jobs) {
  if (!jobs.length) return h("p", { class: "empty" }, "No jobs yet.");
  const items = jobs
    .slice()
    .sort((a, b) => b.id - a.id)
    .map((job) =>
      h(
        "li",
        {},
        h(
          "a",
          { href: `#/jobs/${job.id}`, class: "job-item", "data-testid": "job-item" },
          h("span", { class: "job-title" }, `${humanize(job.kind)} #${job.id}`),
          statusBadge(job.status),
          h("span", { class: "muted small job-when" },
            ACTIVE.has(job.status) ? `${Math.round(job.progress || 0)} % · ${humanize(job.stage) || "waiting"}` : formatDate(job.created_at)),
        ),
      ),
    );
  return h("ul", { class: "plain" }, items);
}

/** `files` split into upload requests within the server's limits: files per request, and bytes per request
 * (with room for the multipart framing); a file alone larger than a request's limit goes alone, and the server
 * says why it refuses it. */
export function batches(files, limits) {
  const maxFiles = Math.max(1, Number(limits.max_files_per_request) || 100);
  const maxBytes = Math.max(1, (Number(limits.max_request_bytes) || 2 ** 31) * 0.95);
  const out = [];
  let current = [];
  let bytes = 0;
  for (const file of files) {
    if (current.length && (current.length >= maxFiles || bytes + file.size > maxBytes)) {
      out.push(current);
      current = [];
      bytes = 0;
    }
    current.push(file);
    bytes += file.size;
  }
  if (current.length) out.push(current);
  return out;
}
