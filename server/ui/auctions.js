// Auctions: the list, and one auction followed live from its event stream.

import { firstRead, follow, getJSON, keepCurrent, pager } from "./api.js";
import { facts, fill, fixed, fixedApart, h, link, notFound, passed, patch, plural, problem, recordedPrice, scrolling, svg, table, tableRow, votePatterns, when } from "./dom.js";

const STOP_REASONS = {
  sold_out: "sold out",
  no_patrons: "no patron left (every one bought or quit)",
  stalemate: "stalemate (the price fell below the threshold)",
  max_iterations: "iteration limit reached",
  cancelled: "cancelled by the operator",
};
// What a row's buy fraction f counts (GET /auctions/{id} buy_fraction).
const BUY_FRACTIONS = {
  all: "all: every voter counts (the paper's)",
  staying: "staying: buyers and holders only (quitting does not lower it)",
};
const CHART = { width: 640, height: 240, left: 56, right: 16, top: 16, bottom: 36 };

function stopReason(reason) {
  return reason ? STOP_REASONS[reason] || reason : "—";
}

// The market's price rules (sim.market.MarketConfig; no auction sets them otherwise).
const PRICE_RULES = { increment: 0.05, decrement: 0.01, threshold: 4.8 };

/** Why the price moved after an iteration, and the stalemate threshold it leaves (docs/auction.md):
 * more buy votes than fish sells nothing and raises the price by the increment less U(0, 4)
 * decrements, the threshold following to a decrement above the iteration's price; otherwise
 * every buyer buys at the iteration's price and it falls by a decrement. */
function priceMove(row, threshold) {
  const moved = row.next_price - row.price;
  const by = `${moved >= 0 ? "+" : "−"}${Math.abs(moved).toFixed(3)} to ${fixed(row.next_price)}`;
  if (row.votes.buy > row.n_available) {
    const next = row.price + PRICE_RULES.decrement;
    const drawn = PRICE_RULES.increment - moved; // the random part: 0 to 4 decrements
    const less = `+${PRICE_RULES.increment} less a random 0 to ${(4 * PRICE_RULES.decrement).toFixed(2)}, here ${fixed(Math.max(0, drawn))}`;
    return { threshold: next, words: `${plural(row.votes.buy, "buy vote")} for ${row.n_available} fish: nobody bought; ${by} (${less}); stalemate below ${fixed(next)}` };
  }
  const sold = row.purchases.length ? `${row.purchases.length} sold at ${fixed(row.price)}` : "nobody bought";
  return { threshold, words: `${plural(row.votes.buy, "buy vote")} for ${row.n_available} fish: ${sold}; ${by} (−${PRICE_RULES.decrement}); stalemate below ${fixed(threshold)}` };
}

/** A share as a percentage with one decimal: "37.5%". */
function percent(share) {
  return `${(100 * share).toFixed(1)}%`;
}

function statusBadge(status) {
  return h("span", { class: `badge status-${status}` }, status);
}

// What the outcomes a patron's own word does not explain mean.
const ANSWER_WORDS = { late: "arrived after the deadline, not applied", missing: "no upload recorded before the deadline: none came, or each one was malformed" };

const STATUSES = ["pending", "running", "finished", "failed", "cancelled"];
const NEURON_WORDS = {
  PG: "the high-price neuron",
  SZ: "the size neuron",
  LSR: "the limited-supply-rush neuron",
  ST: "the sub-type neuron",
  B: "buy",
  L: "hold (want a lower price)",
  Q: "quit",
  PGL: "holding at a high price (right: feeds T)",
  BC: "buying cheap (right: feeds T)",
  FQ: "quitting a good fish (wrong: feeds F)",
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
  const headers = ["Auction", "Status", "Fish sold", "Patrons", "Iterations", "Price asked next", "Revenue", "Stopped", "Created"];
  const list = h(
    "table",
    { class: "list", id: "auction-list" },
    h("caption", {}, `${chosen.status ? `Auctions ${chosen.status}` : "Auctions"}, ${chosen.order} first`),
    h("thead", {}, h("tr", {}, headers.map((text) => h("th", { scope: "col" }, text)))),
    rows,
  );
  const auctionRow = (a) =>
    tableRow(
      [
        link(`#/auctions/${a.id}`, `Auction ${a.id}`),
        statusBadge(a.status),
        // a rarity's fish are counted from the patrons it has when it starts, as its page says
        a.rarity !== null && a.status === "pending" ? "counted when it starts" : a.rarity !== null && a.n_initial === 0 && a.iteration === 0 ? "none: it ended before it started" : `${a.n_sold} of ${a.n_initial}`,
        String(a.n_patrons),
        String(a.iteration),
        ["pending", "running"].includes(a.status) ? fixed(a.price) : "—",
        fixed(a.revenue),
        a.status === "failed" && !a.stop_reason ? "it failed (why: on its page)" : stopReason(a.stop_reason),
        when(a.created_at),
      ],
      { "data-id": a.id, "data-status": a.status },
    );
  const params = { status: chosen.status, order: chosen.order === "newest" ? "" : chosen.order };
  if (chosen.status && !STATUSES.includes(chosen.status)) {
    view.root.append(problem(`No auction status is called "${chosen.status}": pick one of the list.`));
    return;
  }
  const empty = h(
    "p",
    { class: "none-yet", id: "no-auctions", hidden: true },
    chosen.status ? `None matches this filter: no auction is ${chosen.status}.` : "None yet: an operator starts one with POST /auctions.",
  );
  let firstFailure = null;
  // The first page is read again every few seconds while the tab is shown: listed auctions
  // move on in place, and (newest first) new ones are offered by a button above the rows
  // ("2 new auctions — show") that adds them at the top when pressed; whether the list is
  // current is said when a read fails, and cleared when one succeeds, as is the first load's
  // failure.
  const current = keepCurrent(view, {
    ...{ path: "/auctions", params, newestFirst: chosen.order === "newest", rows, rowFor: auctionRow, noun: "auctions", empty },
    onRead: () => {
      firstFailure?.remove();
      firstFailure = null;
    },
  });
  const pages = pager("/auctions", params, current.add);
  view.root.append(current.news, scrolling(list, "Auctions (scrolls sideways)"), empty, pages.box);
  pages
    .load()
    .then(() => current.read())
    .catch((error) => {
      firstFailure = problem(error);
      view.root.append(firstFailure);
    });
}

