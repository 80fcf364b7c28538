// Reviews: the models the screener held for a person (#/reviews) and the inspection page of one
// (#/reviews/{id}): its named neurons (the models view), the screener's evidence drawn, and the
// operator's admit / refuse. The admin token is pasted once and kept in this module's memory
// only (never stored, never in a URL); it travels in the Authorization header.

import { ApiError, LIST_REFRESH_MS, firstRead, getJSON, postJSON } from "./api.js";
import { fill, fixed, fixedApart, h, isMissing, link, navigated, notFound, patch, problem, scrolling, svg, table, votePatterns, when } from "./dom.js";
import { auditLog, by, evidenceTable, inspectorView, measuredAndBar, verdictNow } from "./models.js";

let adminToken = null;

const DECISION_WORDS = /(buys|holds|quits) (\d+(?:\.\d+)?)-(\d+(?:\.\d+)?)/g;

/** The operator's token form; ``then()`` runs once a token is set. ``refused``: why the token
 * given before was refused (the field is marked invalid until another is typed). */
function tokenForm(then, refused = null) {
  const input = h("input", { id: "admin-token", type: "password", autocomplete: "off", required: true, "aria-describedby": "admin-token-help admin-token-status", "aria-invalid": refused ? "true" : null });
  const status = h("p", { id: "admin-token-status", class: "problem", role: "alert", hidden: !refused }, refused ? String(refused.message || refused) : null);
  const form = h(
    "form",
    { class: "filters", id: "token-form" },
    h("label", { for: "admin-token" }, "Operator (admin) token"),
    input,
    h("button", { type: "submit" }, "Use token"),
    h("span", { id: "admin-token-help", class: "quiet" }, "Kept in this page's memory only, sent as Authorization: Bearer."),
    status,
  );
  form.noValidate = true; // said in words below, not in the browser's bubble
  input.addEventListener("input", () => input.removeAttribute("aria-invalid"));
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    adminToken = input.value.trim() || null;
    if (adminToken) then();
    else {
      input.setAttribute("aria-invalid", "true");
      status.textContent = "Paste the operator's admin token first: the field is blank.";
      status.hidden = false;
      input.focus();
    }
  });
  return form;
}

/** Whether the server refused the operator's token. */
function tokenRefused(error) {
  return error instanceof ApiError && (error.status === 401 || error.status === 403);
}

/** Read with the token, asking for it first when there is none (or it was refused): ``read()``
 * is the view's first read, tried again every few seconds while it fails (firstRead: the
 * server out of reach, say, as every detail page's), its answer drawn by ``use(box, answer)``;
 * a refused token asks for another instead. */
function withToken(view, { read, use }, heading = null) {
  const box = h("div");
  view.root.append(box);
  const ask = (words) => {
    fill(box, heading ? h("h1", { tabindex: "-1" }, heading) : null, tokenForm(() => start(), words));
    // After a navigation or a refused token the field takes the focus; on a page's first load
    // the focus stays at the top (the skip link and the navigation come first).
    if (words || navigated()) box.querySelector("input")?.focus();
  };
  const start = () => {
    // The token's field had the focus, or the view was opened by a link: once the page is
    // drawn, its heading takes the focus (it would fall to the document's body).
    const hadFocus = box.contains(document.activeElement) || navigated();
    const loading = h("p", { class: "liveness" }, "Loading…");
    fill(box, loading);
    firstRead(view, read, {
      at: loading,
      missing: (error) => fill(box, problem(error)), // a read of these pages names no subject
      refused: (error) => {
        if (!tokenRefused(error)) return false;
        adminToken = null;
        ask(error);
        return true;
      },
      use: (answer) => {
        loading.remove();
        use(box, answer);
        const lost = !document.activeElement || document.activeElement === document.body;
        if (hadFocus && lost) (box.querySelector("h1") || view.root.querySelector("h1"))?.focus();
      },
    });
  };
  if (adminToken) start();
  else ask(null);
}

/** The queue whole (it is short: the screener holds few), and the review margin. */
async function readQueue() {
  const rows = [];
  let cursor = null;
  let margin = null;
  do {
    const page = await getJSON(`/reviews?limit=100${cursor ? `&cursor=${cursor}` : ""}`, adminToken);
    rows.push(...page.items);
    cursor = page.next_cursor;
    margin = page.review_margin;
  } while (cursor);
  return { rows, margin };
}

