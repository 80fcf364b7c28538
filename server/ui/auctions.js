// Auctions: the list, and one auction followed live from its event stream.

import { follow, getJSON, pager } from "./api.js";
import { facts, fill, fixed, h, isMissing, link, notFound, problem, svg, table, tableRow, when } from "./dom.js";

const STOP_REASONS = {
  sold_out: "sold out",
  no_patrons: "no patron left (every one bought or quit)",
  stalemate: "stalemate (the price fell below the threshold)",
  max_iterations: "round limit reached",
  cancelled: "cancelled by the operator",
};
const CHART = { width: 640, height: 240, left: 56, right: 16, top: 16, bottom: 36 };

function stopReason(reason) {
  return reason ? STOP_REASONS[reason] || reason : "—";
}

function statusBadge(status) {
  return h("span", { class: `badge status-${status}` }, status);
}

const STATUSES = ["pending", "running", "finished", "failed", "cancelled"];
const NEURON_WORDS = {
  PG: "the high-price neuron",
  SZ: "the size neuron",
  LSR: "the limited-supply-rush neuron",
  ST: "the sub-type neuron",
  B: "buy",
  L: "hold (want a lower price)",
  Q: "quit",
  T: "the verdict 'right'",
  F: "the verdict 'wrong'",
};

function filters(id, label, chosen, onApply) {
  const field = (name, text, options) =>
    h("label", { for: `${id}-${name}` }, `${text} `, h("select", { id: `${id}-${name}` }, options.map(([v, t]) => h("option", { value: v, selected: v === chosen[name] }, t))));
  const form = h(
    "form",
    { class: "filters", id, "aria-label": label },
    field("status", "Status", [["", "any"], ...STATUSES.map((v) => [v, v])]),
    field("order", "Order", [["newest", "newest first"], ["oldest", "oldest first"]]),
    h("button", { type: "submit" }, "Apply"),
  );
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    onApply(form.querySelector(`#${id}-status`).value, form.querySelector(`#${id}-order`).value);
  });
  return form;
}

export function auctionList(view, query) {
  view.root.append(h("h1", { tabindex: "-1" }, "Auctions"));
  const chosen = { status: query.get("status") || "", order: query.get("order") || "newest" };
  view.root.append(
    filters("auction-filters", "Filter and sort the auctions", chosen, (status, order) => {
      const params = new URLSearchParams();
      if (status) params.set("status", status);
      if (order !== "newest") params.set("order", order);
      location.hash = `#/auctions${params.toString() ? `?${params}` : ""}`;
    }),
  );
  const rows = h("tbody");
  const headers = ["Auction", "Status", "Fish sold", "Patrons", "Rounds", "Price", "Revenue", "Stopped", "Started"];
  const list = h(
    "table",
    { class: "list", id: "auction-list" },
    h("caption", {}, `Auctions, ${chosen.order} first`),
    h("thead", {}, h("tr", {}, headers.map((text) => h("th", { scope: "col" }, text)))),
    rows,
  );
  const pages = pager("/auctions", { status: chosen.status, order: chosen.order === "newest" ? "" : chosen.order }, (items) => {
    for (const a of items) {
      rows.append(
        tableRow([
          link(`#/auctions/${a.id}`, `Auction ${a.id}`),
          statusBadge(a.status),
          `${a.n_sold} of ${a.n_initial}`,
          String(a.n_patrons),
          String(a.iteration),
          fixed(a.price),
          fixed(a.revenue, 2),
          stopReason(a.stop_reason),
          when(a.created_at),
        ]),
      );
    }
  });
  view.root.append(list, pages.box);
  pages
    .load()
    .then((page) => {
      if (page.items.length === 0) list.after(h("p", { class: "none-yet" }, "None yet: an operator starts one with POST /auctions."));
    })
    .catch((error) => view.root.append(problem(error)));
}

