/* Job page (#/jobs/<id>): live progress per stage by Server-Sent Events, cancel, then the result.
 * `renderJobPage` is the frame other job pages (the crack survey's) share: status, progress, result cards. */

import {
  ACTIVE,
  TERMINAL,
  api,
  breadcrumb,
  formatDate,
  formatSeconds,
  h,
  humanize,
  messageOf,
  parseJson,
  progressBar,
  statusBadge,
} from "./lib.js";
import { CALIBRATION_KINDS, showCalibration } from "./calibration.js";
import { showQuality } from "./quality.js";
import { showResult } from "./result-map.js";

export const CRACK_SURVEY_KIND = "crack_survey";

// -- Job page ------------------------------------------------------------------------------------

export async function renderJob(view, root, jobId) {
  const job = await api("GET", `/api/jobs/${jobId}`);
  if (!view.alive) return;
  if (job.kind === CRACK_SURVEY_KIND) {
    window.location.replace(`#/crack-surveys/${jobId}`); // its own page: map of the specimen, crack table
    return;
  }
  // Calibration jobs belong to no flight: no flight to name, no tiles to show.
  const calibration = CALIBRATION_KINDS.has(job.kind) || job.flight_id === null;
  const flight = calibration ? null : await api("GET", `/api/flights/${job.flight_id}`).catch(() => null);
  if (!view.alive) return;
  const result = h("section", { class: "card result", "aria-labelledby": "result-heading", hidden: true });
  const quality = h("section", { class: "card quality", "aria-labelledby": "quality-heading", "data-testid": "quality", hidden: true });
  const flightName = flight ? flight.name : `Flight ${job.flight_id}`;
  renderJobPage(view, root, job, {
    crumbs: calibration
      ? [["Calibrations"], [`Job #${jobId}`]]
      : [["Flights", "#/"], [flightName, `#/flights/${job.flight_id}`], [`Job #${jobId}`]],
    cards: [result, quality],
    onSucceeded: (done) => showOutcome(view, done, result, quality, calibration),
  });
}

/**
 * What every job page shows: breadcrumb, title and status, `cards` (the result, above the progress once the
 * job has succeeded: it is what one came for), then the live progress by Server-Sent Events; calls
 * `onSucceeded(job)` once, when the job has succeeded.
 */
export function renderJobPage(view, root, initial, { crumbs, cards, onSucceeded }) {
  const jobId = initial.id;
  document.title = `Job ${jobId} · Fotoskhema`;
  const progress = jobProgressCard(view, jobId, (next) => update(next), () => followJob(view, jobId, update));
  const badge = statusBadge(initial.status, { "data-testid": "job-status", role: "status", "aria-live": "polite" });
  const updated = h("span", {});
  let resultShown = false;

  function update(job) {
    badge.className = `badge large status-${job.status}`;
    badge.textContent = job.status;
    updated.textContent = formatDate(job.updated_at);
    progress.update(job);
    if (job.status === "succeeded" && !resultShown) {
      resultShown = true;
      onSucceeded(job);
    }
  }

  root.append(
    breadcrumb(...crumbs),
    h("div", { class: "page-head row" }, h("h1", {}, `${humanize(initial.kind)} job #${jobId}`), badge),
    h("p", { class: "muted small" }, `Created ${formatDate(initial.created_at)} · last update `, updated),
    ...cards,
    progress.node,
  );
  update(initial);
  if (!TERMINAL.has(initial.status)) followJob(view, jobId, update);
}

/** A succeeded job's result: the calibration, or the mosaic map and its Quality card. */
function showOutcome(view, job, result, quality, calibration) {
  const failed = (card, what) => showLoadError(view, card, what);
  if (calibration) {
    showCalibration(view, job, result).catch(failed(result, "result"));
    return;
  }
  // One outputs request for both cards; the Quality card does not wait for the map's tiles.
  const outputs = api("GET", `/api/jobs/${job.id}/outputs`).then((data) => (data && data.outputs) || []);
  showResult(view, job, result, outputs).catch(failed(result, "result"));
  outputs.then((list) => showQuality(view, list, quality)).catch(failed(quality, "quality report"));
}

/** A catch handler that shows, in `card`, that `what` (e.g. "result") could not be loaded. */
export function showLoadError(view, card, what) {
  return (err) => {
    if (!view.alive) return;
    card.hidden = false;
    card.replaceChildren(h("p", { class: "alert error", role: "alert" }, `Could not load the ${what}: ${messageOf(err)}`));
  };
}

/** Follow a job's Server-Sent Events; fall back to polling if the stream keeps failing. */
function followJob(view, jobId, onJob) {
  const source = new EventSource(`/api/jobs/${jobId}/events`);
  let failures = 0;
  let timer = null;
  const handle = (event) => {
    failures = 0;
    const job = parseJson(event.data);
    if (job && view.alive) onJob(job);
  };
  async function poll() {
    try {
      const job = await api("GET", `/api/jobs/${jobId}`);
      if (!view.alive) return;
      onJob(job);
      if (TERMINAL.has(job.status)) return;
    } catch (_err) {
      if (!view.alive) return;
    }
    timer = setTimeout(poll, 2000);
  }
  source.addEventListener("progress", handle);
  source.addEventListener("end", (event) => {
    source.close();
    handle(event);
  });
  source.addEventListener("error", () => {
    // EventSource reconnects by itself after a dropped connection; only give up on it for good
    // when it is closed or keeps failing, and then read the job record instead.
    failures += 1;
    if (source.readyState === EventSource.CLOSED || failures >= 5) {
      source.close();
      if (!timer) poll();
    }
  });
  view.cleanups.push(() => {
    source.close();
    clearTimeout(timer);
  });
}