export function reviewList(view) {
  view.root.append(
    h("h1", { tabindex: "-1" }, "Models held for review"),
    h("p", {}, "The screener holds a model when its deciding evidence lies within the review margin (SRD_REVIEW_MARGIN, in price) of its bar, and a refused model its participant appealed. Oldest first."),
  );
  withToken(view, { read: readQueue, use: (box, first) => followQueue(view, box, first) });
}

/** The queue as first read (``first``), then read again every LIST_REFRESH_MS while the tab is
 * shown (never two reads at once): a model held or appealed since appears in its place (oldest
 * first), one decided goes, the others' rows stay the elements they were, and the focus stays
 * where it was in its model's row (or on the scrolling frame, scrolled as it was). */
function followQueue(view, box, first) {
  // rendered from the start (an empty live region takes no room): a region shown at the
  // moment its words arrive is not read out. It follows the queue: its words arriving move
  // nothing under the pointer (the table stays where it is).
  const state = h("p", { class: "none-yet", id: "list-state", role: "status" });
  const list = h("div");
  box.append(list, state);
  let seen = null;
  let ids = null;
  let readAt = null;
  let failing = false;
  let reading = false;
  const draw = ({ rows, margin }) => {
    readAt = new Date();
    const text = JSON.stringify([rows, margin]);
    if (failing) state.textContent = ""; // read again: the failure is over
    failing = false;
    if (text === seen) return;
    const now = new Set(rows.map((m) => m.id));
    if (ids !== null) {
      const added = rows.filter((m) => !ids.has(m.id)).length;
      const gone = [...ids].filter((id) => !now.has(id)).length;
      const words = [added ? `${added} held since` : "", gone ? `${gone} decided or withdrawn` : ""].filter(Boolean);
      state.textContent = `Read again at ${readAt.toLocaleTimeString()}: ${words.length ? words.join(", ") : "a held model's evidence changed"}.`;
    }
    seen = text;
    ids = now;
    const at = where(list);
    const fresh = rows.length ? queueTable(rows, margin) : h("p", { class: "none-yet", id: "no-reviews" }, "No model is waiting for an inspector.");
    // Patched, not redrawn: a held model's row stays the same element (a press on its link
    // that ends after the queue changed still opens it).
    if (list.firstChild) patch(list.firstChild, fresh);
    else fill(list, fresh);
    if (at) restore(list, at, view.root.querySelector("h1"));
  };
  draw(first);
  const timer = setInterval(() => {
    if (document.visibilityState !== "visible" || !box.isConnected || reading) return;
    reading = true;
    readQueue()
      .then(draw)
      .catch((error) => {
        failing = true;
        if (tokenRefused(error)) {
          adminToken = null; // rotated or revoked: the next visit asks for it again
          clearInterval(timer);
          state.textContent = `The operator token was refused (${String(error.message || error)}): the held models are shown as read at ${readAt.toLocaleTimeString()}; open the queue again to give the token.`;
        } else {
          state.textContent = `The queue could not be read again (${String(error.message || error)}); it shows the held models as read at ${readAt.toLocaleTimeString()}, and is read again every few seconds.`;
        }
      })
      .finally(() => {
        reading = false;
      });
  }, LIST_REFRESH_MS);
  view.onLeave(() => clearInterval(timer));
}

/** Where the focus is in a drawn queue: the scrolling frame (with how far it scrolled), or a
 * control of a model's row (its row by the model's own link, the control by its place). */
function where(list) {
  const active = document.activeElement;
  if (!active || !list.contains(active)) return null;
  const frame = list.querySelector(".scroll");
  const scrolled = frame ? frame.scrollLeft : 0;
  if (active === frame) return { frame: true, scrolled };
  const row = active.closest("tr");
  const own = row?.querySelector("a[href^='#/reviews/']")?.getAttribute("href");
  const controls = row ? [...row.querySelectorAll("a, button")] : [];
  return { own, place: controls.indexOf(active), scrolled };
}

