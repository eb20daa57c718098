/* Fotoskhema viewer: flights, photo uploads, live job progress and the mosaic on a Leaflet map; crack
 * surveys of specimens under load.
 *
 * Vanilla JS with no build step. Routing is by hash (#/, #/flights/3, #/jobs/7, #/crack-surveys/new,
 * #/crack-surveys/9). Every view renders into #app with its own AbortController, whose `view.signal` is
 * aborted when the route changes: that aborts the view's requests (`api(..., { signal })`) and runs the
 * cleanups registered on it (event stream, map, timers, upload: `onAbort`); after each await a view checks
 * `view.signal.aborted` so a slow answer never draws over the next page. The pages are ES modules
 * (flights.js, flight.js, job.js, result-map.js, crack-survey.js, crack-survey-new.js with
 * crack-survey-specimen.js, mesh.js and mesh-plan.js, over lib.js and kinds.js); Leaflet is the classic
 * script loaded before them and used as the global `L`.
 */

import { ApiError, h, messageOf } from "./lib.js";
import { renderFlightList } from "./flights.js";
import { renderFlight } from "./flight.js";
import { renderJob } from "./job.js";
import { renderCrackSurvey, renderCrackSurveyList } from "./crack-survey.js";
import { renderNewCrackSurvey } from "./crack-survey-new.js";

// -- Router --------------------------------------------------------------------------------------

const routes = [
  [/^#?\/?$/, (view, root) => renderFlightList(view, root)],
  [/^#\/flights\/(\d+)$/, (view, root, m) => renderFlight(view, root, Number(m[1]))],
  [/^#\/jobs\/(\d+)$/, (view, root, m) => renderJob(view, root, Number(m[1]))],
  [/^#\/crack-surveys\/?$/, (view, root) => renderCrackSurveyList(view, root)],
  [/^#\/crack-surveys\/new$/, (view, root) => renderNewCrackSurvey(view, root)],
  [/^#\/crack-surveys\/(\d+)$/, (view, root, m) => renderCrackSurvey(view, root, Number(m[1]))],
];
let current = null; // the AbortController of the view shown

function route() {
  if (current) current.abort();
  current = new AbortController();
  const view = { signal: current.signal };
  const root = document.getElementById("app");
  root.replaceChildren();
  const hash = window.location.hash || "#/";
  for (const [pattern, render] of routes) {
    const match = hash.match(pattern);
    if (match) {
      Promise.resolve(render(view, root, match)).catch((err) => {
        if (!view.signal.aborted) renderProblem(root, err); // an aborted view's failures (its aborted requests) are not news
      });
      return;
    }
  }
  renderProblem(root, new ApiError(404, `No page at ${hash}.`));
}

function renderProblem(root, err) {
  document.title = "Problem · Fotoskhema";
  root.replaceChildren(
    h(
      "section",
      { class: "card narrow" },
      h("h1", {}, err instanceof ApiError && err.status === 404 ? "Not found" : "Something went wrong"),
      h("p", { class: "alert error", role: "alert" }, messageOf(err)),
      h("p", {}, h("a", { href: "#/" }, "Back to the flights")),
    ),
  );
}

window.addEventListener("hashchange", route);
route();
