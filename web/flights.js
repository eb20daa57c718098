/* Flights list page (#/): every flight with its recent jobs, and the form to create one. */

import { api, formatDate, h, humanize, messageOf, statusBadge } from "./lib.js";

// -- Flights list --------------------------------------------------------------------------------

export async function renderFlightList(view, root) {
  document.title = "Flights · Fotoskhema";
  const listBody = h("div", { class: "card-body" }, h("p", { class: "muted" }, "Loading flights…"));
  root.append(
    h(
      "div",
      { class: "page-head" },
      h("h1", {}, "Flights"),
      h("p", { class: "muted" }, "Upload the photos of a drone flight, then run a mosaic job to get a map. ",
        "Measuring the cracks of a specimen under load? ",
        h("a", { href: "#/crack-surveys/new", "data-testid": "start-crack-survey" }, "Start a crack survey"), "."),
    ),
    h(
      "div",
      { class: "layout sidebar-right" },
      h("section", { class: "card", "aria-labelledby": "flights-heading" }, h("h2", { id: "flights-heading" }, "All flights"), listBody),
      createFlightForm(),
    ),
  );
  const { signal } = view;
  const flights = await api("GET", "/api/flights", { signal });
  if (signal.aborted) return;
  const jobLists = await Promise.all(
    flights.map((f) => api("GET", `/api/jobs?flight_id=${f.id}`, { signal }).catch(() => [])),
  );
  if (signal.aborted) return;
  listBody.replaceChildren(
    flights.length
      ? flightTable(flights, jobLists)
      : h("p", { class: "empty" }, "No flights yet. Create one with the form to start uploading photos."),
  );
}

function flightTable(flights, jobLists) {
  const rows = flights
    .map((flight, i) => [flight, jobLists[i] || []])
    .sort((a, b) => b[0].id - a[0].id)
    .map(([flight, jobs]) =>
      h(
        "tr",
        { "data-testid": "flight-row" },
        h(
          "td",
          {},
          h("a", { class: "strong", href: `#/flights/${flight.id}` }, flight.name),
          flight.description ? h("div", { class: "muted small clamp" }, flight.description) : null,
        ),
        h("td", { class: "num" }, String(flight.image_count ?? 0)),
        h("td", { class: "nowrap" }, formatDate(flight.created_at)),
        h("td", {}, jobBadges(jobs)),
      ),
    );
  return h(
    "table",
    { class: "table flights" },
    h("caption", { class: "visually-hidden" }, "Flights with their photo counts and jobs"),
    h(
      "thead",
      {},
      h("tr", {}, h("th", { scope: "col" }, "Flight"), h("th", { scope: "col", class: "num" }, "Photos"),
        h("th", { scope: "col" }, "Created"), h("th", { scope: "col" }, "Jobs")),
    ),
    h("tbody", {}, rows),
  );
}

function jobBadges(jobs) {
  if (!jobs.length) return h("span", { class: "muted small" }, "none");
  const recent = jobs.slice().sort((a, b) => b.id - a.id).slice(0, 4);
  const links = recent.map((job) =>
    h("a", { class: "job-chip", href: `#/jobs/${job.id}`, title: `${humanize(job.kind)} job ${job.id}: ${job.status}` },
      `#${job.id}`, statusBadge(job.status)),
  );
  if (jobs.length > recent.length) links.push(h("span", { class: "muted small" }, `+${jobs.length - recent.length} more`));
  return h("div", { class: "chips" }, links);
}

function createFlightForm() {
  const name = h("input", {
    id: "flight-name", name: "name", type: "text", maxlength: 200, autocomplete: "off", required: true,
    placeholder: "e.g. Quarry, north face", "data-testid": "flight-name-input",
  });
  const description = h("textarea", { id: "flight-description", name: "description", rows: 3 });
  const error = h("p", { class: "form-error", role: "alert" });
  const submit = h("button", { type: "submit", class: "btn primary", "data-testid": "create-flight" }, "Create flight");
  async function onSubmit(event) {
    event.preventDefault();
    error.textContent = "";
    const value = name.value.trim();
    if (!value) {
      error.textContent = "Give the flight a name.";
      name.focus();
      return;
    }
    submit.disabled = true;
    try {
      const flight = await api("POST", "/api/flights", { body: { name: value, description: description.value.trim() } });
      window.location.hash = `#/flights/${flight.id}`;
    } catch (err) {
      error.textContent = messageOf(err);
      submit.disabled = false;
    }
  }
  const form = h(
    "form",
    { class: "card form", "aria-labelledby": "new-flight-heading", novalidate: true, onsubmit: onSubmit },
    h("h2", { id: "new-flight-heading" }, "New flight"),
    h("label", { for: "flight-name" }, "Name"),
    name,
    h("label", { for: "flight-description" }, "Description ", h("span", { class: "muted" }, "(optional)")),
    description,
    error,
    submit,
  );
  return form;
}