/** The price line: one point per committed round, redrawn as rounds arrive. */
function drawPriceChart(chart, rounds, nextPrice) {
  const { width, height, left, right, top, bottom } = CHART;
  const prices = rounds.map((r) => r.price);
  if (nextPrice !== null) prices.push(nextPrice);
  const low = Math.min(...prices, 4.8);
  const high = Math.max(...prices, 5.0);
  const pad = (high - low) * 0.08 || 0.05;
  const y0 = low - pad;
  const y1 = high + pad;
  const xMax = Math.max(prices.length - 1, 1);
  const x = (i) => left + ((width - left - right) * i) / xMax;
  const y = (p) => top + ((height - top - bottom) * (y1 - p)) / (y1 - y0);
  const parts = [svg("rect", { class: "plot", x: left, y: top, width: width - left - right, height: height - top - bottom })];
  for (let k = 0; k <= 4; k += 1) {
    const p = y0 + ((y1 - y0) * k) / 4;
    parts.push(
      svg("line", { class: "grid", x1: left, x2: width - right, y1: y(p), y2: y(p) }),
      svg("text", { class: "tick", x: left - 6, y: y(p) + 4, "text-anchor": "end" }, p.toFixed(2)),
    );
  }
  const step = Math.max(1, Math.ceil(xMax / 8));
  for (let i = 0; i <= xMax; i += step) {
    parts.push(svg("text", { class: "tick", x: x(i), y: height - bottom + 16, "text-anchor": "middle" }, String(i)));
  }
  parts.push(
    svg("text", { class: "axis-label", x: (left + width - right) / 2, y: height - 4, "text-anchor": "middle" }, "round"),
    svg("text", { class: "axis-label", x: 12, y: top + (height - top - bottom) / 2, transform: `rotate(-90 12 ${top + (height - top - bottom) / 2})`, "text-anchor": "middle" }, "price"),
  );
  const points = prices.map((p, i) => `${x(i).toFixed(1)},${y(p).toFixed(1)}`).join(" ");
  parts.push(svg("polyline", { class: "price-line", points, "data-points": prices.length }));
  rounds.forEach((r, i) => {
    const sold = r.purchases.length;
    parts.push(
      svg(
        "circle",
        { class: sold ? "price-point sold" : "price-point", cx: x(i), cy: y(r.price), r: sold ? 4.5 : 3 },
        svg("title", {}, `round ${r.iteration}: price ${fixed(r.price)}, ${sold} sold`),
      ),
    );
  });
  chart.setAttribute("data-points", String(prices.length));
  fill(chart, svg("title", { id: "price-chart-title" }, "Price asked in each round"), parts);
}

/** Buy, hold and quit votes of each round, stacked. */
function drawVotesChart(chart, rounds, nPatrons) {
  const { width, left, right, top } = CHART;
  const height = 160;
  const bottom = 28;
  const n = Math.max(rounds.length, 1);
  const band = (width - left - right) / n;
  const total = Math.max(nPatrons, 1);
  const y = (count) => ((height - top - bottom) * count) / total;
  const parts = [svg("rect", { class: "plot", x: left, y: top, width: width - left - right, height: height - top - bottom })];
  parts.push(
    svg("text", { class: "tick", x: left - 6, y: top + 4, "text-anchor": "end" }, String(nPatrons)),
    svg("text", { class: "tick", x: left - 6, y: height - bottom + 4, "text-anchor": "end" }, "0"),
  );
  rounds.forEach((r, i) => {
    let base = height - bottom;
    for (const kind of ["buy", "hold", "quit"]) {
      const tall = y(r.votes[kind]);
      base -= tall;
      parts.push(
        svg(
          "rect",
          { class: `vote-${kind}`, x: left + i * band + band * 0.1, y: base, width: band * 0.8, height: tall },
          svg("title", {}, `round ${r.iteration}: ${r.votes[kind]} ${kind}`),
        ),
      );
    }
  });
  const step = Math.max(1, Math.ceil(n / 8));
  for (let i = 0; i < rounds.length; i += step) {
    parts.push(svg("text", { class: "tick", x: left + (i + 0.5) * band, y: height - bottom + 14, "text-anchor": "middle" }, String(i)));
  }
  parts.push(svg("text", { class: "axis-label", x: (left + width - right) / 2, y: height - 2, "text-anchor": "middle" }, "round"));
  fill(chart, svg("title", {}, "Votes of the patrons still in, per round"), parts);
}