/** The focus put back after a redraw (to ``fallback`` when its model's row is gone). */
function restore(list, at, fallback) {
  const frame = list.querySelector(".scroll");
  if (frame) frame.scrollLeft = at.scrolled;
  if (at.frame) return (frame || fallback)?.focus();
  const link = at.own ? list.querySelector(`a[href="${at.own}"]`) : null;
  const controls = link ? [...link.closest("tr").querySelectorAll("a, button")] : [];
  (controls[at.place] || link || fallback)?.focus();
}

function queueTable(rows, margin) {
  const held = scrolling(
    table(
      `${rows.length} held model${rows.length === 1 ? "" : "s"}`,
      ["Model", "Participant", "Version", "Why held", "From", "Held since"],
      rows.map((m) => [
        link(`#/reviews/${m.id}`, `Inspect model ${m.id}`),
        h("span", { class: "free-text" }, m.participant),
        String(m.version),
        // an appealed model: the screener's refusal first, then the participant's words, quoted
        m.appeal !== null ? [refusedFor(m.reasons), "; appealed: ", h("q", { class: "free-text description-preview", dir: "auto" }, m.appeal)] : nearest(m.evidence, margin),
        m.auction_id !== null ? link(`#/auctions/${m.auction_id}`, `auction ${m.auction_id}, fine-tuning round ${m.round}`) : "POST /submit",
        when(m.created_at),
      ]),
      { class: "list", id: "review-list" },
    ),
    "Held models (scrolls sideways)",
  );
  held.querySelectorAll("tbody tr").forEach((row, i) => row.setAttribute("data-key", String(rows[i].id)));
  return held;
}

/** Why the screener refused a model (an appealed one), in a few words: its first reason's. */
function refusedFor(reasons) {
  if (!reasons.length) return "refused by the screener";
  const more = reasons.length > 1 ? ` and ${reasons.length - 1} more` : "";
  return `refused by the screener: ${reasons[0].neuron} (${reasons[0].rule})${more}`;
}

/** The priced bar closest to its measurement, in words, and what the review margin made of
 * it (``margin``: the server's, in price). */
function nearest(evidence, margin) {
  const priced = evidence.filter((e) => e.units === "price" && e.measured !== null && e.bar !== null);
  if (!priced.length) return "—";
  // A refused model is held for the bars it missed (all within the margin): the nearest of
  // those; an accepted one for a bar it passed within the margin.
  const missed = priced.filter((e) => !e.passed);
  const e = (missed.length ? missed : priced).reduce((a, b) => (Math.abs(a.measured - a.bar) <= Math.abs(b.measured - b.bar) ? a : b));
  const near = margin !== null && Math.abs(e.measured - e.bar) < margin; // as the server holds
  const held = near ? `, within the review margin ${fixed(margin, 4)} of its bar: held for you` : "";
  const [measured, bar] = measuredAndBar(e);
  return `${e.test}: ${measured} against ${bar} (${e.side}), ${by(e)}${held}`;
}

export function reviewView(view, id) {
  document.title = `Inspect model ${id} · srd-auction`;
  // The model's place in the queue; a model not held there is read as it stands.
  const read = async () => {
    const queue = await getJSON(`/reviews?limit=1${id > 1 ? `&cursor=${id - 1}` : ""}`, adminToken);
    const item = queue.items.find((m) => m.id === id);
    if (item) return { item };
    try {
      return { model: await getJSON(`/models/${id}`) };
    } catch (error) {
      if (!isMissing(error)) throw error;
      return {};
    }
  };
  const use = (box, { item, model }) => {
    if (item) {
      inspectorView({ root: box, onLeave: (stop) => view.onLeave(stop) }, id, { heading: "Inspect model", evidence: false, extra: (m) => [evidenceSection(m, item), decisionForm(m)].flat() });
      return;
    }
    if (!model) {
      notFound(box, `Model ${id}`, ["#/reviews", "Every held model"]);
      return;
    }
    const last = model.reviews.filter((r) => r.decision !== "appeal").pop();
    const decided = last ? ` It was ${last.decision === "admit" ? "admitted" : "refused"} by inspector ${last.inspector} on ${when(last.at)}.` : "";
    box.append(h("h1", { tabindex: "-1" }, `Model ${id}`), h("p", { id: "not-held", class: "free-text" }, `This model is not held for review.${decided} `, link(`#/models/${id}`, "Its inspector's view"), " · ", link("#/reviews", "Every held model")));
    document.title = `Model ${id} · srd-auction`;
  };
  withToken(view, { read, use }, `Inspect model ${id}`);
}

