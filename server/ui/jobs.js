// Jobs: the list (filtered, sorted, jobs picked for comparison), one job followed live and then
// read at a glance (headline cards, tables, figures; the raw JSON collapsed), and jobs compared.

import { ApiError, firstRead, follow, getJSON, keepCurrent, pager } from "./api.js";
import { facts, fill, h, link, notFound, problem, scrolling, tableRow, when } from "./dom.js";
import { card, headline, kindLayouts, lineChart, rowsTable, shown, splitColumns, tablesOf, words } from "./results.js";

const IMAGE = /\.(png|gif)$/i;
const STATUSES = ["queued", "running", "succeeded", "failed", "cancelled"];
const FINISHED = ["succeeded", "failed", "cancelled"];

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

function select(id, label, options, value) {
  return h(
    "label",
    { for: id },
    `${label} `,
    h("select", { id }, options.map(([v, text]) => h("option", { value: v, selected: v === value }, text))),
  );
}

export function jobList(view, query) {
  view.root.append(h("h1", { tabindex: "-1" }, "Jobs"));
  const chosen = { status: query.get("status") || "", kind: query.get("kind") || "", order: query.get("order") || "newest" };
  if (chosen.status && !STATUSES.includes(chosen.status)) {
    view.root.append(problem(`No job status is called "${chosen.status}": pick one of the list.`), link("#/jobs", "All jobs"));
    return;
  }
  const picked = new Map(); // job id -> kind
  const compare = h("button", { type: "button", id: "compare", disabled: true }, "Compare selected");
  const note = h("span", { id: "compare-note", role: "status" }, "Select two or more jobs of one kind.");
  const form = h(
    "form",
    { class: "filters", id: "job-filters", "aria-label": "Filter and sort the jobs" },
    select("filter-status", "Status", [["", "any"], ...STATUSES.map((s) => [s, s])], chosen.status),
    select("filter-kind", "Kind", [["", "any"]], chosen.kind),
    select("filter-order", "Order", [["newest", "newest first"], ["oldest", "oldest first"]], chosen.order),
    h("button", { type: "submit" }, "Apply"),
    compare,
    note,
  );
  kindLayouts().then((kinds) => {
    const kind = form.querySelector("#filter-kind");
    for (const name of Object.keys(kinds)) kind.append(h("option", { value: name, selected: name === chosen.kind }, name));
  });
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    const params = new URLSearchParams();
    for (const name of ["status", "kind", "order"]) {
      const value = form.querySelector(`#filter-${name}`).value;
      if (value && !(name === "order" && value === "newest")) params.set(name, value);
    }
    location.hash = `#/jobs${params.toString() ? `?${params}` : ""}`;
  });
  function updateCompare() {
    const kinds = new Set(picked.values());
    compare.disabled = picked.size < 2 || kinds.size !== 1;
    note.textContent = kinds.size > 1 ? "The selected jobs are of different kinds." : picked.size < 2 ? "Select two or more jobs of one kind." : `${picked.size} ${[...kinds][0]} jobs selected.`;
  }
  compare.addEventListener("click", () => {
    location.hash = `#/jobs/compare?ids=${[...picked.keys()].sort((a, b) => a - b).join(",")}`;
  });
  // The filter in words, for the caption and for a list it leaves empty.
  const filterWords = [chosen.status && `status ${chosen.status}`, chosen.kind && `kind ${chosen.kind}`].filter(Boolean).join(", ");
  const rows = h("tbody");
  const headers = ["Compare", "Job", "Kind", "Status", "Progress", "Message", "Queued", "Finished"];
  const list = h(
    "table",
    { class: "list", id: "job-list" },
    h("caption", {}, `Experiment jobs${filterWords ? ` (${filterWords})` : ""}, ${chosen.order} first`),
    h("thead", {}, h("tr", {}, headers.map((text) => h("th", { scope: "col" }, text)))),
    rows,
  );
  const params = { status: chosen.status, kind: chosen.kind, order: chosen.order === "newest" ? "" : chosen.order };
  const jobRow = (j) => {
    const box = h("input", { type: "checkbox", "aria-label": `Select job ${j.id} for comparison`, "data-job": j.id });
    box.checked = picked.has(j.id); // a row redrawn as its job moves keeps its selection
    box.addEventListener("change", () => {
      if (box.checked) picked.set(j.id, j.kind);
      else picked.delete(j.id);
      updateCompare();
    });
    return tableRow(
      [
        box,
        link(`#/jobs/${j.id}`, `Job ${j.id}`),
        j.kind,
        statusBadge(j.status),
        progressBar(j.progress, `job ${j.id} progress`),
        j.message,
        when(j.created_at),
        when(j.finished_at),
      ],
      { "data-id": j.id, "data-status": j.status },
    );
  };
  const none = h(
    "p",
    { class: "none-yet", id: "no-jobs", hidden: true },
    filterWords ? `None matches this filter (${filterWords}).` : "None yet: an operator queues a job with POST /jobs.",
  );
  // As the auctions list: the first page is read again every few seconds while the tab is
  // shown, jobs move on in place and (newest first) new ones are offered by a button above the
  // rows, added at the top when it is pressed.
  const newestFirst = chosen.order === "newest";
  const current = keepCurrent(view, { path: "/jobs", params, newestFirst, rows, rowFor: jobRow, noun: "jobs", empty: none });
  const pages = pager("/jobs", params, current.add);
  view.root.append(form, current.news, scrolling(list, "Experiment jobs (scrolls sideways)"), none, pages.box);
  pages
    .load()
    .then(() => current.read())
    .catch((error) => {
      // a kind the server does not run (the list of kinds is the server's): said as a status is
      const unknownKind = error instanceof ApiError && error.status === 422 && chosen.kind;
      view.root.append(problem(unknownKind ? `No job kind is called "${chosen.kind}": pick one of the list.` : error));
    });
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
    h("h2", { id: "artifacts-heading" }, "Figures and files"),
    names.length === 0 ? h("p", { class: "none-yet" }, "None.") : null,
    images.map((name) => h("figure", { class: "artifact" }, h("img", { src: artifactUrl(id, name), alt: `Plot ${name}`, loading: "lazy" }), h("figcaption", {}, name))),
    files.length ? h("ul", {}, files.map((name) => h("li", {}, h("a", { href: artifactUrl(id, name) }, name)))) : null,
  );
}