function jobProgressCard(view, jobId, onJob, onRetried) {
  const overall = progressBar("Overall job progress", { "data-testid": "job-progress" });
  const percent = h("span", { class: "percent" });
  const detail = h("p", { class: "stage-detail", "data-testid": "job-detail" });
  const stageList = h("ol", { class: "stages", "aria-label": "Stages" });
  const error = h("div", { class: "alert error", role: "alert", "data-testid": "job-error", hidden: true });
  const cancel = h("button", { type: "button", class: "btn danger", "data-testid": "cancel-job", hidden: true }, "Cancel job");
  const retry = h("button", { type: "button", class: "btn", "data-testid": "retry-job", hidden: true }, "Retry job");
  const total = h("p", { class: "muted small" });
  let cancelling = false;

  retry.addEventListener("click", async () => {
    retry.disabled = true;
    try {
      const job = await api("POST", `/api/jobs/${jobId}/retry`);
      if (!view.alive) return;
      onJob(job);
      onRetried();
    } catch (err) {
      if (!view.alive) return;
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
      const job = await api("POST", `/api/jobs/${jobId}/cancel`);
      if (view.alive && job) onJob(job);
    } catch (err) {
      if (!view.alive) return;
      error.hidden = false;
      error.textContent = `Could not cancel: ${messageOf(err)}`;
      cancelling = false;
      cancel.disabled = false;
      cancel.textContent = "Cancel job";
    }
  });

  function update(job) {
    const active = ACTIVE.has(job.status);
    overall.set(job.status === "succeeded" ? 100 : job.progress || 0);
    overall.tone(job.status === "succeeded" ? "done" : job.status === "failed" ? "error" : job.status === "cancelled" ? "muted" : "");
    percent.textContent = `${Math.round(job.status === "succeeded" ? 100 : job.progress || 0)} %`;
    detail.textContent = stageSentence(job);
    stageList.replaceChildren(...stageRows(job));
    error.hidden = !job.error || job.status === "succeeded";
    if (!error.hidden) {
      error.replaceChildren(h("strong", {}, job.status === "failed" ? "Job failed: " : "Error: "), job.error);
    }
    cancel.hidden = !active;
    retry.hidden = job.status !== "failed" && job.status !== "cancelled"; // finished stages are kept
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
    error,
    stageList,
    total,
  );
  return { node, update };
}

const READY = {
  mosaic: "the mosaic is ready",
  calibration: "the camera is calibrated",
  stereo_calibration: "the rig is calibrated",
  crack_survey: "the cracks are measured",
};

function stageSentence(job) {
  const stage = job.stage ? humanize(job.stage) : "";
  switch (job.status) {
    case "queued":
      return "Waiting for a worker…";
    case "running":
      return [stage || "Starting", job.progress_detail].filter(Boolean).join(" — ");
    case "succeeded":
      return `Finished: ${READY[job.kind] || "the result is ready"}.`;
    case "cancelled":
      return `Cancelled${stage ? ` during ${stage.toLowerCase()}` : ""}.`;
    case "failed":
      return `Failed${stage ? ` during ${stage.toLowerCase()}` : ""}.`;
    default:
      return job.status;
  }
}

/** The state of each stage, from the current stage, the status and the recorded timings. */
function stageState(job, name, index) {
  const current = (job.stages || []).indexOf(job.stage);
  const timed = Object.prototype.hasOwnProperty.call(job.timings || {}, name);
  if (job.status === "succeeded") return "done";
  if (index === current) {
    if (timed) return "done";
    if (job.status === "running") return "running";
    if (job.status === "failed" || job.status === "cancelled") return job.status;
    return "pending";
  }
  if (timed || (current >= 0 && index < current)) return "done";
  return "pending";
}

/** Fraction of the running stage from a detail like "frame 4/12"; null when it has none. */
function detailFraction(detail) {
  const m = /(\d+)\s*\/\s*(\d+)/.exec(detail || "");
  if (!m || Number(m[2]) === 0) return null;
  return (Number(m[1]) / Number(m[2])) * 100;
}

function stageRows(job) {
  const stages = job.stages && job.stages.length ? job.stages : job.stage ? [job.stage] : [];
  const labels = { done: "done", running: "running", pending: "pending", failed: "failed", cancelled: "cancelled" };
  return stages.map((name, index) => {
    const state = stageState(job, name, index);
    const bar = progressBar(`${humanize(name)} progress`);
    if (state === "done") bar.set(100);
    else if (state === "running") bar.set(detailFraction(job.progress_detail));
    else if (state === "failed" || state === "cancelled") bar.set(detailFraction(job.progress_detail) ?? 0);
    else bar.set(0);
    bar.tone(state === "done" ? "done" : state === "failed" ? "error" : state === "cancelled" ? "muted" : "");
    const seconds = (job.timings || {})[name];
    return h(
      "li",
      { class: `stage stage-${state}`, "data-stage": name },
      h("span", { class: "stage-dot", "aria-hidden": "true" }),
      h("span", { class: "stage-name", title: name }, humanize(name)),
      bar.node,
      h("span", { class: "stage-meta" },
        state === "running" && job.progress_detail ? job.progress_detail : state === "done" && typeof seconds === "number" ? formatSeconds(seconds) : labels[state]),
    );
  });
}
