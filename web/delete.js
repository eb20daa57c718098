/* The "Delete" button of the flight and job pages: asks first (confirm), then DELETE, then the list. */

import { api, h, messageOf } from "./lib.js";

/**
 * A danger button that, once `question` is confirmed, deletes `path` (DELETE, answered 204) and goes to the
 * route `then`; a refusal is shown in `error`. Not aborted by leaving the page: it was asked for.
 * Answers { button, error }.
 */
export function deleteControl({ label, testid, question, path, then }) {
  const error = h("p", { class: "form-error", role: "alert", "data-testid": `${testid}-error` });
  const button = h("button", { type: "button", class: "btn danger small", "data-testid": testid }, label);
  button.addEventListener("click", async () => {
    if (!window.confirm(question)) return;
    button.disabled = true;
    error.textContent = "";
    try {
      await api("DELETE", path);
      window.location.hash = then;
    } catch (err) {
      error.textContent = `Could not delete: ${messageOf(err)}`;
      button.disabled = false;
    }
  });
  return { button, error };
}