/** A finished job's result at a glance: headline cards, then its tables. */
function resultAtAGlance(result, layout) {
  const names = headline(result, layout);
  const tables = tablesOf(result, layout);
  return [
    h(
      "section",
      { "aria-labelledby": "headline-heading" },
      h("h2", { id: "headline-heading" }, "Headline numbers"),
      names.length ? h("dl", { class: "cards-row", id: "headline" }, names.map((n) => card(n, result[n]))) : h("p", { class: "none-yet" }, "None yet."),
    ),
    h(
      "section",
      { "aria-labelledby": "tables-heading", id: "result-tables" },
      h("h2", { id: "tables-heading" }, "Tables"),
      tables.length ? tables.map((t) => rowsTable(t)) : h("p", { class: "none-yet" }, "This result has no table."),
    ),
  ];
}

function parameters(params) {
  return Object.entries(params).map(([k, v]) => `${k} = ${JSON.stringify(v)}`).join(", ") || "defaults";
}

export function jobView(view, id) {
  const title = h("h1", { tabindex: "-1" }, `Job ${id}`);
  const liveness = h("p", { class: "liveness", role: "status", id: "liveness" }, "Loading…");
  const state = h("div", { id: "job-state" });
  const outcome = h("div", { id: "job-outcome" }, h("p", { class: "none-yet" }, "No result yet."));
  view.root.append(title, liveness, state, outcome);

  function showState(job, status, progress, message) {
    fill(
      state,
      facts([
        ["Kind", job.kind],
        ["Status", statusBadge(status)],
        ["Progress", progressBar(progress, "job progress")],
        ["Message", message],
        ["Parameters", parameters(job.params)],
        ["Queued", when(job.created_at)],
        // A job seen queued, then running, had its start read before it: the end tells it.
        ["Started", job.started_at ? when(job.started_at) : status === "queued" ? "not yet" : "—"],
        ...(job.finished_at ? [["Ended", when(job.finished_at)]] : []),
      ]),
    );
  }

  // Read until it can be (a server out of reach for a while, say), then followed live.
  firstRead(view, () => Promise.all([getJSON(`/jobs/${id}`), kindLayouts()]), {
    at: liveness,
    missing: () => notFound(view.root, `Job ${id}`, ["#/jobs", "All jobs"]),
    use: ([job, kinds]) => {
      fill(title, `Job ${id}: ${job.kind}`);
      showState(job, job.status, job.progress, job.message);
      const ended = (done) => {
        showState(done, done.status, done.progress, done.message);
        liveness.textContent = `Ended: ${done.status} at ${when(done.finished_at)}.`;
        fill(
          outcome,
          done.error ? h("section", {}, h("h2", {}, "Error"), h("pre", { class: "error" }, done.error)) : null,
          done.result ? resultAtAGlance(done.result, kinds[done.kind]) : null,
          artifacts(id, done.artifacts),
          done.result ? h("section", {}, h("h2", {}, "Result"), h("details", {}, h("summary", {}, "The result as JSON (the CLI's --json object)"), h("pre", {}, JSON.stringify(done.result, null, 2)))) : null,
        );
      };
      const stream = follow(
        `/jobs/${id}/events`,
        { progress: (p) => showState(job, p.status, p.progress, p.message), end: ended },
        (s) => {
          if (s === "live") liveness.textContent = "Following live.";
          if (s === "connecting") liveness.textContent = "Connecting to live updates…";
          if (s === "waiting") liveness.textContent = "Connection lost; resuming…";
          if (s === "paused") liveness.textContent = "Paused while this tab is hidden; it resumes when shown.";
          if (s !== "refused") return;
          // No stream to be had (too many open from this address, say): read the job instead.
          liveness.textContent = `The server refused live updates; the job as read at ${new Date().toLocaleTimeString()}, read again every few seconds.`;
          getJSON(`/jobs/${id}`)
            .then((now) => {
              if (FINISHED.includes(now.status)) {
                stream.stop();
                ended(now);
              } else {
                showState(now, now.status, now.progress, now.message);
              }
            })
            .catch(() => {});
        },
      );
      view.onLeave(stream.stop);
    },
  });
}