/** The price line: one point per committed iteration, redrawn as iterations arrive. */
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
    svg("text", { class: "axis-label", x: (left + width - right) / 2, y: height - 4, "text-anchor": "middle" }, "iteration"),
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
        svg("title", {}, `iteration ${r.iteration}: price ${fixed(r.price)}, ${sold} sold`),
      ),
    );
  });
  chart.setAttribute("data-points", String(prices.length));
  chart.setAttribute("aria-label", priceSaid(rounds, nextPrice));
  fill(chart, svg("title", {}, "Price asked in each iteration"), parts);
}

// What the price chart shows, in words (its accessible name): where the price began and ended,
// its range, the iterations that sold and the next price; the table below holds every value.
function priceSaid(rounds, nextPrice) {
  const next = nextPrice === null ? "" : `; the next price ${fixed(nextPrice)}`;
  if (!rounds.length) return `Price asked in each iteration: none yet${next}.`;
  const first = rounds[0];
  const last = rounds[rounds.length - 1];
  const sold = rounds.filter((r) => r.purchases.length).map((r) => `${r.iteration} (${r.purchases.length} sold)`);
  const sales = sold.length ? `fish sold in iteration ${sold.join(", ")}` : "no fish sold";
  const asked = rounds.map((r) => r.price); // the range of prices asked, not the next one
  const span =
    rounds.length === 1
      ? `${fixed(first.price)} at iteration ${first.iteration}`
      : `${fixed(first.price)} at iteration ${first.iteration}, ${fixed(last.price)} at iteration ${last.iteration}, ` +
        `lowest ${fixed(Math.min(...asked))}, highest ${fixed(Math.max(...asked))}`;
  return `Price asked in each iteration: ${span}; ${sales}${next}. Every iteration is in the table below.`;
}

/** Buy, hold and quit votes of each iteration, stacked: each kind its colour and its texture
 * (buy solid, hold hatched, quit dotted), and every count in the chart's name, for a reader
 * who does not see it. */
function drawVotesChart(chart, rounds, nPatrons) {
  const { width, left, right, top } = CHART;
  const height = 160;
  const bottom = 28;
  const n = Math.max(rounds.length, 1);
  const band = (width - left - right) / n;
  const total = Math.max(nPatrons, 1);
  const y = (count) => ((height - top - bottom) * count) / total;
  const patterns = votePatterns("votes-chart");
  const parts = [patterns.defs, svg("rect", { class: "plot", x: left, y: top, width: width - left - right, height: height - top - bottom })];
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
          { class: `vote-${kind}`, fill: patterns.fill(kind), x: left + i * band + band * 0.1, y: base, width: band * 0.8, height: tall },
          svg("title", {}, `iteration ${r.iteration}: ${r.votes[kind]} ${kind}`),
        ),
      );
    }
  });
  const step = Math.max(1, Math.ceil(n / 8));
  for (let i = 0; i < rounds.length; i += step) {
    parts.push(svg("text", { class: "tick", x: left + (i + 0.5) * band, y: height - bottom + 14, "text-anchor": "middle" }, String(i)));
  }
  parts.push(svg("text", { class: "axis-label", x: (left + width - right) / 2, y: height - 2, "text-anchor": "middle" }, "iteration"));
  const counts = rounds.map((r) => `iteration ${r.iteration}: ${r.votes.buy} buy, ${r.votes.hold} hold, ${r.votes.quit} quit`);
  chart.setAttribute("aria-label", `Votes of the patrons still in, per iteration: ${counts.join("; ")}.`);
  fill(chart, svg("title", {}, "Votes of the patrons still in, per iteration"), parts);
}