function evidenceSection(model, item) {
  const scan = model.evidence.find((e) => e.detail.clean && e.detail.noisy);
  const impacts = model.evidence.filter((e) => e.test === "market-impact");
  // The appeal is the participant's words: set apart as a description is (quoted, in a dashed
  // frame, in italics) and outside the screener's evidence, so it cannot pass for a finding.
  const appeal =
    item.appeal !== null
      ? h(
          "section",
          { "aria-labelledby": "appeal-heading" },
          h("h2", { id: "appeal-heading" }, "The appeal, in the participant's words"),
          h("blockquote", { class: "description", id: "appeal", dir: "auto" }, item.appeal),
        )
      : null;
  const evidence = h(
    "section",
    { "aria-labelledby": "evidence-heading", id: "evidence" },
    h("h2", { id: "evidence-heading" }, "The screener's evidence"),
    item.later_versions.length
      ? h(
          "p",
          { id: "later-versions" },
          h("strong", {}, "Its participant's later versions: "),
          ...item.later_versions.flatMap((v, i) => [i ? ", " : "", link(`#/models/${v.model_id}`, `version ${v.version}`), ` (${v.status})`]),
          ". Deciding this one does not decide them.",
        )
      : null,
    model.reasons.length ? h("ul", { class: "reasons" }, model.reasons.map((r) => h("li", {}, h("strong", {}, `${r.neuron} (${r.rule}): `), r.message))) : null,
    scan ? h("figure", {}, scrolling(decisionsChart(scan.detail), "The decisions chart (scrolls sideways on a narrow screen)"), h("figcaption", {}, `The auction's decisive row (the base fish, buy fraction ${scan.detail.buy_fraction}) across the prices it can reach: the model's decision clean and on its ${scan.detail.copies} noisy copies (σ ${Number(Number(scan.detail.noise_std).toPrecision(4))}, ${scan.detail.draws} draws): green buys (solid), amber holds (hatched), grey quits (dotted).`)) : null,
    impacts.length ? h("figure", {}, scrolling(impactChart(impacts), "The market-impact chart (scrolls sideways on a narrow screen)"), h("figcaption", {}, "The market-impact test: the mean purchase price its copies leave in the test auctions (green: passed, amber: missed, each said beside its price) against the lowest allowed (the dashed bar), and the references (grey).")) : null,
    populationsNote(impacts),
    evidenceTable(model),
  );
  return appeal ? [appeal, evidence] : evidence;
}

/** Segments [decision, from, to] of words such as "buys 4.75-5.10, holds 5.11-5.11, ...". */
function segments(words) {
  return [...String(words).matchAll(DECISION_WORDS)].map(([, what, from, to]) => [what, Number(from), Number(to)]);
}

function decisionsChart(detail) {
  const lines = [["clean", segments(detail.clean)], ["noisy", segments(detail.noisy)]];
  const all = lines.flatMap(([, s]) => s);
  const lo = Math.min(...all.map((s) => s[1]));
  const hi = Math.max(...all.map((s) => s[2]));
  const step = 0.01; // a segment covers its last price's cent too
  const [left, right, width] = [70, 20, 640];
  const x = (p) => left + ((p - lo) / (hi + step - lo || 1)) * (width - left - right);
  const ticks = [];
  for (let p = Math.ceil(lo * 4) / 4; p <= hi + 1e-9; p += 0.25) ticks.push(p);
  const patterns = votePatterns("decisions-chart"); // buys solid, holds hatched, quits dotted
  return svg(
    "svg",
    { class: "chart", viewBox: `0 0 ${width} 120`, role: "img", "aria-label": `Decisions across prices. Clean: ${detail.clean}. Noisy: ${detail.noisy}.` },
    patterns.defs,
    lines.map(([label, parts], row) => [
      svg("text", { x: 8, y: 30 + row * 40, class: "axis-label" }, label),
      parts.map(([what, from, to]) => svg("rect", { class: `vote-${what.slice(0, -1)}`, fill: patterns.fill(what.slice(0, -1)), x: x(from), y: 15 + row * 40, width: Math.max(1.5, x(to + step) - x(from)), height: 24 }, svg("title", {}, `${label}: ${what} ${from.toFixed(2)}–${to.toFixed(2)}`))),
    ]),
    ticks.map((p) => [svg("line", { class: "grid", x1: x(p), x2: x(p), y1: 12, y2: 96 }), svg("text", { class: "tick", x: x(p), y: 112, "text-anchor": "middle" }, p.toFixed(2))]),
  );
}

