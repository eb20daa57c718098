/* Sign-in: the form shown instead of a page when the API answers 401, the "signed in as" bar of the top bar,
 * and the sign-in link (`http://host:port/#token=fsk_...`).
 *
 * lib.js keeps the token (sessionStorage only: never a cookie, never localStorage) and sends it with every
 * request; app.js decides when the form replaces the page. A token typed into the form is checked with
 * GET /api/me before it is kept. The user's name is the server's, but it is still set as text.
 */

import { ApiError, api, h, messageOf, storeToken, storedToken } from "./lib.js";

const SWITCH_QUESTION = "This link signs in with another API token, possibly another user's account: "
  + "what you do next would be done as that user. Sign in with the link's token?";

/**
 * A sign-in link carries the token in the URL's fragment (`#token=fsk_...`, or `#/jobs/7?token=fsk_...` to
 * open a page): the browser never sends a fragment to the server. Keep the token and put the URL back
 * without it (history.replaceState: no history entry, no hashchange), so it is neither shown, bookmarked
 * nor shared by accident; the route that was left in the fragment is shown. Answers whether one was found.
 */
export function takeTokenFromUrl() {
  const fragment = window.location.hash.replace(/^#/, "");
  const cut = fragment.startsWith("token=") ? 0 : fragment.indexOf("?");
  if (cut < 0) return false;
  const params = new URLSearchParams(fragment.slice(cut === 0 ? 0 : cut + 1));
  if (!params.has("token")) return false;
  const token = (params.get("token") || "").trim();
  params.delete("token");
  const rest = params.toString();
  const hash = `#${fragment.slice(0, cut) || "/"}${rest ? `?${rest}` : ""}`;
  window.history.replaceState(window.history.state, "", `${window.location.pathname}${window.location.search}${hash}`);
  if (!token) return false;
  // A link sent by someone else must not silently sign this tab into their account (whatever is uploaded
  // next would be theirs to read): replacing the token in use needs the user's yes.
  const current = storedToken();
  if (current && current !== token && !window.confirm(SWITCH_QUESTION)) return false;
  storeToken(token);
  return true;
}

/**
 * The account part of the top bar, in `node`: "Signed in as <name>" and "Sign out", or a "Sign in" button.
 * Answers { show(user) } (user: GET /api/me's answer, or null when nobody is signed in).
 */
export function accountBar(node, { onSignIn, onSignOut }) {
  function show(user) {
    if (user && typeof user.name === "string") {
      node.replaceChildren(
        // The whole name in the tooltip: a long one is cut short in the bar.
        h("span", { class: "account-name", title: `${user.name}${user.is_admin ? " (administrator)" : ""}`, "data-testid": "signed-in-as" },
          "Signed in as ", h("strong", { "data-testid": "user-name" }, user.name)),
        h("button", { type: "button", class: "btn small topbar-btn", "data-testid": "sign-out", onclick: onSignOut }, "Sign out"),
      );
    } else {
      node.replaceChildren(
        h("button", { type: "button", class: "btn small topbar-btn", "data-testid": "sign-in-open", onclick: onSignIn }, "Sign in"),
      );
    }
  }
  return { show };
}

/**
 * The sign-in form: a token (a password field: it is a secret), checked with GET /api/me; once accepted it
 * is stored and `onSignedIn(user)` is called. `reason` says why the form is shown.
 */
export function signInForm({ reason, onSignedIn }) {
  const input = h("input", {
    id: "token-input", name: "token", type: "password", autocomplete: "off", spellcheck: "false", required: true,
    placeholder: "fsk_…", "aria-describedby": "token-hint", "data-testid": "token-input",
  });
  const error = h("p", { class: "form-error", role: "alert", "data-testid": "sign-in-error" });
  const submit = h("button", { type: "submit", class: "btn primary", "data-testid": "sign-in-submit" }, "Sign in");

  async function onSubmit(event) {
    event.preventDefault();
    error.textContent = "";
    const token = input.value.trim();
    if (!token) {
      error.textContent = "Paste your API token first.";
      input.focus();
      return;
    }
    submit.disabled = true;
    submit.textContent = "Checking…";
    try {
      const user = await api("GET", "/api/me", { token });
      storeToken(token);
      onSignedIn(user);
    } catch (err) {
      error.textContent = err instanceof ApiError && err.status === 401
        ? "That token was not accepted: it is unknown or has been revoked. Check it and try again."
        : `Could not sign in: ${messageOf(err)}`;
      submit.disabled = false;
      submit.textContent = "Sign in";
      input.select();
      input.focus();
    }
  }

  return h(
    "form",
    { class: "card narrow form sign-in", "aria-labelledby": "sign-in-heading", novalidate: true, onsubmit: onSubmit, "data-testid": "sign-in-form" },
    h("h1", { id: "sign-in-heading" }, "Sign in"),
    reason ? h("p", { class: "alert info", role: "status", "data-testid": "sign-in-reason" }, reason) : null,
    h("label", { for: "token-input" }, "API token"),
    input,
    h("p", { id: "token-hint", class: "muted small" },
      "A token starts with fsk_. The first ", h("code", {}, "fotoskhema up"), " prints the admin's; an admin makes one for you with ",
      h("code", {}, "fotoskhema users create <name>"), ". It is kept in this browser tab only, until you sign out or close the tab."),
    error,
    submit,
  );
}
