/* Fotoskhema viewer: flights, photo uploads, live job progress and the mosaic on a Leaflet map; crack
 * surveys of specimens under load.
 *
 * Vanilla JS with no build step. Routing is by hash (#/, #/flights/3, #/jobs/7, #/calibrations,
 * #/calibrations/new, #/stereo-rigs/new, #/crack-surveys/new, #/crack-surveys/9). Every view renders into #app with its own AbortController, whose `view.signal` is
 * aborted when the route changes: that aborts the view's requests (`api(..., { signal })`) and runs the
 * cleanups registered on it (event stream, map, timers, upload: `onAbort`); after each await a view checks
 * `view.signal.aborted` so a slow answer never draws over the next page. The pages are ES modules
 * (flights.js, flight.js, job.js, result-map.js, stereo-dem.js, crack-survey.js, crack-survey-new.js with
 * crack-survey-specimen.js, mesh.js and mesh-plan.js, over lib.js and kinds.js); Leaflet is the classic
 * script loaded before them and used as the global `L`.
 *
 * Sign-in (sign-in.js): a `#token=...` in the URL is kept and taken out of it before the first route. When
 * a request is answered 401 (no token, or one that was revoked), the view is stopped and the sign-in form
 * is shown in its place; once a token is accepted the route is rendered again.
 */

import { ApiError, api, forgetToken, h, messageOf, onUnauthorized, storedToken } from "./lib.js";
import { accountBar, signInForm, takeTokenFromUrl } from "./sign-in.js";
import { renderFlightList } from "./flights.js";
import { renderFlight } from "./flight.js";
import { renderJob } from "./job.js";
import { renderCrackSurvey, renderCrackSurveyList } from "./crack-survey.js";
import { renderNewCrackSurvey } from "./crack-survey-new.js";
import { renderCalibrationList, renderNewCalibration } from "./calibration-new.js";

// -- Router --------------------------------------------------------------------------------------

const routes = [
  [/^#?\/?$/, (view, root) => renderFlightList(view, root)],
  [/^#\/flights\/(\d+)$/, (view, root, m) => renderFlight(view, root, Number(m[1]))],
  [/^#\/jobs\/(\d+)$/, (view, root, m) => renderJob(view, root, Number(m[1]))],
  [/^#\/calibrations\/?$/, (view, root) => renderCalibrationList(view, root)],
  [/^#\/calibrations\/new$/, (view, root) => renderNewCalibration(view, root, false)],
  [/^#\/stereo-rigs\/new$/, (view, root) => renderNewCalibration(view, root, true)],
  [/^#\/crack-surveys\/?$/, (view, root) => renderCrackSurveyList(view, root)],
  [/^#\/crack-surveys\/new$/, (view, root) => renderNewCrackSurvey(view, root)],
  [/^#\/crack-surveys\/(\d+)$/, (view, root, m) => renderCrackSurvey(view, root, Number(m[1]))],
];
let current = null; // the AbortController of the view shown
let signIn = null; // the sign-in form, while it is shown instead of a view

function route() {
  if (current) current.abort();
  current = new AbortController();
  signIn = null;
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

// -- Sign-in -------------------------------------------------------------------------------------

const SIGN_IN_NEEDED = "Sign in with your API token to use Fotoskhema.";
const TOKEN_REFUSED = "Your token is no longer accepted (it may have been revoked): sign in again.";

const account = accountBar(document.getElementById("account"), {
  onSignIn: () => showSignIn(""),
  onSignOut: () => {
    forgetToken();
    account.show(null);
    showSignIn("You are signed out.");
  },
});

/** Stop the view and show the sign-in form in its place (once: a view's parallel requests fail together). */
function showSignIn(reason) {
  if (signIn) return;
  if (current) current.abort();
  current = null;
  document.title = "Sign in · Fotoskhema";
  signIn = signInForm({
    reason,
    onSignedIn: (user) => {
      account.show(user);
      route();
    },
  });
  document.getElementById("app").replaceChildren(signIn);
  signIn.querySelector("input").focus();
}

onUnauthorized(({ sentToken }) => {
  // An answer to a request sent before the token changed (signed in or out meanwhile) is old news.
  if (sentToken !== storedToken()) return;
  if (sentToken) forgetToken(); // refused: revoked or unknown
  account.show(null);
  showSignIn(sentToken ? TOKEN_REFUSED : SIGN_IN_NEEDED);
});

function showAccount() {
  if (!storedToken()) {
    account.show(null);
    return;
  }
  // A refused token is answered 401, which shows the sign-in form (above); nothing else to do here.
  api("GET", "/api/me").then((user) => account.show(user), () => {});
}

takeTokenFromUrl();
showAccount();
window.addEventListener("hashchange", () => {
  if (takeTokenFromUrl()) showAccount(); // a sign-in link opened in this tab: the page is not loaded again
  route();
});
route();