/** Which reference populations the market-impact test met, and whether this server's test
 * still meets them (its SRD_SCREENER_SECRET may have changed since). */
function populationsNote(impacts) {
  const seen = [...new Set(impacts.map((e) => e.detail.populations).filter(Boolean))];
  if (!seen.length) return null;
  const named = (p) => (p === "public" ? "the public reference populations (no deployment secret set)" : `the reference populations of a deployment's secret (${p})`);
  const note = h("p", { id: "populations" }, `Its test auctions used ${seen.map(named).join(" and ")}.`);
  getJSON("/healthz")
    .then((health) => {
      const now = health.screener_populations;
      if (seen.some((p) => p !== now)) note.append(` This server's test uses ${named(now)} now: measured again, the model would meet other auctions.`);
    })
    .catch(() => {}); // not ready: the note stays as measured
  return note;
}

function impactChart(impacts) {
  // One set of references and one bar per count of test auctions: a model near the bar was
  // judged on more auctions (its second stage), against their own references.
  const counted = (e) => e.detail.test_auctions ?? 16;
  const sets = [...new Map(impacts.map((e) => [counted(e), e])).values()];
  // each point with its count of auctions where there are two stages, or where the one shown
  // is not the first stage's 16
  const suffix = (e) => (sets.length > 1 || counted(sets[0]) !== 16 ? ` (${counted(e)} auctions)` : "");
  const named = sets.flatMap((e) => [
    [`without its copies${suffix(e)}`, e.detail.without_copies],
    [`always-hold saboteurs${suffix(e)}`, e.detail.always_hold_saboteurs],
    [`copies that quit at the opening price${suffix(e)}`, e.detail.quitters_at_opening],
  ]).filter(([, v]) => typeof v === "number");
  const bars = sets.map((e) => [e.bar, suffix(e)]);
  const values = [...impacts.map((e) => e.measured), ...bars.map(([b]) => b), ...named.map(([, v]) => v)].filter((v) => v !== null);
  const lo = Math.min(...values) - 0.005;
  const hi = Math.max(...values) + 0.005;
  const [left, width] = [300, 700];
  const rowsY = (i) => 20 + i * 26;
  const x = (p) => left + ((p - lo) / (hi - lo)) * (width - left - 115); // room for the label
  // Whether the copies passed is said beside their price, not by the dot's colour alone.
  const marks = [...impacts.map((e) => [`copies, ${e.detail.version}${suffix(e)}`, e.measured, e.passed ? "ink-buy" : "ink-hold", e.passed ? "passed" : "missed"]), ...named.map(([label, v]) => [label, v, "ink-quit", null])];
  // four decimals, or more where a price and a bar would read alike (a near tie held for review)
  const digits = fixedApart([...impacts.map((e) => e.measured).filter((v) => v !== null), ...bars.map(([b]) => b)], 4)[0]?.split(".")[1]?.length ?? 4;
  const valued = (value, verdict) => `${Number(value).toFixed(digits)}${verdict ? ` ${verdict}` : ""}`;
  const top = rowsY(marks.length);
  const height = top + 14 * bars.length + 10;
  const said = bars.map(([b, words]) => `bar ${b.toFixed(digits)}${words}`).join("; ");
  return svg(
    "svg",
    { class: "chart", viewBox: `0 0 ${width} ${height}`, role: "img", "aria-label": `Market impact: ${said}; ${marks.map(([l, v, , verdict]) => `${l} ${valued(v, verdict)}`).join("; ")}.` },
    marks.map(([label, value, cls, verdict], i) => [
      svg("text", { x: 8, y: rowsY(i) + 4, class: "axis-label" }, label),
      svg("circle", { class: cls, cx: x(value), cy: rowsY(i), r: 6 }, svg("title", {}, `${label}: ${valued(value, verdict)}`)),
      svg("text", { x: x(value) + 10, y: rowsY(i) + 4, class: "tick" }, valued(value, verdict)),
    ]),
    bars.map(([b, words], i) => [
      svg("line", { class: "bar-line", x1: x(b), x2: x(b), y1: 6, y2: top + 14 * i }),
      // A bar near the right edge names itself leftwards: the label stays inside the chart.
      svg("text", { class: "tick", x: x(b), y: top + 10 + 14 * i, "text-anchor": x(b) > width - 120 ? "end" : "middle" }, `bar ${b.toFixed(digits)}${words}`),
    ]),
  );
}

