/* Job page (#/jobs/<id>): live progress per stage by Server-Sent Events, cancel, then the result.
 * `renderJobPage` is the frame other job pages (the crack survey's) share: status, progress, result cards. */

import {
  ACTIVE,
  TERMINAL,
  api,
  apiUrl,
  breadcrumb,
  formatDate,
  formatSeconds,
  h,
  jobOutputs,
  jobSignature,
  messageOf,
  onAbort,
  parseJson,
  progressBar,
  signedUrl,
  statusBadge,
} from "./lib.js";
import { CALIBRATION_KINDS, showCalibration } from "./calibration.js";
import { deleteControl } from "./delete.js";
import { JobKind, JobStatus } from "./kinds.js";
import { label } from "./labels.js";
import { showQuality } from "./quality.js";
import { showResult } from "./result-map.js";
import { showStereoDem } from "./stereo-dem.js";

// -- Job page ------------------------------------------------------------------------------------

export async function renderJob(view, root, jobId) {
  const { signal } = view;
  const job = await api("GET", `/api/jobs/${jobId}`, { signal });
  if (signal.aborted) return;
  if (job.kind === JobKind.CRACK_SURVEY) {
    window.location.replace(`#/crack-surveys/${jobId}`); // its own page: map of the specimen, crack table
    return;
  }
  // Calibration and stereo DEM jobs belong to no flight: no flight to name; a stereo DEM has its own map.
  const stereo = job.kind === JobKind.STEREO_DEM;
  const calibration = !stereo && (CALIBRATION_KINDS.has(job.kind) || job.flight_id === null);
  const flight = calibration || stereo ? null : await api("GET", `/api/flights/${job.flight_id}`, { signal }).catch(() => null);
  if (signal.aborted) return;
  const result = h("section", { class: "card result", "aria-labelledby": "result-heading", hidden: true });
  const quality = h("section", { class: "card quality", "aria-labelledby": "quality-heading", "data-testid": "quality", hidden: true });
  const flightName = flight ? flight.name : `Flight ${job.flight_id}`;
  renderJobPage(view, root, job, {
    crumbs: stereo ? [["Stereo DEMs"], [`Job #${jobId}`]]
      : calibration ? [["Calibrations", "#/calibrations"], [`Job #${jobId}`]]
        : [["Flights", "#/"], [flightName, `#/flights/${job.flight_id}`], [`Job #${jobId}`]],
    cards: stereo ? [result] : [result, quality],
    listHref: calibration ? "#/calibrations" : stereo ? "#/" : `#/flights/${job.flight_id}`,
    onSucceeded: (done) => (stereo ? showStereoDem(view, done, result).catch(showLoadError(view, result, "result"))
      : showOutcome(view, done, result, quality, calibration)),
  });
}

/**
 * What every job page shows: breadcrumb, title and status, `cards` (the result, above the progress once the
 * job has succeeded: it is what one came for), then the live progress by Server-Sent Events; calls
 * `onSucceeded(job)` once, when the job has succeeded. A "Delete job" button goes to `listHref` once done.
 */
export function renderJobPage(view, root, initial, { crumbs, cards, listHref, onSucceeded }) {
  const jobId = initial.id;
  document.title = `Job ${jobId} · Fotoskhema`;
  // EventSource cannot send the token: the stream is opened with the job's signature (GET /api/jobs/<id>
  // answers it; a crack survey's record does not carry it, so it is asked for then).
  let signature = null;
  const follow = () => {
    signature = signature || (typeof initial.signature === "string" ? Promise.resolve(initial.signature)
      : jobSignature(jobId, { signal: view.signal }).catch(() => {
        signature = null; // asked for again next time; this time the stream is tried without it
        return "";
      }));
    followJob(view, jobId, update, signature);
  };
  const progress = jobProgressCard(view, jobId, (next) => update(next), follow);
  const badge = statusBadge(initial.status, { "data-testid": "job-status", role: "status", "aria-live": "polite" });
  const updated = h("span", {});
  let resultShown = false;

  function update(job) {
    badge.className = `badge large status-${job.status}`;
    badge.textContent = job.status;
    updated.textContent = formatDate(job.updated_at);
    progress.update(job);
    if (job.status === JobStatus.SUCCEEDED && !resultShown) {
      resultShown = true;
      onSucceeded(job);
    }
  }

  const deletion = deleteControl({
    label: "Delete job",
    testid: "delete-job",
    question: `Delete job #${jobId} and its results? A running job is stopped first. This cannot be undone.`,
    path: `/api/jobs/${jobId}`,
    then: listHref,
  });
  root.append(
    breadcrumb(...crumbs),
    h("div", { class: "page-head row" }, h("h1", {}, `${label("kind", initial.kind)} job #${jobId}`), badge,
      h("span", { class: "push-right" }, deletion.button)),
    deletion.error,
    h("p", { class: "muted small" }, `Created ${formatDate(initial.created_at)} · last update `, updated),
    ...cards,
    progress.node,
  );
  update(initial);
  if (!TERMINAL.has(initial.status)) follow();
}