/** Parameters side by side, one column per job; rows where the jobs differ are marked. */
function parameterTable(jobs) {
  const names = [...new Set(jobs.flatMap((j) => Object.keys(j.params)))].sort();
  const rows = names.map((name) => {
    const values = jobs.map((j) => (name in j.params ? JSON.stringify(j.params[name]) : "default"));
    const differs = new Set(values).size > 1;
    return h(
      "tr",
      { class: differs ? "differs" : null, "data-param": name },
      h("th", { scope: "row" }, name),
      values.map((v) => h("td", {}, v)),
      h("td", {}, differs ? "differs" : "same"),
    );
  });
  return h(
    "table",
    { class: "list", id: "compare-params" },
    h("caption", {}, "Parameters (rows where the jobs differ are marked)"),
    h("thead", {}, h("tr", {}, h("th", { scope: "col" }, "Parameter"), jobs.map((j) => h("th", { scope: "col" }, `Job ${j.id}`)), h("th", { scope: "col" }, "Across jobs"))),
    h("tbody", {}, rows.length ? rows : h("tr", {}, h("td", { colspan: jobs.length + 2 }, "Every job ran on the defaults."))),
  );
}

function rowKey(row, keys) {
  return keys.map((k) => `${words(k).toLowerCase()} ${shown(k, row[k])}`).join(", ");
}

/** One table of every job, rows matched on their key columns; each measure per job and its
 * change from the first job. */
function diffTable(name, specs, jobs) {
  const spec = specs.find((s) => s);
  const { keys, measures } = splitColumns(spec.rows, spec.scanned);
  const byKey = specs.map((s) => new Map((s ? s.rows : []).map((r) => [rowKey(r, keys), r])));
  const order = [...new Set(byKey.flatMap((m) => [...m.keys()]))];
  const head = [h("th", { scope: "col" }, "Row")];
  for (const m of measures) {
    jobs.forEach((j, i) => head.push(h("th", { scope: "col" }, `${words(m)}, job ${j.id}${i ? " (Δ)" : ""}`)));
  }
  const body = order.map((key) =>
    h(
      "tr",
      { "data-row": key },
      h("th", { scope: "row" }, key || "all"),
      measures.flatMap((m) =>
        jobs.map((_, i) => {
          const value = byKey[i].get(key)?.[m];
          const base = byKey[0].get(key)?.[m];
          if (i === 0 || typeof value !== "number" || typeof base !== "number") return h("td", {}, shown(m, value));
          const delta = value - base;
          const sign = delta > 0 ? "+" : delta < 0 ? "\u2212" : "±";
          // a value that differs from the first job's is printed apart from it (5 | 5 would not say)
          let digits = 4;
          while (delta !== 0 && digits < 12 && Number(value.toPrecision(digits)) === Number(base.toPrecision(digits))) digits += 1;
          const text = digits > 4 ? String(Number(value.toPrecision(digits))) : shown(m, value);
          return h("td", { class: delta > 0 ? "delta-up" : delta < 0 ? "delta-down" : null, "data-delta": delta }, `${text} (${sign}${shown(m, Math.abs(delta))})`);
        }),
      ),
    ),
  );
  return scrolling(
    h("table", { class: "list", "data-diff": name }, h("caption", {}, `${spec.caption}: job against job (Δ from job ${jobs[0].id})`), h("thead", {}, h("tr", {}, head)), h("tbody", {}, body)),
    `${spec.caption}: job against job (scrolls)`,
    true,
  );
}

/** Each table's main outcome (its first mean or accuracy) against its first numeric key, one
 * line per job (and setting). */