function decisionForm(model) {
  const inspector = h("input", { id: "inspector", name: "inspector", "aria-required": "true", maxlength: 64, autocomplete: "name" });
  const note = h("textarea", { id: "note", name: "note", rows: 3, maxlength: 2000, "aria-describedby": "note-public" });
  const status = h("p", { id: "decision-status", role: "status", tabindex: "-1" });
  const buttons = [
    // Plain buttons, not submit buttons: Enter in a field submits a form with its first
    // submit button, and no keystroke in a field may admit (or refuse) a model.
    h("button", { type: "button", value: "admit", id: "admit" }, "Admit"),
    h("button", { type: "button", value: "refuse", id: "refuse" }, "Refuse"),
  ];
  const fields = [
    h("p", { class: "field" }, h("label", { for: "inspector" }, "Inspector"), inspector),
    h("p", { class: "field" }, h("label", { for: "note" }, "Note (why)"), note),
    h("p", { id: "note-public", class: "hint" }, "Public: your name and note are shown with the model to everyone (GET /models/{id}) and to its participant."),
    h("p", { class: "actions" }, buttons),
  ];
  const form = h("form", { id: "decision", "aria-labelledby": "decision-heading" }, h("h2", { id: "decision-heading" }, "Your decision"), fields, status);
  form.addEventListener("submit", (event) => {
    // Enter in the Inspector field: nothing is decided, and the page says how to decide.
    event.preventDefault();
    fill(status, "Nothing recorded: press Admit or Refuse to decide.");
  });
  for (const b of buttons) b.addEventListener("click", () => decide(b.value));
  function decide(decision) {
    if (!inspector.value.trim()) {
      // the server's own words for a blank name, said before asking it
      fill(status, problem("Inspector: must name someone: it is blank."));
      inspector.focus();
      return;
    }
    for (const b of buttons) b.disabled = true;
    postJSON(`/models/${model.id}/review`, { decision, inspector: inspector.value, note: note.value }, adminToken)
      .then((done) => {
        showNow({ ...model, ...done });
        const did = decision === "admit" ? "admitted" : "refused";
        // one sentence in the live region: the history is shown above, not read out again
        fill(status, `Model ${done.model_id} is now ${done.status} (${did} by ${inspector.value}). `, link("#/reviews", "Back to the held models"));
        status.focus(); // the button pressed is disabled now: the focus goes to what it did
      })
      .catch((error) => {
        for (const b of buttons) b.disabled = false;
        fill(status, problem(error));
        status.focus();
        // Not held any more (another inspector decided it meanwhile, say): the page is drawn
        // again as the model stands, and a decided model offers no decision.
        if (error.status === 409) getJSON(`/models/${model.id}`).then(showNow, () => {});
      });
  }
  /** The verdict and the review history at the top as ``now`` has them; a model no longer
   * held loses the decision's fields and buttons (its answer stays). */
  function showNow(now) {
    const banner = verdictNow(now);
    document.getElementById("verdict")?.replaceWith(banner);
    const old = document.getElementById("model-audit");
    const history = now.reviews.length ? auditLog(now.reviews) : null;
    if (old && history) old.replaceWith(history);
    else if (history) banner.after(history);
    if (now.status !== "held") for (const part of fields) part.remove();
  }
  return form;
}