/** A succeeded job's result: the calibration, or the mosaic map and its Quality card. */
function showOutcome(view, job, result, quality, calibration) {
  const failed = (card, what) => showLoadError(view, card, what);
  if (calibration) {
    showCalibration(view, job, result).catch(failed(result, "result"));
    return;
  }
  // One outputs request and one report for both cards; the Quality card does not wait for the map's tiles.
  const outputs = jobOutputs(job.id, { signal: view.signal });
  const report = outputs.then((list) => readReport(view, list));
  report.catch(() => {}); // each card says when it cannot read it
  showResult(view, job, result, outputs, report).catch(failed(result, "result"));
  outputs.then((list) => showQuality(view, list, quality, report)).catch(failed(quality, "quality report"));
}

/** The job's report.json from this service (null when it has none). */
function readReport(view, outputs) {
  const entry = (outputs || []).find((o) => o.name === "report.json");
  const url = entry && apiUrl(entry.url);
  return url ? api("GET", url, { signal: view.signal }) : Promise.resolve(null);
}

/** A catch handler that shows, in `card`, that `what` (e.g. "result") could not be loaded. */
export function showLoadError(view, card, what) {
  return (err) => {
    if (view.signal.aborted) return;
    card.hidden = false;
    card.replaceChildren(h("p", { class: "alert error", role: "alert" }, `Could not load the ${what}: ${messageOf(err)}`));
  };
}

/**
 * Follow a job's Server-Sent Events, opened with `signature` (a promise of the job's signature); fall back to
 * polling (with the token) if the stream keeps failing, e.g. once the signature has expired.
 */
async function followJob(view, jobId, onJob, signature) {
  const query = await signature;
  if (view.signal.aborted) return; // e.g. a refused token (401) has shown the sign-in form meanwhile
  const source = new EventSource(signedUrl(`/api/jobs/${jobId}/events`, query));
  let failures = 0;
  let timer = null;
  const handle = (event) => {
    failures = 0;
    const job = parseJson(event.data);
    if (job && !view.signal.aborted) onJob(job);
  };
  async function poll() {
    try {
      const job = await api("GET", `/api/jobs/${jobId}`, { signal: view.signal });
      if (view.signal.aborted) return;
      onJob(job);
      if (TERMINAL.has(job.status)) return;
    } catch {
      if (view.signal.aborted) return;
    }
    timer = setTimeout(poll, 2000);
  }
  source.addEventListener("progress", handle);
  source.addEventListener("end", (event) => {
    source.close();
    handle(event);
  });
  // the job was deleted (here or elsewhere) while followed: nothing more will come, and no reconnecting
  source.addEventListener("deleted", () => source.close());
  source.addEventListener("error", () => {
    // EventSource reconnects by itself after a dropped connection; only give up on it for good
    // when it is closed or keeps failing, and then read the job record instead.
    failures += 1;
    if (source.readyState === EventSource.CLOSED || failures >= 5) {
      source.close();
      if (!timer) poll();
    }
  });
  onAbort(view.signal, () => {
    source.close();
    clearTimeout(timer);
  });
}