function overlay(name, specs, jobs, index) {
  const spec = specs.find((s) => s);
  const { keys, measures } = splitColumns(spec.rows, spec.scanned);
  const x = keys.find((k) => spec.rows.every((r) => typeof r[k] === "number"));
  const numeric = measures.filter((m) => spec.rows.some((r) => typeof r[m] === "number"));
  const y = numeric.find((m) => /^(mean|accuracy)/.test(m)) || numeric[0]; // an outcome, not a count
  if (!x || !y) return null;
  const others = keys.filter((k) => k !== x);
  const lines = [];
  specs.forEach((s, i) => {
    const groups = new Map();
    for (const row of s ? s.rows : []) {
      const group = rowKey(row, others);
      if (!groups.has(group)) groups.set(group, []);
      groups.get(group).push([row[x], typeof row[y] === "number" ? row[y] : NaN]);
    }
    for (const [group, points] of groups) lines.push({ label: `job ${jobs[i].id}${group ? `, ${group}` : ""}`, points });
  });
  return lineChart(lines, x, y, `overlay-${index}`, words(name));
}

export function compareView(view, query) {
  const asked = (query.get("ids") || "").split(",").map((s) => s.trim()).filter(Boolean);
  const ids = [...new Set(asked.filter((s) => /^\d+$/.test(s)).map(Number))];
  const unread = [...new Set(asked.filter((s) => !/^\d+$/.test(s)))];
  view.root.append(h("h1", { tabindex: "-1" }, `Compare jobs ${ids.join(", ")}`));
  // An id that is not a job's number is left out, and said so.
  if (unread.length) view.root.append(h("p", { class: "problem", id: "compare-unread" }, `Not understood, left out: ${unread.map((s) => `"${s}"`).join(", ")} (a job's id is a number).`));
  if (ids.length < 2) {
    view.root.append(h("p", { class: "problem" }, "Name two or more jobs: #/jobs/compare?ids=3,5."), link("#/jobs", "All jobs"));
    return;
  }
  const body = h("div", { id: "comparison" }, h("p", { class: "liveness" }, "Loading…"));
  view.root.append(body);
  Promise.all([Promise.all(ids.map((i) => getJSON(`/jobs/${i}`))), kindLayouts()])
    .then(([jobs, kinds]) => {
      const kindsSeen = new Set(jobs.map((j) => j.kind));
      if (kindsSeen.size > 1) {
        fill(body, h("p", { class: "problem" }, `These jobs are of different kinds (${[...kindsSeen].join(", ")}); compare jobs of one kind.`));
        return;
      }
      const layout = kinds[jobs[0].kind];
      const results = jobs.map((j) => j.result || {});
      const names = [...new Set(results.flatMap((r) => tablesOf(r, layout).map((t) => t.name)))];
      const sections = names.map((name, index) => {
        const specs = results.map((r) => tablesOf(r, layout).find((t) => t.name === name) || null);
        return h("section", { "aria-label": words(name) }, h("h3", {}, specs.find((s) => s).caption), overlay(name, specs, jobs, index), diffTable(name, specs, jobs));
      });
      const heads = [...new Set(results.flatMap((r) => headline(r, layout)))];
      // Jobs still to run may yet have results; ended ones never will.
      const none = jobs.every((j) => ["succeeded", "failed", "cancelled"].includes(j.status)) ? "None" : "None yet";
      fill(
        body,
        h("p", {}, `${jobs.length} ${jobs[0].kind} jobs: `, jobs.map((j, i) => [i ? ", " : "", link(`#/jobs/${j.id}`, `job ${j.id}`), ` (${j.status})`]), ". Share this view by its address."),
        h("section", { "aria-labelledby": "params-heading" }, h("h2", { id: "params-heading" }, "Parameters"), scrolling(parameterTable(jobs), "Parameters (scrolls sideways)")),
        h(
          "section",
          { "aria-labelledby": "heads-heading" },
          h("h2", { id: "heads-heading" }, "Headline numbers"),
          heads.length
            ? h("table", { class: "list", id: "compare-headline" }, h("caption", {}, "Headline numbers of each job"), h("thead", {}, h("tr", {}, h("th", { scope: "col" }, "Number"), jobs.map((j) => h("th", { scope: "col" }, `Job ${j.id}`)))), h("tbody", {}, heads.map((n) => h("tr", {}, h("th", { scope: "row" }, words(n)), results.map((r) => h("td", {}, shown(n, r[n])))))))
            : h("p", { class: "none-yet" }, `${none}.`),
        ),
        h("section", { "aria-labelledby": "diff-heading" }, h("h2", { id: "diff-heading" }, "Tables and curves"), sections.length ? sections : h("p", { class: "none-yet", id: "compare-no-table" }, `${none}: these results have no table.`)),
      );
    })
    .catch((error) => fill(body, problem(error)));
}