export function auctionView(view, id) {
  const title = h("h1", { tabindex: "-1" }, `Auction ${id}`);
  const liveness = h("p", { class: "liveness", role: "status", id: "liveness" }, "Loading…");
  const summary = h("div");
  const priceChart = svg("svg", { class: "chart", id: "price-chart", viewBox: `0 0 ${CHART.width} ${CHART.height}`, role: "img", "aria-label": "Price asked in each iteration: none yet.", "data-points": "0" });
  const votesChart = svg("svg", { class: "chart", id: "votes-chart", viewBox: `0 0 ${CHART.width} 160`, role: "img", "aria-label": "Votes per iteration: buy, hold, quit" });
  const roundRows = h("tbody");
  const buyerRows = h("tbody");
  const quitterList = h("ul", { class: "quitters", id: "quitters" });
  const fineTuneRows = h("tbody");
  const noneYet = (span) => h("tr", { class: "none-yet-row" }, h("td", { colspan: span, class: "none-yet" }, "none yet"));
  // Before its first iteration an auction has no chart to draw: each says so instead.
  const priceNone = h("p", { class: "none-yet", id: "price-none" }, "none yet");
  const votesNone = h("p", { class: "none-yet", id: "votes-none" }, "none yet");
  const explainRound = h("select", { id: "explain-round" }, h("option", { value: "" }, "none yet"));
  const explainPatron = h("select", { id: "explain-patron" });
  // What the explanation's place says before a vote is shown: what to press for one.
  const explainHint = h("p", { class: "none-yet", id: "explain-hint" }, "None yet: once an iteration is committed, pick it and a patron, then press “Explain the vote”.");
  const explanation = h("div", { id: "explanation", tabindex: "-1" }, explainHint);
  /** Say what to press, while no explanation (nor its loading) replaced the hint. */
  function hint(words) {
    if (explanation.firstChild === explainHint) explainHint.textContent = words;
  }
  const explainStatus = h("p", { class: "visually-hidden", role: "status", id: "explain-status" });
  const roundVotes = h("div", { id: "round-votes" });
  const explainButton = h("button", { type: "submit", disabled: true }, "Explain the vote");
  const explainForm = h(
    "form",
    { class: "filters", id: "explain-form", "aria-label": "Explain a vote" },
    h("label", { for: "explain-round" }, "Iteration ", explainRound),
    h("label", { for: "explain-patron" }, "Patron ", explainPatron),
    explainButton,
  );
  const explainSection = h(
    "section",
    { "aria-labelledby": "explain-heading", id: "explain" },
    h("h2", { id: "explain-heading" }, "Every vote explained"),
    h("p", {}, "Why a patron voted buy, hold or quit in an iteration: its neurons on the row that decides (row 0), averaged over its copies as its vote was. Pick an iteration to see every patron's vote in it, and a patron for its neurons."),
    explainForm,
    explainStatus,
    roundVotes,
    explanation,
  );
  const leftAt = new Map(); // model id -> the iteration it bought or quit in (its last vote)
  /** The patrons who voted in the chosen iteration: those who had not left before it. */
  function listPatrons() {
    if (!head) return;
    const iteration = Number(explainRound.value || 0);
    const picked = explainPatron.value;
    const voters = head.model_ids.filter((modelId) => !(leftAt.get(modelId) < iteration));
    const none = h("option", { value: "" }, ended ? "none" : "none yet");
    explainPatron.replaceChildren(...(voters.length ? voters.map((modelId) => h("option", { value: modelId }, nameOf(modelId))) : [none]));
    if (voters.map(String).includes(picked)) explainPatron.value = picked;
    // No vote to explain before an iteration is committed, or without a patron.
    explainButton.disabled = !explainRound.value || !explainPatron.value;
    if (!explainButton.disabled && !roundVotes.firstChild) hint("Press “Explain the vote” for the picked patron's neurons in the picked iteration, or “Explain iteration n” in the table above for every vote in it.");
  }
  explainRound.addEventListener("change", () => {
    listPatrons();
    showRoundVotes(Number(explainRound.value));
  });
  explainForm.addEventListener("submit", (event) => {
    event.preventDefault();
    if (explainButton.disabled) return;
    showExplanation(Number(explainRound.value), Number(explainPatron.value));
  });
  function pickRound(iteration) {
    explainRound.value = String(iteration);
    listPatrons();
    showRoundVotes(iteration);
    explainPatron.focus();
  }
  /** Every patron's vote in an iteration: its decision logits and its PFC's verdict, each row
   * opening that vote's whole explanation. */
  let votesShown = Promise.resolve(); // the iteration's votes table drawn (or its failure said)
  function showRoundVotes(iteration) {
    fill(roundVotes, h("p", { class: "liveness" }, "Loading…"));
    votesShown = getJSON(`/auctions/${id}/iterations/${iteration}/votes`)
      .then((all) => {
        if (Number(explainRound.value) !== iteration) return; // another iteration was picked meanwhile
        const rows = all.votes.map((v) => {
          names.set(v.model_id, v.participant);
          const open = () => {
            explainPatron.value = String(v.model_id);
            showExplanation(iteration, v.model_id, true);
          };
          return [
            h("span", { class: "free-text" }, v.participant), // a 64-character name wraps
            bidWith(iteration, v),
            h("strong", { class: `vote-word vote-${v.vote}-text` }, v.vote),
            ...fixedApart([v.decision.B, v.decision.L, v.decision.Q]),
            ...fixedApart([v.pfc.T, v.pfc.F]),
            h("button", { type: "button", class: "explain-vote", "data-model": v.model_id, "aria-label": `Its neurons: ${v.participant}, iteration ${iteration}`, onclick: open }, "Its neurons"),
          ];
        });
        const counts = ["buy", "hold", "quit"].map((kind) => `${all.votes.filter((v) => v.vote === kind).length} ${kind}`).join(", ");
        fill(
          roundVotes,
          scrolling(
            table(`Every vote in iteration ${iteration} at price ${recordedPrice(all.row.price)}: ${counts}. B, L, Q are the decision logits (the largest is the vote); T and F the PFC's verdict on it`, ["Patron", "Bid with", "Vote", "B", "L", "Q", "T", "F", "Explain"], rows, { id: "round-votes-table", "data-iteration": iteration }),
            `Every vote in iteration ${iteration} (scrolls)`,
            true,
          ),
        );
        explainStatus.textContent = `Iteration ${iteration}: ${all.votes.length} votes listed, ${counts}.`;
        hint("Press “Its neurons” on a vote above, or “Explain the vote”, for that patron's neurons here.");
      })
      .catch((error) => fill(roundVotes, problem(error)));
  }
  const weightsHash = (iteration, modelId) => `#/auctions/${id}/iterations/${iteration}/votes/${modelId}/weights`;
  /** The version a patron bid with in an iteration, and whether the market had fine-tuned it. */
  function bidWith(iteration, v) {
    // The accessible name is the visible text after the patron's name (WCAG 2.5.3: a voice
    // user says what they see).
    const named = (href, text) => h("a", { href, "aria-label": `${v.participant}: ${text}` }, text);
    if (!v.weights_kept) return named(`#/models/${v.version_id}`, `version ${v.version}, fine-tuned (not kept)`);
    if (v.fine_tuned_after === null) return named(`#/models/${v.version_id}`, `version ${v.version}`);
    return named(weightsHash(iteration, v.model_id), `version ${v.version}, tuned after iteration ${v.fine_tuned_after}`);
  }
  /** Each named neuron's push on B, L and Q (its weight × its value; the logits are linear
   * in them, so the pushes and the bias add up to each logit), and in words what decided the
   * vote against the runner-up. */
  function pushTable(v, decision) {
    const logits = ["B", "L", "Q"];
    const sensors = Object.keys(v.sensor);
    const push = (d, n) => decision[d].weights[n] * v.sensor[n];
    const total = (d) => sensors.reduce((sum, n) => sum + push(d, n), decision[d].bias);
    if (logits.some((d) => Math.abs(total(d) - v.decision[d]) > 1e-6)) return null; // not these weights
    const rows = [...sensors.map((n) => [n, ...logits.map((d) => signedFixed(push(d, n)))]), ["bias", ...logits.map((d) => signedFixed(decision[d].bias))]];
    const won = { buy: "B", hold: "L", quit: "Q" }[v.vote];
    const next = logits.filter((d) => d !== won).reduce((a, b) => (v.decision[a] >= v.decision[b] ? a : b));
    const gaps = [...sensors, "bias"].map((n) => [n, n === "bias" ? decision[won].bias - decision[next].bias : push(won, n) - push(next, n)]);
    const [lead, by] = gaps.reduce((a, b) => (b[1] > a[1] ? b : a));
    const words = `${won} ${fixed(v.decision[won], 4)} against ${next} ${fixed(v.decision[next], 4)}: ${lead === "bias" ? "its bias" : `${lead} (${NEURON_WORDS[lead] || lead})`} pushed ${won} over ${next} the most, by ${fixed(by, 4)}.`;
    return [
      scrolling(table("Why this vote: each neuron's push on each logit (its weight × its value), and the bias; they add up to the logits", ["Neuron", "on B", "on L", "on Q"], rows, { "data-part": "pushes" }), "Why this vote (scrolls sideways)"),
      h("p", { id: "push-words" }, words),
    ];
  }
  const signedFixed = (x) => `${x < 0 ? "−" : "+"}${fixed(Math.abs(x), 4)}`;
  /** What the PFC's verdict says about the vote, in words. */
  function verdictWords(v) {
    const agrees = v.pfc.T >= v.pfc.F;
    const [t, f] = [fixed(v.pfc.T, 4), fixed(v.pfc.F, 4)];
    const judge = "Its prefrontal cortex, which judges the model's own decision (its self-reward),";
    return agrees
      ? `${judge} judged this ${v.vote} right (T ${t} ≥ F ${f}): it agrees with the vote.`
      : `${judge} judged this ${v.vote} wrong (T ${t} < F ${f}): it disagrees with the vote.`;
  }
  let explaining = 0; // the newest explanation asked for: an older answer arriving late is dropped
  /** Show a vote's neurons; ``focus``: the explanation takes the focus once shown (the button
   * pressed stays in the votes' table, far above what it showed). The weights that cast the
   * vote are read first and the explanation drawn once, with its pushes, and after the votes
   * table above it asked for before: a table drawn later above the links would move them from
   * under a press (released elsewhere, it clicks nothing). */
  function showExplanation(iteration, modelId, focus = false) {
    const asked = ++explaining;
    fill(explanation, h("p", { class: "liveness" }, "Loading…"));
    const read = getJSON(`/auctions/${id}/iterations/${iteration}/votes/${modelId}`).then((v) =>
      v.weights_kept
        ? getJSON(`/auctions/${id}/iterations/${v.iteration}/votes/${v.model_id}/weights`)
            .then((w) => [v, w])
            .catch(() => [v, null]) // the logits still stand
        : [v, null],
    );
    const tableDrawn = () => {
      const drawing = votesShown; // another iteration picked meanwhile: its table first
      return drawing.then(() => (drawing === votesShown ? null : tableDrawn()));
    };
    Promise.all([read, tableDrawn()])
      .then(([[v, w]]) => {
        if (asked !== explaining) return;
        names.set(v.model_id, v.participant);
        const pushes = h("div", { id: "pushes" }, w ? pushTable(v, w.manifest.decision) : null);
        const part = (caption, key, values) =>
          table(caption, ["Neuron", "Meaning", "Value"], Object.entries(values).map(([n, x]) => [n, NEURON_WORDS[n] || n, fixed(x, 4)]), { "data-part": key });
        fill(
          explanation,
          h(
            "div",
            { class: "explanation", "data-vote": v.vote },
            h("h3", {}, `${v.participant} (version ${v.version}) voted `, h("strong", { class: `vote-word vote-${v.vote}-text` }, v.vote), ` in iteration ${v.iteration}`),
            facts(Object.entries(v.row).map(([k, x]) => [k, String(x)]), { "aria-label": "The row it voted on: every decimal the network read" }),
            part("External sensor (after its activations)", "sensor", v.sensor),
            part("Decision logits (the largest is the vote)", "decision", v.decision),
            pushes,
            v.judgement ? part("Prefrontal cortex: its judgements of the decision (before their tanh)", "judgement", v.judgement) : null,
            part("Prefrontal cortex: its verdict on the decision", "pfc", v.pfc),
            h("p", { id: "verdict-words" }, verdictWords(v)),
            h(
              "p",
              { id: "voted-weights" },
              v.weights_kept
                ? link(weightsHash(v.iteration, v.model_id), v.fine_tuned_after === null ? `The weights that cast this vote: version ${v.version}'s` : `The weights that cast this vote: version ${v.version} as the market fine-tuned it after iteration ${v.fine_tuned_after}`)
                : `The weights that cast this vote were not kept: this auction fine-tuned this patron inside the market before the server kept fine-tuned weights.`,
              " · ",
              link(`#/models/${v.version_id}`, `Version ${v.version} in the inspector`),
            ),
          ),
        );
        explainStatus.textContent = `${v.participant} voted ${v.vote} in iteration ${v.iteration}: its neurons are shown.`;
        if (focus) explanation.focus();
      })
      .catch((error) => asked === explaining && fill(explanation, problem(error)));
  }
  const fineTuning = h(
    "section",
    { "aria-labelledby": "fine-tuning-heading", id: "fine-tuning", hidden: true },
    h("h2", { id: "fine-tuning-heading" }, "Remote fine-tuning rounds"),
    h("p", {}, "After each of the auction's first iterations the participants fine-tune their own patrons over HTTP; a round waits for their uploads until its deadline."),
    scrolling(
      h(
        "table",
        { class: "list" },
        h("caption", {}, "Each fine-tuning round and how its patrons answered"),
        h("thead", {}, h("tr", {}, ["Round", "After iteration", "Status", "Open", "Answers", "Each patron"].map((t) => h("th", { scope: "col" }, t)))),
        fineTuneRows,
      ),
      "Fine-tuning rounds (scrolls sideways)",
    ),
  );
  view.root.append(
    title,
    liveness,
    summary,
    h(
      "section",
      { "aria-labelledby": "price-heading" },
      h("h2", { id: "price-heading" }, "Price over the iterations"),
      priceNone,
      h("figure", { hidden: true }, scrolling(priceChart, "The price chart (scrolls sideways on a narrow screen)"), h("figcaption", {}, "Each point is the price asked in an iteration; filled larger points are iterations in which fish were sold; while the auction plays, the last point is the next price.")),
    ),
    h(
      "section",
      { "aria-labelledby": "votes-heading" },
      h("h2", { id: "votes-heading" }, "Votes per iteration"),
      votesNone,
      h("figure", { hidden: true }, scrolling(votesChart, "The votes chart (scrolls sideways on a narrow screen)"), h("figcaption", { class: "legend" }, h("span", { class: "key vote-buy" }), "buy ", h("span", { class: "key vote-hold" }), "hold (hatched) ", h("span", { class: "key vote-quit" }), "quit (dotted)")),
    ),
    h(
      "section",
      { "aria-labelledby": "rounds-heading" },
      h("h2", { id: "rounds-heading" }, "Every committed iteration"),
      scrolling(
        h(
          "table",
          { class: "list", id: "rounds", "aria-labelledby": "rounds-heading" }, // named once, by its heading
          h("thead", {}, h("tr", {}, ["Iteration", "Price", "Fish at its start", "Buy", "Hold", "Quit", "Sold", "Quit now", "Why the price moved", "Votes"].map((t) => h("th", { scope: "col" }, t)))),
          roundRows,
        ),
        "Every committed iteration (scrolls)",
        true,
      ),
    ),
    h(
      "section",
      { "aria-labelledby": "buyers-heading" },
      h("h2", { id: "buyers-heading" }, "Buyers"),
      scrolling(
        h(
          "table",
          { class: "list", id: "buyers" },
          h("caption", {}, "Who bought a fish, at what price, with which version"),
          h("thead", {}, h("tr", {}, ["Participant", "Patron (model)", "Version that bought", "Price", "Iteration"].map((t) => h("th", { scope: "col" }, t)))),
          buyerRows,
        ),
        "Buyers (scrolls sideways)",
      ),
    ),
    h("section", { "aria-labelledby": "quitters-heading" }, h("h2", { id: "quitters-heading" }, "Quitters"), quitterList),
    explainSection,
    fineTuning,
  );
  buyerRows.append(noneYet(5));
  roundRows.append(noneYet(10));
  quitterList.append(h("li", { class: "none-yet" }, "none yet"));

  const rounds = [];
  let threshold = PRICE_RULES.threshold; // the stalemate threshold after the iterations shown
  const stoppedBecause = (reason) =>
    reason === "stalemate" ? `stalemate (the price ${fixed(rounds.length ? rounds[rounds.length - 1].next_price : null)} fell below the threshold ${fixed(threshold)})` : stopReason(reason);
  let head = null;
  let drawPending = false;
  let ended = false;

  function fineTuningWords(a) {
    if (a.fine_tune_mode === "remote") return `remote: up to ${a.fine_tune_rounds} rounds in which the participants fine-tune their own patrons, each open up to ${a.round_deadline_s} s`;
    if (a.fine_tune && !a.fine_tune_rounds) return "in the market, after 0 iterations: nobody fine-tunes";
    if (a.fine_tune) return `in the market: after each of its first ${plural(a.fine_tune_rounds, "iteration")}, every patron whose manifest fine-tunes (epochs above 0) fine-tunes itself, and bids on with the result if its re-screening accepts it (every vote links to the weights that cast it)`;
    return "none";
  }

  function showSummary(state) {
    const sold = rounds.reduce((n, r) => n + r.purchases.length, 0);
    const revenue = rounds.reduce((n, r) => n + r.purchases.reduce((m, p) => m + p.price, 0), 0);
    const last = rounds[rounds.length - 1];
    const over = !["pending", "running"].includes(state.status);
    const enrolling = state.status === "pending" && Boolean(head.enroll_until);
    // an enrolling auction's supply is a rarity of the patrons it will have: no count yet
    const neverCounted = over && head.rarity !== null && head.n_initial === 0 && rounds.length === 0;
    const uncounted = enrolling && head.rarity !== null ? "counted when it starts" : neverCounted ? "none: it ended before it started" : null;
    const joined = head.model_ids.map((modelId, i) => link(`#/models/${modelId}`, head.participants[i]));
    const shown = [
      facts(
        [
          ["Status", statusBadge(state.status)],
          ["Fish on sale", uncounted || String(head.n_initial)],
          ["Fish left", uncounted || String(last ? last.n_available_after : head.n_initial)],
          ["Sold", String(sold)],
          ["Purchase rate", uncounted || !head.n_initial ? "—" : `${percent(sold / head.n_initial)} of the fish on sale`],
          ["Patrons", String(head.n_patrons)],
          ["Buyer fraction", head.n_patrons && state.status !== "pending" ? `${percent(sold / head.n_patrons)} of the patrons bought` : "—"],
          ...(enrolling ? [["Joined so far", joined.length ? h("span", { id: "joined" }, ...joined.flatMap((a, i) => (i ? [", ", a] : [a]))) : "none yet"]] : []),
          ["Iterations", String(rounds.length)],
          over ? ["Price asked last", fixed(last ? last.price : null)] : ["Price asked next", fixed(last ? last.next_price : head.price)],
          ["Revenue", fixed(revenue)],
          ["Mean price paid", sold ? fixed(revenue / sold) : "—"],
          ["Stopped because", state.status === "failed" && state.error && !state.stop_reason ? `it failed: ${state.error}` : stoppedBecause(state.stop_reason)],
          ["Supply", head.rarity === null ? `${head.n_initial} fish` : `rarity ${head.rarity}`],
          ["Iteration limit", String(head.max_iterations)],
          ["Buy fraction", BUY_FRACTIONS[head.buy_fraction] || head.buy_fraction],
          ["Item rows", head.rows === 64 ? "64 (the reference's)" : head.rows === 16 ? "16 (the paper's text's)" : String(head.rows)],
          ["Fine-tuning", fineTuningWords(head)],
          ["Seed", String(head.seed)],
          ...(enrolling ? [passed(head.enroll_until) ? ["Took patrons until", `${when(head.enroll_until)} (passed; starting)`] : ["Takes patrons until", when(head.enroll_until)]] : []),
          ["Created", when(head.created_at)],
          ["Started", head.started_at ? when(head.started_at) : over ? "never" : "not yet"],
          ...(over ? [[`Ended (${state.status})`, when(state.finished_at || head.finished_at)]] : []),
        ],
        { id: "auction-summary" },
      ),
      state.error ? h("p", { class: "problem" }, `Failed: ${state.error}`) : null,
    ].filter(Boolean);
    // Drawn again only when it changed (it is asked every few seconds while patrons join): a
    // link under a press or holding the keyboard's focus stays, and a redraw keeps the focus
    // on the link to the same place.
    if (shown.length === summary.childNodes.length && shown.every((node, i) => node.isEqualNode(summary.childNodes[i]))) return;
    const focused = summary.contains(document.activeElement) ? document.activeElement.getAttribute("href") : null;
    fill(summary, ...shown);
    if (focused) [...summary.querySelectorAll("a")].find((a) => a.getAttribute("href") === focused)?.focus();
  }

  const fineTuneRowOf = new Map(); // round number -> its table row, updated in place
  const fineTuneShown = new Map(); // round number -> what its row shows (redrawn on a change)
  /** Why a closed round closed: a round closes on its last answer, at its deadline, or when
   * its auction is cancelled or fails (then at the auction's end). */
  function closedWhy(r) {
    const closed = new Date(r.closed_at).getTime();
    const stopped = ["cancelled", "failed"].includes(head.status) && head.finished_at;
    if (stopped && Math.abs(new Date(head.finished_at).getTime() - closed) < 1000) {
      return head.status === "cancelled" ? "when the auction was cancelled" : "when the auction failed";
    }
    // At its deadline the silent are marked missing (late, once they upload after it); a last
    // answer judged after the deadline closes it later than the deadline too.
    const silent = r.answers.some((a) => a.outcome === "missing" || a.outcome === "late");
    return closed >= new Date(r.deadline).getTime() && silent ? "at its deadline" : "on its last answer";
  }
  let following = false; // the event stream is live
  let openRound = null; // the fine-tuning round open now, as read last
  /** What the live view waits for: the next iteration, or an open round's uploads. */
  function sayFollowing() {
    if (!following || ended) return;
    let words = "Following live: each iteration appears as soon as it is committed.";
    if (openRound) {
      const r = openRound;
      const asked = head.model_ids.filter((modelId) => !(leftAt.get(modelId) <= r.iteration)).length;
      const answered = `(${r.answers.length} of ${asked} answered)`;
      // A deadline gone by the reader's clock, the round still open: the server closes it (or
      // will, once it is back), and the page says so rather than "until" a time past.
      words = passed(r.deadline)
        ? `Following live: fine-tuning round ${r.round}'s deadline ${when(r.deadline)} passed; closing ${answered}.`
        : `Following live: waiting for fine-tuning round ${r.round} until ${when(r.deadline)} ${answered}.`;
    } else if (head && head.status === "pending" && head.enroll_until) {
      words = passed(head.enroll_until)
        ? `Following live: enrollment deadline ${when(head.enroll_until)} passed; starting: the first iteration appears once it starts.`
        : `Following live: taking patrons until ${when(head.enroll_until)}; the first iteration appears once it starts.`;
    }
    if (liveness.textContent !== words) liveness.textContent = words; // a live region: said once
  }
  function showFineTuneRound(r) {
    fineTuning.hidden = false;
    const was = fineTuneShown.get(r.round);
    // A read that left before a newer event arrived never takes the row back: an open round
    // does not reopen, nor lose answers.
    if (was && ((was.status !== "open" && r.status === "open") || r.answers.length < was.answers)) return;
    if (r.status === "open") {
      if (!openRound || r.round >= openRound.round) openRound = r;
    } else if (openRound && openRound.round <= r.round) openRound = null;
    sayFollowing();
    // A round ends at its deadline, or sooner: its last answer, a cancel, a failure. One still
    // open after its deadline by the reader's clock (its close pending, or the server
    // restarting) says the deadline passed: its row is redrawn once it has (read every 3 s).
    const open = r.status === "open" || !r.closed_at ? (passed(r.deadline) ? `deadline ${when(r.deadline)} passed; closing` : `until ${when(r.deadline)}`) : `closed ${when(r.closed_at)} ${closedWhy(r)} (deadline ${when(r.deadline)})`;
    const shows = JSON.stringify(r) + open;
    if (was && was.shows === shows) return; // unchanged: no redraw, no reasons read again
    fineTuneShown.set(r.round, { status: r.status, answers: r.answers.length, shows });
    const outcomes = {};
    for (const a of r.answers) outcomes[a.outcome] = (outcomes[a.outcome] || 0) + 1;
    const nothing = r.status === "open" ? "none yet" : "none";
    const answers = Object.entries(outcomes).map(([outcome, n]) => `${n} ${outcome}`).join(", ") || nothing;
    const each = r.answers.length ? h("ul", { class: "answers" }, r.answers.map((a) => answerItem(a, r))) : h("span", { class: "none-yet" }, nothing);
    const row = tableRow([String(r.round), String(r.iteration), statusBadge(r.status), open, answers, each], { "data-round": r.round });
    const old = fineTuneRowOf.get(r.round);
    if (old) {
      // Brought up to date in place: the row and its links stay the same elements (a press
      // across the update lands, the focus stays), and the reasons opened stay open. A
      // control that had to be replaced gives the focus to its successor.
      const focused = old.contains(document.activeElement) ? document.activeElement : null;
      const kind = focused && (focused.tagName === "SUMMARY" ? "summary" : focused.getAttribute("href") ? `a[href='${focused.getAttribute("href")}']` : null);
      const patron = focused?.closest("li[data-model]");
      const within = patron ? `li[data-model='${patron.dataset.model}'] ` : "";
      for (const open of old.querySelectorAll("li[data-model] details[open]")) {
        row.querySelector(`li[data-model='${open.closest("li").dataset.model}'] details`)?.setAttribute("open", "");
      }
      const shown = patch(old, row);
      fineTuneRowOf.set(r.round, shown);
      if (kind && !shown.contains(document.activeElement)) shown.querySelector(within + kind)?.focus();
    } else {
      fineTuneRows.append(row);
      fineTuneRowOf.set(r.round, row);
    }
  }

  const reasonsOf = new Map(); // an upload's model id -> its stored version, read once
  /** A patron's outcome in a round, linked to the version it bids with; a refused or held
   * upload's screener reasons are read from that stored version. */
  function answerItem(a, r) {
    // An upload of the weights it already had is accepted unscreened: no new version.
    const unchanged = a.outcome === "accepted" && a.uploaded_id === null ? " (unchanged weights, not screened)" : "";
    // Late after a round that closed before its deadline (a cancel, a failure): after the close.
    const early = r.closed_at && new Date(r.closed_at).getTime() < new Date(r.deadline).getTime();
    const words = a.outcome === "late" && early ? `arrived after the round closed ${closedWhy(r)}, not applied` : ANSWER_WORDS[a.outcome];
    const explained = words ? ` (${words})` : "";
    const item = h("li", { "data-key": a.model_id, "data-model": a.model_id, "data-outcome": a.outcome }, `${nameOf(a.model_id)}: ${a.outcome}${unchanged}${explained}, bids with `, link(`#/models/${a.version_id}`, `version ${a.version}`));
    if ((a.outcome === "refused" || a.outcome === "held") && a.uploaded_id !== null) {
      // The reasons fold away (an auction of many rounds repeats them): the first is shown.
      const reasons = h("ul", { class: "reasons" });
      const summary = h("summary", {}, "the screener's reasons");
      const words = a.outcome === "held" ? "upload held for an inspector" : "refused upload";
      const details = h("details", { "data-upload": a.uploaded_id }, summary, reasons);
      item.append(` (${words}: `, link(`#/models/${a.uploaded_id}`, `model ${a.uploaded_id}`), ")", details);
      // The reasons go where this upload's are shown when they arrive: in a row brought up to
      // date since, its own (patched in place) elements, not these.
      const shown = () => {
        const here = fineTuneRowOf.get(r.round)?.querySelector(`li[data-model='${a.model_id}'] details[data-upload='${a.uploaded_id}']`);
        return here ? [...here.children] : [summary, reasons];
      };
      if (!reasonsOf.has(a.uploaded_id)) reasonsOf.set(a.uploaded_id, getJSON(`/models/${a.uploaded_id}`));
      reasonsOf
        .get(a.uploaded_id)
        .then((m) => {
          const [first] = m.reasons;
          const [title, list] = shown();
          if (first) title.textContent = `${first.rule} on ${first.neuron}${m.reasons.length > 1 ? ` and ${m.reasons.length - 1} more` : ""}: the screener's reasons`;
          fill(list, m.reasons.map((reason) => h("li", {}, `${reason.rule} on ${reason.neuron}: ${reason.message}`)));
        })
        .catch((error) => {
          reasonsOf.delete(a.uploaded_id); // read again at the next redraw
          fill(shown()[1], h("li", {}, String(error.message || error)));
        });
    }
    return item;
  }

  const names = new Map(); // model id -> participant, as the events name the patrons
  function nameOf(modelId) {
    return names.get(modelId) || `model ${modelId}`;
  }

  /** A patron who left, linked to the version that bid when it left. */
  function patronLink(p) {
    return link(`#/models/${p.version_id}`, p.participant);
  }

  function readHead(auction) {
    head = auction;
    auction.model_ids.forEach((modelId, i) => names.set(modelId, auction.participants[i]));
    listPatrons();
  }

  // An auction read while it enrolled had no patrons and no fish yet: it is read again while
  // it takes patrons (every few seconds), once it plays (its first iteration) and when it ends,
  // so the summary, the charts and the patron picker show the patrons it has. The read at
  // the end also shows each fine-tuning round as it ended: a closed round can change without
  // an event (an upload after its deadline is recorded late).
  function readHeadAgain(atEnd = false) {
    getJSON(`/auctions/${id}`)
      .then((auction) => {
        readHead(auction);
        sayFollowing(); // an enrolling auction that started: the line says so
        if (atEnd) for (const r of auction.fine_tuning) showFineTuneRound(r);
        scheduleDraw();
        if (auction.status !== "running") showSummary(auction);
      })
      .catch(() => {}); // the stream goes on; the next read will tell
  }
  // A patron's answer in an open fine-tuning round, and an upload recorded late after one
  // closed, send no event: while a remote auction plays on (its first iteration shown), its
  // rounds are read again every few seconds, as an enrolling auction's patrons are, while the
  // tab is shown; a row is redrawn only when it changed.
  let rereading = false; // one read at a time: a slow server is not asked again meanwhile
  const rereads = setInterval(() => {
    if (!head || ended || document.hidden || rereading) return;
    if (head.status === "pending" && head.enroll_until) readHeadAgain();
    else if (head.fine_tune_mode === "remote" && fineTuneRowOf.size) {
      rereading = true;
      getJSON(`/auctions/${id}`)
        .then((auction) => {
          if (!ended) for (const r of auction.fine_tuning) showFineTuneRound(r);
        })
        .catch(() => {}) // the next read will tell
        .finally(() => {
          rereading = false;
        });
    }
  }, 3000);
  view.onLeave(() => clearInterval(rereads));

  function addRound(row) {
    if (row.iteration !== rounds.length) return; // the stream never skips or repeats; a guard
    if (row.iteration === 0 && head.status === "pending") readHeadAgain();
    rounds.push(row);
    if (rounds.length === 1) {
      roundRows.replaceChildren();
      explainRound.replaceChildren();
    }
    const move = priceMove(row, threshold);
    threshold = move.threshold;
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
        move.words,
        h("button", { type: "button", class: "explain-round", "data-iteration": row.iteration, onclick: () => pickRound(row.iteration) }, `Explain iteration ${row.iteration}`),
      ]),
    );
    for (const p of [...row.purchases, ...row.quits]) {
      names.set(p.model_id, p.participant);
      leftAt.set(p.model_id, row.iteration);
    }
    explainRound.append(h("option", { value: row.iteration }, `iteration ${row.iteration}`));
    if (rounds.length === 1) listPatrons(); // a vote to explain now
    if (row.purchases.length) buyerRows.querySelector(".none-yet-row")?.remove();
    if (row.quits.length) quitterList.querySelector(".none-yet")?.remove();
    for (const p of row.purchases) {
      // the patron (the auction's model_ids, the API's buyers' model_id), then the version that
      // bought: after remote rounds an upload, a model of its own
      const bought = link(`#/models/${p.version_id}`, `version ${p.version} (model ${p.version_id})`);
      buyerRows.append(tableRow([patronLink(p), link(`#/models/${p.model_id}`, String(p.model_id)), bought, fixed(p.price), String(row.iteration)]));
    }
    for (const q of row.quits) quitterList.append(h("li", {}, patronLink(q), ` (version ${q.version}, iteration ${row.iteration})`));
    scheduleDraw();
  }

  /** The iterations an auction's GET already holds, as its stream would send them. */
  function addRoundsOf(auction) {
    for (const row of auction.history.slice(rounds.length)) {
      const here = (p) => p.iteration === row.iteration;
      addRound({ ...row, purchases: auction.buyers.filter(here), quits: auction.quitter_details.filter(here) });
    }
    for (const r of auction.fine_tuning) showFineTuneRound(r);
  }

  // Iterations can arrive in a burst (a finished auction sends them all at once): draw once a frame.
  function draw() {
    drawPending = false;
    if (rounds.length === 0) return;
    for (const none of [priceNone, votesNone]) {
      none.hidden = true;
      none.nextElementSibling.hidden = false; // its figure
    }
    // the next price while it plays; once it ended, a price never asked is not drawn
    const playing = ["pending", "running"].includes(head.status);
    drawPriceChart(priceChart, rounds, playing ? rounds[rounds.length - 1].next_price : null);
    drawVotesChart(votesChart, rounds, head.n_patrons);
  }
  function scheduleDraw() {
    if (!drawPending) requestAnimationFrame(draw);
    drawPending = true;
    // an auction read as ended is summed up as it ended, with the iterations added so far
    if (!ended) showSummary(["pending", "running"].includes(head.status) ? { status: head.status === "pending" && rounds.length === 0 ? "pending" : "running", stop_reason: null, error: null } : head);
  }

  function end(outcome) {
    ended = true;
    readHeadAgain(true); // once more: it may have enrolled, or a closed round changed, meanwhile
    draw();
    showSummary(outcome);
    if (rounds.length === 0) {
      buyerRows.replaceChildren();
      quitterList.replaceChildren();
      // It ended without an iteration: nothing more will come.
      for (const none of [priceNone, votesNone, roundRows.querySelector("td"), explainRound.options[0]]) none.textContent = "none: no iteration was played";
      fill(explanation, h("p", { class: "none-yet" }, "None: no iteration was played."));
    }
    quitterList.querySelector(".none-yet")?.remove();
    if (quitterList.children.length === 0) quitterList.append(h("li", {}, "nobody quit"));
    buyerRows.querySelector(".none-yet-row")?.remove();
    if (buyerRows.children.length === 0) buyerRows.append(tableRow(["nobody bought a fish", "", "", "", ""]));
    listPatrons();
    // "cancelled" says it all: its stop reason would only repeat it
    const why = outcome.stop_reason && !(outcome.stop_reason === "cancelled" && outcome.status === "cancelled") ? `, ${stoppedBecause(outcome.stop_reason)}` : "";
    const played = outcome.iterations ? `${outcome.n_sold} of ${outcome.n_initial} fish sold in ${plural(outcome.iterations, "iteration")}` : "no iteration played";
    liveness.textContent = `Ended: ${outcome.status}${why}; ${played}.`;
  }

  /** The ``end`` event an ended auction's stream would send, from its GET. */
  function endOf(auction) {
    return {
      status: auction.status,
      iterations: auction.history.length,
      price: auction.price,
      n_available: auction.n_available,
      n_initial: auction.n_initial,
      n_sold: auction.n_initial - auction.n_available,
      stop_reason: auction.stop_reason,
      error: auction.error,
      finished_at: auction.finished_at,
    };
  }

  // Read until it can be (a server out of reach for a while, say), then followed live.
  firstRead(view, () => getJSON(`/auctions/${id}`), {
    at: liveness,
    missing: () => notFound(view.root, `Auction ${id}`, ["#/", "All auctions"]),
    use: (auction) => {
      readHead(auction);
      showSummary(auction);
      drawPriceChart(priceChart, [], auction.price);
      addRoundsOf(auction);
      const readUpTo = () => (rounds.length ? String(rounds.length - 1) : null);
      const stream = follow(
        `/auctions/${id}/events?rounds=true`,
        { iteration: addRound, round: showFineTuneRound, end },
        (state) => {
          following = state === "live";
          if (state === "live") sayFollowing();
          if (state === "connecting") liveness.textContent = "Connecting to live updates…";
          if (state === "waiting") liveness.textContent = "Connection lost; resuming where it left off…";
          if (state === "paused") liveness.textContent = "Paused while this tab is hidden; it catches up when shown.";
          if (state !== "refused") return;
          // No stream to be had (too many open from this address, say): read the auction
          // instead, and resume the stream after what that read showed.
          liveness.textContent = `The server refused live updates; the auction as read at ${new Date().toLocaleTimeString()}, read again every few seconds.`;
          getJSON(`/auctions/${id}`)
            .then((now) => {
              addRoundsOf(now);
              stream.readUpTo(readUpTo());
              if (!["pending", "running"].includes(now.status)) {
                stream.stop();
                end(endOf(now));
              }
            })
            .catch(() => {});
        },
        readUpTo(),
      );
      view.onLeave(stream.stop);
    },
  });
}