function jobProgressCard(view, jobId, onJob, onRetried) {
  const overall = progressBar("Overall job progress", { "data-testid": "job-progress" });
  const percent = h("span", { class: "percent" });
  const detail = h("p", { class: "stage-detail", "data-testid": "job-detail" });
  const eta = h("p", { class: "muted small", "data-testid": "job-eta", hidden: true });
  const stageList = h("ol", { class: "stages", "aria-label": "Stages" });
  const error = h("div", { class: "alert error", role: "alert", "data-testid": "job-error", hidden: true });
  const cancel = h("button", { type: "button", class: "btn danger", "data-testid": "cancel-job", hidden: true }, "Cancel job");
  const retry = h("button", { type: "button", class: "btn", "data-testid": "retry-job", hidden: true }, "Retry job");
  const total = h("p", { class: "muted small" });
  let cancelling = false;

  retry.addEventListener("click", async () => {
    retry.disabled = true;
    try {
      const job = await api("POST", `/api/jobs/${jobId}/retry`); // not aborted by leaving the page: it was asked for
      if (view.signal.aborted) return;
      onJob(job);
      onRetried();
    } catch (err) {
      if (view.signal.aborted) return;
      error.hidden = false;
      error.textContent = `Could not retry: ${messageOf(err)}`;
    } finally {
      retry.disabled = false;
    }
  });

  cancel.addEventListener("click", async () => {
    cancelling = true;
    cancel.disabled = true;
    cancel.textContent = "Cancelling…";
    try {
      const job = await api("POST", `/api/jobs/${jobId}/cancel`); // not aborted by leaving the page: it was asked for
      if (!view.signal.aborted && job) onJob(job);
    } catch (err) {
      if (view.signal.aborted) return;
      error.hidden = false;
      error.textContent = `Could not cancel: ${messageOf(err)}`;
      cancelling = false;
      cancel.disabled = false;
      cancel.textContent = "Cancel job";
    }
  });

  function update(job) {
    const active = ACTIVE.has(job.status);
    const succeeded = job.status === JobStatus.SUCCEEDED;
    overall.set(succeeded ? 100 : job.progress || 0);
    overall.tone(succeeded ? "done" : job.status === JobStatus.FAILED ? "error" : job.status === JobStatus.CANCELLED ? "muted" : "");
    percent.textContent = `${Math.round(succeeded ? 100 : job.progress || 0)} %`;
    detail.textContent = stageSentence(job);
    eta.hidden = !(active && job.eta);
    eta.textContent = eta.hidden ? "" : etaSentence(job.eta);
    stageList.replaceChildren(...stageRows(job));
    error.hidden = !job.error || succeeded;
    if (!error.hidden) {
      error.replaceChildren(h("strong", {}, job.status === JobStatus.FAILED ? "Job failed: " : "Error: "), job.error);
    }
    cancel.hidden = !active;
    retry.hidden = job.status !== JobStatus.FAILED && job.status !== JobStatus.CANCELLED; // finished stages are kept
    if (!active) cancelling = false;
    if (!cancelling) {
      cancel.disabled = false;
      cancel.textContent = "Cancel job";
    }
    const seconds = Object.values(job.timings || {}).filter((v) => typeof v === "number");
    total.textContent = seconds.length ? `Total stage time ${formatSeconds(seconds.reduce((a, b) => a + b, 0))}` : "";
  }

  const node = h(
    "section",
    { class: "card", "aria-labelledby": "progress-heading" },
    h("div", { class: "row spread" }, h("h2", { id: "progress-heading" }, "Progress"), h("div", { class: "row" }, retry, cancel)),
    h("div", { class: "overall" }, overall.node, percent),
    detail,
    eta,
    error,
    stageList,
    total,
  );
  return { node, update };
}

const READY = {
  [JobKind.MOSAIC]: "the mosaic is ready",
  [JobKind.CALIBRATION]: "the camera is calibrated",
  [JobKind.STEREO_CALIBRATION]: "the rig is calibrated",
  [JobKind.CRACK_SURVEY]: "the cracks are measured",
  [JobKind.STEREO_DEM]: "the surface is ready",
};

// The state of a pipeline stage (its row's class `stage-<state>` and its text); running, failed and cancelled as the job's.
const StageState = Object.freeze({
  DONE: "done",
  RUNNING: JobStatus.RUNNING,
  PENDING: "pending",
  FAILED: JobStatus.FAILED,
  CANCELLED: JobStatus.CANCELLED,
});

function stageSentence(job) {
  const stage = job.stage ? label("stage", job.stage) : "";
  switch (job.status) {
    case JobStatus.QUEUED:
      return "Waiting for a worker…";
    case JobStatus.RUNNING:
      return [stage || "Starting", job.progress_detail].filter(Boolean).join(" — ");
    case JobStatus.SUCCEEDED:
      return `Finished: ${READY[job.kind] || "the result is ready"}.`;
    case JobStatus.CANCELLED:
      return `Cancelled${stage ? ` during ${stage.toLowerCase()}` : ""}.`;
    case JobStatus.FAILED:
      return `Failed${stage ? ` during ${stage.toLowerCase()}` : ""}.`;
    default:
      return job.status;
  }
}

