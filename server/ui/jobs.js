// Jobs: the list with progress, and one job followed live, its PNG artifacts shown inline.

import { follow, getJSON, pager } from "./api.js";
import { facts, fill, h, link, problem, tableRow, when } from "./dom.js";

const IMAGE = /\.(png|gif)$/i;

function progressBar(fraction, label) {
  return h(
    "span",
    { class: "progress" },
    h("progress", { max: "1", value: String(fraction), "aria-label": label }),
    ` ${Math.round(fraction * 100)}%`,
  );
}

function statusBadge(status) {
  return h("span", { class: `badge status-${status}` }, status);
}

export function jobList(view) {
  view.root.append(h("h1", { tabindex: "-1" }, "Jobs"));
  const rows = h("tbody");
  const headers = ["Job", "Kind", "Status", "Progress", "Message", "Queued", "Finished"];
  const list = h(
    "table",
    { class: "list", id: "job-list" },
    h("caption", {}, "Every experiment job, newest first"),
    h("thead", {}, h("tr", {}, headers.map((text) => h("th", { scope: "col" }, text)))),
    rows,
  );
  const pages = pager("/jobs", {}, (items) => {
    for (const j of items) {
      rows.append(
        tableRow([
          link(`#/jobs/${j.id}`, `Job ${j.id}`),
          j.kind,
          statusBadge(j.status),
          progressBar(j.progress, `job ${j.id} progress`),
          j.message,
          when(j.created_at),
          when(j.finished_at),
        ]),
      );
    }
  });
  view.root.append(list, pages.box);
  pages
    .load()
    .then((page) => {
      if (page.items.length === 0) list.after(h("p", {}, "No job yet: an operator queues one with POST /jobs."));
    })
    .catch((error) => view.root.append(problem(error)));
}

function artifactUrl(id, name) {
  return `/jobs/${id}/artifacts/${name.split("/").map(encodeURIComponent).join("/")}`;
}

function artifacts(id, names) {
  const images = names.filter((n) => IMAGE.test(n));
  const files = names.filter((n) => !IMAGE.test(n));
  return h(
    "section",
    { "aria-labelledby": "artifacts-heading", id: "artifacts" },
    h("h2", { id: "artifacts-heading" }, "Artifacts"),
    names.length === 0 ? h("p", {}, "This job wrote no files.") : null,
    images.map((name) => h("figure", { class: "artifact" }, h("img", { src: artifactUrl(id, name), alt: `Plot ${name}`, loading: "lazy" }), h("figcaption", {}, name))),
    files.length ? h("ul", {}, files.map((name) => h("li", {}, h("a", { href: artifactUrl(id, name) }, name)))) : null,
  );
}

export function jobView(view, id) {
  const title = h("h1", { tabindex: "-1" }, `Job ${id}`);
  const liveness = h("p", { class: "liveness", role: "status", id: "liveness" }, "Loading…");
  const state = h("div", { id: "job-state" });
  const outcome = h("div");
  view.root.append(title, liveness, state, outcome);

  function showState(job, status, progress, message) {
    fill(
      state,
      facts([
        ["Kind", job.kind],
        ["Status", statusBadge(status)],
        ["Progress", progressBar(progress, "job progress")],
        ["Message", message],
        ["Parameters", Object.entries(job.params).map(([k, v]) => `${k} = ${JSON.stringify(v)}`).join(", ") || "defaults"],
        ["Queued", when(job.created_at)],
      ]),
    );
  }

  getJSON(`/jobs/${id}`)
    .then((job) => {
      fill(title, `Job ${id}: ${job.kind}`);
      showState(job, job.status, job.progress, job.message);
      const stop = follow(
        `/jobs/${id}/events`,
        {
          progress: (p) => showState(job, p.status, p.progress, p.message),
          end: (done) => {
            showState(done, done.status, done.progress, done.message);
            liveness.textContent = `Ended: ${done.status} at ${when(done.finished_at)}.`;
            fill(
              outcome,
              done.error ? h("section", {}, h("h2", {}, "Error"), h("pre", { class: "error" }, done.error)) : null,
              artifacts(id, done.artifacts),
              done.result ? h("section", {}, h("h2", {}, "Result"), h("details", {}, h("summary", {}, "The result as JSON (the CLI's --json object)"), h("pre", {}, JSON.stringify(done.result, null, 2)))) : null,
            );
          },
        },
        (s) => {
          if (s === "live") liveness.textContent = "Following live.";
          if (s === "waiting") liveness.textContent = "Connection lost; resuming…";
        },
      );
      view.onLeave(stop);
    })
    .catch((error) => liveness.replaceWith(problem(error)));
}