export function auctionView(view, id) {
  const title = h("h1", { tabindex: "-1" }, `Auction ${id}`);
  const liveness = h("p", { class: "liveness", role: "status", id: "liveness" }, "Loading…");
  const summary = h("div");
  const priceChart = svg("svg", { class: "chart", id: "price-chart", viewBox: `0 0 ${CHART.width} ${CHART.height}`, role: "img", "aria-labelledby": "price-chart-title", "data-points": "0" });
  const votesChart = svg("svg", { class: "chart", id: "votes-chart", viewBox: `0 0 ${CHART.width} 160`, role: "img", "aria-label": "Votes per round: buy, hold, quit" });
  const roundRows = h("tbody");
  const buyerRows = h("tbody");
  const quitterList = h("ul", { class: "quitters", id: "quitters" });
  const fineTuneRows = h("tbody");
  const noneYet = (span) => h("tr", { class: "none-yet-row" }, h("td", { colspan: span, class: "none-yet" }, "none yet"));
  const explainRound = h("select", { id: "explain-round" });
  const explainPatron = h("select", { id: "explain-patron" });
  const explanation = h("div", { id: "explanation", "aria-live": "polite" }, h("p", { class: "none-yet" }, "None yet: pick a round and a patron."));
  const explainForm = h(
    "form",
    { class: "filters", id: "explain-form", "aria-label": "Explain a vote" },
    h("label", { for: "explain-round" }, "Round ", explainRound),
    h("label", { for: "explain-patron" }, "Patron ", explainPatron),
    h("button", { type: "submit" }, "Explain the vote"),
  );
  const explainSection = h(
    "section",
    { "aria-labelledby": "explain-heading", id: "explain" },
    h("h2", { id: "explain-heading" }, "Every vote explained"),
    h("p", {}, "Why a patron voted buy, hold or quit in a round: its neurons on the row that decides (row 0), averaged over its copies as its vote was."),
    explainForm,
    explanation,
  );
  const leftAt = new Map(); // model id -> the round it bought or quit in (its last vote)
  /** The patrons who voted in the chosen round: those who had not left before it. */
  function listPatrons() {
    if (!head) return;
    const round = Number(explainRound.value || 0);
    const picked = explainPatron.value;
    const voters = head.model_ids.filter((modelId) => !(leftAt.get(modelId) < round));
    explainPatron.replaceChildren(...voters.map((modelId) => h("option", { value: modelId }, nameOf(modelId))));
    if (voters.map(String).includes(picked)) explainPatron.value = picked;
  }
  explainRound.addEventListener("change", listPatrons);
  explainForm.addEventListener("submit", (event) => {
    event.preventDefault();
    showExplanation(Number(explainRound.value), Number(explainPatron.value));
  });
  function pickRound(iteration) {
    explainRound.value = String(iteration);
    listPatrons();
    explainPatron.focus();
  }
  function showExplanation(iteration, modelId) {
    fill(explanation, h("p", { class: "liveness" }, "Loading…"));
    getJSON(`/auctions/${id}/iterations/${iteration}/votes/${modelId}`)
      .then((v) => {
        names.set(v.model_id, v.participant);
        const part = (caption, key, values) =>
          table(caption, ["Neuron", "Meaning", "Value"], Object.entries(values).map(([n, x]) => [n, NEURON_WORDS[n] || n, fixed(x, 4)]), { "data-part": key });
        fill(
          explanation,
          h(
            "div",
            { class: "explanation", "data-vote": v.vote },
            h("h3", {}, `${v.participant} (version ${v.version}, model ${v.model_id}) voted `, h("strong", { class: `vote-word vote-${v.vote}-text` }, v.vote), ` in round ${v.iteration}`),
            facts(Object.entries(v.row).map(([k, x]) => [k, fixed(x, 3)]), { "aria-label": "The row it voted on" }),
            part("External sensor (after its activations)", "sensor", v.sensor),
            part("Decision logits (the largest is the vote)", "decision", v.decision),
            part("Prefrontal cortex: its verdict on the decision", "pfc", v.pfc),
            link(`#/models/${v.model_id}`, "This model's neurons and weights in the inspector"),
          ),
        );
      })
      .catch((error) => fill(explanation, problem(error)));
  }
  const fineTuning = h(
    "section",
    { "aria-labelledby": "fine-tuning-heading", id: "fine-tuning", hidden: true },
    h("h2", { id: "fine-tuning-heading" }, "Remote fine-tuning rounds"),
    h("p", {}, "After each of the first rounds the participants fine-tune their own patrons over HTTP; a round waits for their uploads until its deadline."),
    h(
      "table",
      { class: "list" },
      h("caption", {}, "Each fine-tuning round and how its patrons answered"),
      h("thead", {}, h("tr", {}, ["Round", "After round", "Status", "Deadline", "Answers", "Each patron"].map((t) => h("th", { scope: "col" }, t)))),
      fineTuneRows,
    ),
  );
  view.root.append(
    title,
    liveness,
    summary,
    h(
      "section",
      { "aria-labelledby": "price-heading" },
      h("h2", { id: "price-heading" }, "Price over the rounds"),
      h("figure", {}, priceChart, h("figcaption", {}, "Each point is the price asked in a round; filled larger points are rounds in which fish were sold; the last point is the next price.")),
    ),
    h(
      "section",
      { "aria-labelledby": "votes-heading" },
      h("h2", { id: "votes-heading" }, "Votes per round"),
      h("figure", {}, votesChart, h("figcaption", { class: "legend" }, h("span", { class: "key vote-buy" }), "buy ", h("span", { class: "key vote-hold" }), "hold ", h("span", { class: "key vote-quit" }), "quit")),
      h(
        "div",
        { class: "scroll", tabindex: "0", role: "region", "aria-label": "Scrollable table" },
        h(
          "table",
          { class: "list", id: "rounds" },
          h("caption", {}, "Every committed round"),
          h("thead", {}, h("tr", {}, ["Round", "Price", "Fish left", "Buy", "Hold", "Quit", "Sold", "Quit now", "Votes"].map((t) => h("th", { scope: "col" }, t)))),
          roundRows,
        ),
      ),
    ),
    h(
      "section",
      { "aria-labelledby": "buyers-heading" },
      h("h2", { id: "buyers-heading" }, "Buyers"),
      h(
        "table",
        { class: "list", id: "buyers" },
        h("caption", {}, "Who bought a fish, at what price"),
        h("thead", {}, h("tr", {}, ["Participant", "Version", "Model", "Price", "Round"].map((t) => h("th", { scope: "col" }, t)))),
        buyerRows,
      ),
    ),
    h("section", { "aria-labelledby": "quitters-heading" }, h("h2", { id: "quitters-heading" }, "Quitters"), quitterList),
    explainSection,
    fineTuning,
  );
  buyerRows.append(noneYet(5));
  quitterList.append(h("li", { class: "none-yet" }, "none yet"));

  const rounds = [];
  let head = null;
  let drawPending = false;

  function showSummary(state) {
    const sold = rounds.reduce((n, r) => n + r.purchases.length, 0);
    const last = rounds[rounds.length - 1];
    fill(
      summary,
      facts(
        [
          ["Status", statusBadge(state.status)],
          ["Fish on sale", String(head.n_initial)],
          ["Fish left", String(last ? last.n_available_after : head.n_initial)],
          ["Sold", String(sold)],
          ["Patrons", String(head.n_patrons)],
          ["Rounds", String(rounds.length)],
          ["Price now", fixed(last ? last.next_price : head.price)],
          ["Revenue", fixed(rounds.reduce((n, r) => n + r.purchases.reduce((m, p) => m + p.price, 0), 0), 2)],
          ["Stopped because", stopReason(state.stop_reason)],
          ["Seed", String(head.seed)],
          ["Fine-tuning", head.fine_tune ? "yes" : "no"],
          ...(head.enroll_until && state.status === "pending"
            ? [["Takes patrons until", when(head.enroll_until)]]
            : []),
        ],
        { id: "auction-summary" },
      ),
      state.error ? h("p", { class: "problem" }, `Failed: ${state.error}`) : null,
    );
  }

  const fineTuneRowOf = new Map(); // round number -> its table row, updated in place
  function showFineTuneRound(r) {
    fineTuning.hidden = false;
    const outcomes = {};
    for (const a of r.answers) outcomes[a.outcome] = (outcomes[a.outcome] || 0) + 1;
    const nothing = r.status === "open" ? "none yet" : "none";
    const answers = Object.entries(outcomes).map(([outcome, n]) => `${n} ${outcome}`).join(", ") || nothing;
    const each = r.answers.length ? h("ul", { class: "answers" }, r.answers.map(answerItem)) : h("span", { class: "none-yet" }, nothing);
    const row = tableRow([String(r.round), String(r.iteration), statusBadge(r.status), when(r.deadline), answers, each], { "data-round": r.round });
    const old = fineTuneRowOf.get(r.round);
    if (old) old.replaceWith(row);
    else fineTuneRows.append(row);
    fineTuneRowOf.set(r.round, row);
  }

  /** A patron's outcome in a round, linked to the version it bids with; a refused upload's
   * screener reasons are read from that stored version. */
  function answerItem(a) {
    const item = h("li", { "data-model": a.model_id, "data-outcome": a.outcome }, `${nameOf(a.model_id)}: ${a.outcome}, bids with `, link(`#/models/${a.version_id}`, `version ${a.version}`));
    if (a.outcome === "refused" && a.uploaded_id !== null) {
      const reasons = h("ul", { class: "reasons" });
      item.append(" (refused upload: ", link(`#/models/${a.uploaded_id}`, `model ${a.uploaded_id}`), ")", reasons);
      getJSON(`/models/${a.uploaded_id}`)
        .then((m) => fill(reasons, m.reasons.map((reason) => h("li", {}, `${reason.rule} on ${reason.neuron}: ${reason.message}`))))
        .catch((error) => fill(reasons, h("li", {}, String(error.message || error))));
    }
    return item;
  }

  const names = new Map(); // model id -> participant, as the events name the patrons
  function nameOf(modelId) {
    return names.get(modelId) || `model ${modelId}`;
  }

  function patronLink(p) {
    return link(`#/models/${p.model_id}`, p.participant);
  }

  // An auction read while it enrolled had no patrons and no fish yet: read it again once it
  // plays (its first round) and when it ends, so the summary, the charts and the patron picker
  // show the patrons it started with.
  function readHeadAgain() {
    getJSON(`/auctions/${id}`)
      .then((auction) => {
        head = auction;
        auction.model_ids.forEach((modelId, i) => names.set(modelId, auction.participants[i]));
        listPatrons();
        scheduleDraw();
        if (auction.status !== "pending" && auction.status !== "running") showSummary(auction);
      })
      .catch(() => {}); // the stream goes on; the next read will tell
  }

  function addRound(row) {
    if (row.iteration !== rounds.length) return; // the stream never skips or repeats; a guard
    if (row.iteration === 0 && head.status === "pending") readHeadAgain();
    rounds.push(row);
    roundRows.append(
      tableRow([
        String(row.iteration),
        fixed(row.price),
        String(row.n_available),
        String(row.votes.buy),
        String(row.votes.hold),
        String(row.votes.quit),
        String(row.purchases.length),
        String(row.quits.length),
        h("button", { type: "button", class: "explain-round", "data-iteration": row.iteration, onclick: () => pickRound(row.iteration) }, `Explain round ${row.iteration}`),
      ]),
    );
    for (const p of [...row.purchases, ...row.quits]) {
      names.set(p.model_id, p.participant);
      leftAt.set(p.model_id, row.iteration);
    }
    explainRound.append(h("option", { value: row.iteration }, `round ${row.iteration}`));
    if (row.iteration === 0) {
      buyerRows.replaceChildren();
      quitterList.replaceChildren();
    }
    for (const p of row.purchases) {
      buyerRows.append(tableRow([patronLink(p), String(p.version), String(p.model_id), fixed(p.price), String(row.iteration)]));
    }
    for (const q of row.quits) quitterList.append(h("li", {}, patronLink(q), ` (round ${row.iteration})`));
    scheduleDraw();
  }

  // Rounds can arrive in a burst (a finished auction sends them all at once): draw once a frame.
  function draw() {
    drawPending = false;
    if (rounds.length === 0) return;
    drawPriceChart(priceChart, rounds, rounds[rounds.length - 1].next_price);
    drawVotesChart(votesChart, rounds, head.n_patrons);
  }
  function scheduleDraw() {
    if (!drawPending) requestAnimationFrame(draw);
    drawPending = true;
    showSummary({ status: "running", stop_reason: null, error: null });
  }

  getJSON(`/auctions/${id}`)
    .then((auction) => {
      head = auction;
      auction.model_ids.forEach((modelId, i) => names.set(modelId, auction.participants[i]));
      listPatrons();
      showSummary(auction);
      drawPriceChart(priceChart, [], auction.price);
      const stop = follow(
        `/auctions/${id}/events`,
        {
          iteration: addRound,
          round: showFineTuneRound,
          end: (end) => {
            if (head.n_initial !== end.n_initial) readHeadAgain(); // it enrolled meanwhile
            draw();
            showSummary(end);
            if (rounds.length === 0) {
              buyerRows.replaceChildren();
              quitterList.replaceChildren();
            }
            if (quitterList.children.length === 0) quitterList.append(h("li", {}, "nobody quit"));
            listPatrons();
            liveness.textContent = `Ended: ${end.status}, ${stopReason(end.stop_reason)}; ${end.n_sold} of ${end.n_initial} fish sold in ${end.iterations} ${end.iterations === 1 ? "round" : "rounds"}.`;
            if (buyerRows.children.length === 0) buyerRows.append(tableRow(["nobody bought a fish", "", "", "", ""]));
          },
        },
        (state) => {
          if (state === "live") liveness.textContent = "Following live: each round appears as soon as it is committed.";
          if (state === "waiting") liveness.textContent = "Connection lost; resuming where it left off…";
        },
      );
      view.onLeave(stop);
    })
    .catch((error) => {
      if (isMissing(error)) notFound(view.root, `Auction ${id}`, ["#/", "All auctions"]);
      else liveness.replaceWith(problem(error));
    });
}