/** The state of each stage, from the current stage, the status and the recorded timings. */
function stageState(job, name, index) {
  const current = (job.stages || []).indexOf(job.stage);
  const timed = Object.prototype.hasOwnProperty.call(job.timings || {}, name);
  if (job.status === JobStatus.SUCCEEDED) return StageState.DONE;
  if (index === current) {
    if (timed) return StageState.DONE;
    if (job.status === JobStatus.RUNNING) return StageState.RUNNING;
    if (job.status === JobStatus.FAILED) return StageState.FAILED;
    if (job.status === JobStatus.CANCELLED) return StageState.CANCELLED;
    return StageState.PENDING;
  }
  if (timed || (current >= 0 && index < current)) return StageState.DONE;
  return StageState.PENDING;
}

/** Fraction of the running stage from a detail like "frame 4/12"; null when it has none. */
function detailFraction(detail) {
  const m = /(\d+)\s*\/\s*(\d+)/.exec(detail || "");
  if (!m || Number(m[2]) === 0) return null;
  return (Number(m[1]) / Number(m[2])) * 100;
}

function stageRows(job) {
  const stages = job.stages && job.stages.length ? job.stages : job.stage ? [job.stage] : [];
  return stages.map((name, index) => {
    const state = stageState(job, name, index);
    const bar = progressBar(`${label("stage", name)} progress`);
    if (state === StageState.DONE) bar.set(100);
    else if (state === StageState.RUNNING) bar.set(detailFraction(job.progress_detail));
    else if (state === StageState.FAILED || state === StageState.CANCELLED) bar.set(detailFraction(job.progress_detail) ?? 0);
    else bar.set(0);
    bar.tone(state === StageState.DONE ? "done" : state === StageState.FAILED ? "error" : state === StageState.CANCELLED ? "muted" : "");
    const seconds = (job.timings || {})[name];
    const ahead = ((job.eta || {}).stages || {})[name];
    return h(
      "li",
      { class: `stage stage-${state}`, "data-stage": name },
      h("span", { class: "stage-dot", "aria-hidden": "true" }),
      h("span", { class: "stage-name" }, label("stage", name)),
      bar.node,
      h("span", { class: "stage-meta", "data-testid": `stage-meta-${name}`,
        title: ahead && ACTIVE.has(job.status) && state !== StageState.DONE ? `time left ${label("eta_basis", ahead.basis)}` : null },
      stageMeta(job, state, seconds, ahead)),
    );
  });
}

/** "About 2 min 10 s left (this step 35 s)": the job's time left from its measured rates (core/eta.py). */
function etaSentence(eta) {
  const left = roughDuration(eta.seconds_left);
  const step = eta.stage_seconds_left > 0 && eta.stage_seconds_left < eta.seconds_left
    ? ` (this step ${roughDuration(eta.stage_seconds_left)})` : "";
  return `About ${left} left${step}`;
}

/** What a stage's row says after its bar: the running stage's count, rate and time left; a finished stage's
 * time; a stage to come, its expected time; else its state. */
function stageMeta(job, state, seconds, ahead) {
  if (state === StageState.DONE && typeof seconds === "number") return formatSeconds(seconds);
  const active = ACTIVE.has(job.status) && ahead && Number.isFinite(ahead.seconds_left);
  if (state === StageState.RUNNING) {
    const parts = [job.progress_detail];
    if (active && ahead.unit && Number.isFinite(ahead.units_per_second) && ahead.units_per_second > 0) {
      parts.push(`${formatRate(ahead.units_per_second)} ${ahead.unit}s/s`);
    }
    if (active) parts.push(`${roughDuration(ahead.seconds_left)} left`);
    return parts.filter(Boolean).join(" · ") || state;
  }
  if (state === StageState.PENDING && active) return `≈ ${roughDuration(ahead.seconds_left)}`;
  return state; // the state names itself
}

/** A duration as people say it: "under 5 s", "40 s", "1 min 35 s", "12 min", "1 h 20 min". */
function roughDuration(s) {
  if (!Number.isFinite(s) || s < 5) return "under 5 s";
  if (s < 60) return `${Math.round(s / 5) * 5} s`;
  if (s < 600) {
    const fives = Math.round(s / 5) * 5;
    return fives % 60 ? `${Math.floor(fives / 60)} min ${fives % 60} s` : `${fives / 60} min`;
  }
  if (s < 3600) return `${Math.round(s / 60)} min`;
  return `${Math.floor(s / 3600)} h ${Math.round((s % 3600) / 60)} min`;
}

function formatRate(r) {
  return r >= 10 ? r.toFixed(0) : r >= 1 ? r.toFixed(1) : r.toPrecision(2);
}
