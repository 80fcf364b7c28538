// Models: the list with verdicts, a participant's versions, and the inspector's view of one
// model: the Fish Sale Negotiator drawn neuron by neuron, every weight by name and sign, and
// each screener reason on the neuron it names.

import { firstRead, getJSON, keepCurrent, pager, withQuery } from "./api.js";
import { facts, fill, fixed, fixedApart, h, isMissing, link, notFound, plural, problem, scrolling, signed, svg, table, tableRow, when } from "./dom.js";
import { shown } from "./results.js";

const NAME_PATTERN = /^[A-Za-z0-9_.-]+$/; // participant names the API accepts
const TINY = 0.0011; // |weight| at or below the design's δ = 0.001: drawn faint

function verdictBadge(model) {
  // an inspector's decision reads as one, in the model page's words (admitted, refused), not
  // as the screener's own verdict
  const words = model.inspected ? (model.accepted ? "admitted" : "refused") : model.verdict;
  const badge = h("span", { class: `badge verdict-${model.verdict}` }, words);
  if (model.inspected) return h("span", {}, badge, " by an inspector");
  // a held model came to the inspector either from the screener or by its participant's appeal
  return model.appealed ? h("span", {}, badge, " on appeal") : badge;
}

function participantLink(name) {
  // only names the API could have accepted get a link; any other text stays plain text
  return NAME_PATTERN.test(name) ? link(`#/participants/${encodeURIComponent(name)}`, name) : name;
}

function modelRow(m) {
  return tableRow([
    link(`#/models/${m.id}`, `Model ${m.id}`),
    participantLink(m.participant),
    String(m.version),
    verdictBadge(m),
    m.rules.length ? m.rules.join(", ") : "—",
    m.description ? h("q", { class: "description-preview", dir: "auto" }, m.description) : "—", // quoted: the participant's words
    when(m.created_at),
  ]);
}

const MODEL_HEADERS = ["Model", "Participant", "Version", "Verdict", "Screener rules that fired", "Description (the participant's words)", "Submitted"];

function modelTable(caption, id) {
  const rows = h("tbody");
  const node = h(
    "table",
    { class: "list", id },
    h("caption", {}, caption),
    h("thead", {}, h("tr", {}, MODEL_HEADERS.map((text) => h("th", { scope: "col" }, text)))),
    rows,
  );
  return { node, rows };
}

export function modelList(view, query) {
  const participant = query.get("participant") || "";
  const accepted = query.get("accepted") || ""; // older links: true, or false (refused or held)
  const status = query.get("status") || "";
  view.root.append(h("h1", { tabindex: "-1" }, "Models"));
  if (!["", "true", "false"].includes(accepted)) {
    view.root.append(problem(`"accepted" is true or false, not "${accepted}".`), link("#/models", "All models"));
    return;
  }
  if (!["", "accepted", "held", "refused"].includes(status)) {
    view.root.append(problem(`"status" is accepted, held or refused, not "${status}".`), link("#/models", "All models"));
    return;
  }
  const nameInput = h("input", { id: "filter-participant", name: "participant", value: participant, pattern: NAME_PATTERN.source, maxlength: "64", autocomplete: "off" });
  const verdictSelect = h(
    "select",
    { id: "filter-verdict", name: "status" },
    h("option", { value: "", selected: status === "" }, "any status"),
    h("option", { value: "accepted", selected: status === "accepted" }, "accepted"),
    h("option", { value: "held", selected: status === "held" }, "held for an inspector"),
    h("option", { value: "refused", selected: status === "refused" }, "refused (rejected)"),
  );
  const form = h(
    "form",
    { role: "search", class: "filters" },
    h("label", { for: "filter-participant" }, "Participant"),
    nameInput,
    h("label", { for: "filter-verdict" }, "Status"),
    verdictSelect,
    h("button", { type: "submit" }, "Filter"),
  );
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    location.hash = withQuery("#/models", { participant: nameInput.value.trim(), status: verdictSelect.value });
  });
  const shownFilter = [participant && `participant ${participant}`, status && `status ${status}`, accepted && `accepted ${accepted}`].filter(Boolean).join(", ");
  const { node, rows } = modelTable(`Model versions${shownFilter ? ` (${shownFilter})` : ""}, newest first`, "model-list");
  const filtered = participant || accepted || status;
  const none = h(
    "p",
    { class: "none-yet", id: "no-models", hidden: true },
    participant ? `None: no version of "${participant}"${status ? ` is ${status}` : ""} (or no such participant).` : filtered ? "None with this status." : "None yet.",
  );
  // As the auctions list: the first page is read again every few seconds while the tab is
  // shown, a version moving on in place (a held one admitted), new ones offered by a button
  // above the rows and added at the top when it is pressed.
  const params = { participant, accepted, status };
  const current = keepCurrent(view, { path: "/models", params, newestFirst: true, rows, rowFor: modelRow, noun: "models", empty: none });
  const pages = pager("/models", params, current.add);
  view.root.append(form, current.news, scrolling(node, "Model versions (scrolls sideways)"), none, pages.box);
  pages
    .load()
    .then(() => current.read())
    .catch((error) => view.root.append(problem(error)));
}

const OUTCOMES = {
  bought: (e) => `bought a fish at ${fixed(e.price)} in iteration ${e.iteration}`,
  quit: (e) => `quit in iteration ${e.iteration}`,
  joined: () => "joined; the auction has not started",
  bidding: () => "still bidding",
  stayed: () => "stayed to the end without buying",
  // (whether it had bid yet: an auction can stop before its first iteration)
  stopped: (e) => (e.auction_status === "cancelled" ? "still in when the operator cancelled the auction" : "still in when the auction failed"),
};

/** The auctions a participant's models entered, newest first, and how each patron left. */
function entryTable(entries, versions) {
  // A model among the newest versions listed names its version number too (no other read).
  const versionOf = new Map(versions.map((m) => [m.id, m.version]));
  const model = (modelId) => `Model ${modelId}${versionOf.has(modelId) ? ` (version ${versionOf.get(modelId)})` : ""}`;
  const rows = entries.map((e) => [
    link(`#/auctions/${e.auction_id}`, `Auction ${e.auction_id}`),
    e.auction_status,
    link(`#/models/${e.model_id}`, model(e.model_id)),
    e.bidding_model_id === e.model_id ? "the same" : link(`#/models/${e.bidding_model_id}`, model(e.bidding_model_id)),
    OUTCOMES[e.outcome](e),
  ]);
  return table("Auctions its models entered, newest first", ["Auction", "Status", "Entered with", "Bid with (after remote fine-tuning)", "Outcome"], rows, { class: "list", id: "entries" });
}

export function participantView(view, name) {
  const title = h("h1", { tabindex: "-1" }, `Participant ${name}`);
  view.root.append(title);
  getJSON(`/participants/${encodeURIComponent(name)}`)
    .then((p) => {
      // The address may spell the name in any case: the page names it as it was registered.
      if (p.name !== name) {
        title.textContent = `Participant ${p.name}`;
        if (title.isConnected) document.title = `Participant ${p.name} · srd-auction`;
      }
      const all = p.versions.length === p.n_versions;
      const caption = all ? `Its ${plural(p.n_versions, "version")}, newest first` : `The newest ${p.versions.length} of its ${p.n_versions} versions`;
      const { node, rows } = modelTable(caption, "versions");
      p.versions.forEach((m) => rows.append(modelRow(m)));
      view.root.append(
        facts([
          ["Registered", when(p.created_at)],
          ["Versions", String(p.n_versions)],
        ]),
        h(
          "section",
          { "aria-labelledby": "versions-heading" },
          h("h2", { id: "versions-heading" }, "Versions"),
          scrolling(node, "Versions (scrolls sideways)"),
          h("p", {}, link(`#/models?participant=${encodeURIComponent(p.name)}`, "All versions, page by page")),
        ),
        h(
          "section",
          { "aria-labelledby": "entries-heading" },
          h("h2", { id: "entries-heading" }, "Auctions"),
          p.auctions.length
            ? scrolling(entryTable(p.auctions, p.versions), "Auctions (scrolls sideways)")
            : h("p", { id: "entries" }, "Its models have entered no auction yet."),
        ),
      );
    })
    .catch((error) => {
      if (isMissing(error)) notFound(view.root, `Participant ${name}`, ["#/models", "All models"]);
      else view.root.append(problem(error));
    });
}

// --- the inspector's view -------------------------------------------------------------------

/** The network's layers, as the manifest names them (served from the Python definitions). */
let anatomy = null;
async function loadAnatomy() {
  anatomy = anatomy || (await getJSON("/ui/neurons.json"));
  return anatomy;
}

/** The manifest's neurons: {PG: {layer, weights: {price: 0.2, ...}, bias, activation}, ...}. */
function neuronsOf(manifest) {
  const out = {};
  const add = (layer, group) => {
    for (const [name, neuron] of Object.entries(group)) out[name] = { layer, ...neuron };
  };
  add("external_sensor", manifest.external_sensor);
  add("decision", manifest.decision);
  add("judgement", manifest.pfc.judgement);
  add("verdict", manifest.pfc.verdict);
  return out;
}

/**
 * One layered drawing: columns of nodes, an edge for every weight (blue solid = positive,
 * red dashed = negative, width = size), flagged neurons ringed with their count of reasons.
 */
function network({ id, label, columns, neurons, reasonsByNeuron, sourceLabel, onPick }) {
  const width = 640;
  const gap = 44;
  const tallest = Math.max(...columns.map((c) => c.names.length));
  const height = tallest * gap + 56;
  const xs = columns.map((_, i) => 70 + (i * (width - 140)) / (columns.length - 1));
  const place = {};
  columns.forEach((column, i) => {
    const top = (height - column.names.length * gap) / 2 + gap / 2 + 10;
    column.names.forEach((name, k) => {
      place[`${i}:${name}`] = { x: xs[i], y: top + k * gap };
    });
  });
  const edges = [];
  const nodes = [];
  columns.forEach((column, i) => {
    if (i === 0) return;
    const weights = column.names.map((name) => neurons[name].weights);
    const largest = Math.max(...weights.flatMap((w) => Object.values(w).map(Math.abs)), 1e-9);
    column.names.forEach((target, k) => {
      for (const [source, w] of Object.entries(weights[k])) {
        const a = place[`${i - 1}:${source}`];
        const b = place[`${i}:${target}`];
        if (!a || !b || w === 0) continue; // a cut connection is drawn as missing
        const kind = Math.abs(w) <= TINY ? "tiny" : w > 0 ? "pos" : "neg";
        edges.push(
          svg(
            "line",
            { class: `edge ${kind}`, x1: a.x + 17, y1: a.y, x2: b.x - 17, y2: b.y, "stroke-width": (0.6 + (3.4 * Math.abs(w)) / largest).toFixed(2), "data-edge": `${source}->${target}`, "data-weight": w },
            svg("title", {}, `${sourceLabel(source)} → ${target}: ${signed(w)}`),
          ),
        );
      }
    });
  });
  columns.forEach((column, i) => {
    nodes.push(svg("text", { class: "column-label", x: xs[i], y: 16, "text-anchor": "middle" }, column.label));
    column.names.forEach((name) => {
      const { x, y } = place[`${i}:${name}`];
      const isNeuron = i > 0 || column.neurons;
      const reasons = isNeuron ? reasonsByNeuron[name] || [] : [];
      const shapes = [
        svg("circle", { cx: x, cy: y, r: 17 }),
        svg("text", { x, y: y + 4, "text-anchor": "middle" }, i === 0 && !column.neurons ? column.short(name) : name),
      ];
      // The count sits beside the focusable neuron, not in it: its name already says the count.
      const badge = reasons.length
        ? svg("g", { class: "node badge", "aria-hidden": "true" }, svg("circle", { class: "badge-dot", cx: x + 14, cy: y - 14, r: 9 }), svg("text", { class: "badge-count", x: x + 14, y: y - 10.5, "text-anchor": "middle" }, String(reasons.length)))
        : null;
      if (!isNeuron) {
        nodes.push(svg("g", { class: "node input", "data-input": name }, svg("title", {}, name), shapes));
        return;
      }
      if (column.repeats) {
        // a neuron of another drawing, repeated as a source: its control is there (one tab
        // stop per neuron, not two that open the same card)
        nodes.push(svg("g", { class: "node neuron repeat", "data-repeats": name }, svg("title", {}, `${name} (select it in ${column.repeats})`), shapes), badge);
        return;
      }
      const words = reasons.length ? `${reasons.length} screener reason${reasons.length > 1 ? "s" : ""}` : "no screener reason";
      const group = svg(
        "g",
        { class: reasons.length ? "node neuron flagged" : "node neuron", "data-neuron": name, tabindex: "0", role: "button", "aria-label": `${name}: ${words}; show its weights` },
        svg("title", {}, `${name}: ${words}`),
        shapes,
      );
      group.addEventListener("click", () => onPick(name));
      group.addEventListener("keydown", (event) => {
        if (event.key === "Enter" || event.key === " ") {
          event.preventDefault();
          onPick(name);
        }
      });
      nodes.push(group, badge);
    });
  });
  return svg("svg", { class: "network", id, viewBox: `0 0 ${width} ${height}`, role: "group", "aria-label": label }, edges, nodes);
}

/** What a weight does to its neuron's output, through the neuron's activation: a threshold
 * (and a decision logit) rises with its argument, a below-threshold neuron falls as it rises,
 * and a selective one peaks at its centre, so a weight only moves it toward or past the peak. */
function effect(w, kind) {
  if (w === 0) return "none (cut)";
  if (Math.abs(w) <= TINY) return "barely (δ)";
  if (kind === "selective") return `${w > 0 ? "raises" : "lowers"} its argument: toward or past the peak`;
  if (kind === "below_threshold") return w > 0 ? "inhibits (it falls as its argument rises)" : "excites (it rises as its argument falls)";
  return w > 0 ? "excites" : "inhibits";
}

function weightTable(name, neuron, sourceLabel) {
  const kind = neuron.activation ? neuron.activation.kind : null;
  const rows = Object.entries(neuron.weights).map(([source, w]) => [
    sourceLabel(source),
    h("span", { class: w > 0 ? "w-pos" : w < 0 ? "w-neg" : "" }, signed(w)),
    effect(w, kind),
  ]);
  rows.push(["bias", h("span", { class: neuron.bias > 0 ? "w-pos" : neuron.bias < 0 ? "w-neg" : "" }, signed(neuron.bias)), "constant"]);
  return table(`Weights into ${name}`, ["From", "Weight", "Effect"], rows, { class: "weights", "data-weights-of": name });
}

function activationText(activation) {
  if (!activation) return null;
  const { kind, ...numbers } = activation;
  // six significant digits, as a fine-tuned value reads (85.2289, not 85.22890989664344)
  const parameters = Object.entries(numbers)
    .map(([k, v]) => `${k} = ${typeof v === "number" ? Number(v.toPrecision(6)) : v}`)
    .join(", ");
  return h("p", { class: "activation" }, `Activation: ${kind.replace("_", " ")} (${parameters})`);
}

function reasonList(reasons) {
  return h(
    "ul",
    { class: "reasons" },
    reasons.map((r) => h("li", {}, h("strong", {}, r.rule), ": ", r.message)),
  );
}

function neuronCard(name, neuron, roles, reasons, sourceLabel) {
  return h(
    "article",
    { class: reasons.length ? "neuron-card flagged" : "neuron-card", id: `neuron-${name}`, tabindex: "-1", "data-neuron": name },
    h("h4", {}, `${name}: ${roles[name] || ""}`, reasons.length ? h("span", { class: "badge verdict-rejected" }, `${reasons.length} reason${reasons.length > 1 ? "s" : ""}`) : null),
    reasons.length ? reasonList(reasons) : h("p", { class: "quiet" }, "The screener found nothing wrong here."),
    weightTable(name, neuron, sourceLabel),
    activationText(neuron.activation),
  );
}

/** Who decided the model's status, and why: the screener, or an inspector after it (the last
 * decision of its audit log), or an appeal waiting for one. */
function verdictBanner(model, flagged) {
  const banner = (kind, strong, ...words) => h("p", { class: `verdict ${kind}`, id: "verdict" }, h("strong", {}, strong), ...words);
  const last = model.reviews[model.reviews.length - 1];
  const why = model.reasons.length ? `${model.reasons.length} reason${model.reasons.length === 1 ? "" : "s"}${flagged.length ? ` on ${flagged.join(", ")}` : ""}` : "no rule broken";
  if (model.status === "held") {
    const decide = link(`#/reviews/${model.id}`, "Its inspection page (inspectors)");
    return last && last.decision === "appeal"
      ? banner("held", "Held", " for an inspector: its participant appealed the screener's refusal (", why, "). It enters no auction until admitted. ", decide)
      : banner("held", "Held", " for an inspector: the screener's deciding evidence lies within the review margin of its bar. It enters no auction until admitted. ", decide);
  }
  if (last && last.decision !== "appeal") {
    const who = [`${last.decision === "admit" ? "Admitted" : "Refused"} by inspector `, h("span", { class: "free-text" }, last.inspector), ` on ${when(last.at)}`];
    const appealed = model.reviews.some((r) => r.decision === "appeal");
    const before = appealed
      ? `the screener had refused it (${why}) and its participant appealed`
      : "the screener had held it: its deciding evidence lay within the review margin of its bar";
    return model.accepted
      ? banner("accepted", ...who, `: it may enter auctions (${before}).`)
      : banner("rejected", ...who, `: it can never enter an auction (${before}).`);
  }
  return model.accepted
    ? banner("accepted", "Accepted", " by the screener: every weight reads as its neuron's meaning asks.")
    : banner("rejected", "Rejected", ` by the screener: ${why}. It enters no auction: its participant may appeal once (POST /models/${model.id}/appeal), and an inspector who admits it lets it in.`);
}

/** The verdict banner of ``model`` as it stands (after an inspector's decision, say). */
export function verdictNow(model) {
  const neurons = neuronsOf(model.manifest);
  return verdictBanner(model, [...new Set(model.reasons.map((r) => r.neuron).filter((n) => neurons[n]))]);
}

/** A measurement and its bar with 4 decimals, or more (up to 8) where the two would look
 * alike: "5.091843 against 5.091783", never "5.0918 against 5.0918". */
export function measuredAndBar(e) {
  if (e.measured === null || e.bar === null) return [fixed(e.measured, 4), fixed(e.bar, 4)];
  return fixedApart([e.measured, e.bar], 4);
}

/** How far a priced measurement lies from its bar, on which side: "missed by 0.0043", with
 * as many decimals as it takes to tell the two apart. */
export function by(e) {
  const digits = Math.max(4, measuredAndBar(e)[0].split(".")[1]?.length || 0);
  return `${e.passed ? "passed" : "missed"} by ${fixed(Math.abs(e.measured - e.bar), digits)}`;
}

/** Every bar the screener held a model to: its ``evidence``, one row a bar. */
export function evidenceTable(model) {
  const auctions = (e) => (e.detail.test_auctions ? `, ${e.detail.test_auctions} test auctions` : "");
  const priced = (e) => e.units === "price" && e.measured !== null && e.bar !== null;
  // A missed bar says why in the screener's words: its evidence's finding, or else the reason
  // the screener gave under the bar's name.
  const reasonOf = (e) => model.reasons.find((r) => r.rule === (e.detail.check || e.test))?.message;
  const finding = (e) => (e.passed ? "" : e.detail.finding || reasonOf(e) || "");
  const rows = model.evidence.map((e) => [e.test, (e.detail.version || e.detail.check || "") + auctions(e), ...measuredAndBar(e), `${e.side} (${e.units})`, priced(e) ? by(e) : e.passed ? "passed" : "missed", finding(e)]);
  return scrolling(table("Every bar the model was held to", ["Test", "Version", "Measured", "Bar", "Side", "Result", "Why missed"], rows, { id: "evidence-table" }), "Every bar (scrolls sideways)");
}

/** A model's audit log: appeals and inspectors' decisions, oldest first. */
export function auditLog(reviews) {
  const words = { admit: "admitted", refuse: "refused", appeal: "appealed" };
  return h(
    "section",
    { "aria-labelledby": "audit-heading", id: "model-audit" },
    h("h2", { id: "audit-heading" }, "Review history"),
    h("ol", { class: "audit" }, reviews.map((r) => h("li", {}, `${when(r.at)}: `, h("span", { class: "free-text" }, r.inspector), ` ${words[r.decision]}`, r.note ? [": ", h("q", { class: "free-text" }, r.note)] : null))),
  );
}

/**
 * The drawing of ``manifest`` and every weight, by name and sign: ``reasons`` (the screener's)
 * ring their neurons. ``flagged`` names the neurons ringed.
 */
function drawnNeurons(manifest, reasons, a, { screened = true } = {}) {
  const neurons = neuronsOf(manifest);
  const reasonsByNeuron = {};
  const unplaced = [];
  for (const reason of reasons) {
    if (neurons[reason.neuron]) (reasonsByNeuron[reason.neuron] ||= []).push(reason);
    else unplaced.push(reason);
  }
  const pick = (name) => {
    const card = document.getElementById(`neuron-${name}`);
    if (card) {
      card.scrollIntoView({ block: "start" });
      card.focus();
    }
  };
  const input = (name) => a.input_words[name] || name;
  const short = (name) => a.input_short[name] || name;
  const decisionPath = network({
    id: "network-decision",
    label: "The decision path: inputs, external sensor, decision",
    columns: [
      { label: "inputs", names: a.inputs, short },
      { label: "external sensor", names: a.sensor },
      { label: "decision", names: a.decision },
    ],
    neurons,
    reasonsByNeuron,
    sourceLabel: input,
    onPick: pick,
  });
  const pfcPath = network({
    id: "network-pfc",
    label: "The self-judge: prefrontal cortex judgements and verdicts",
    columns: [
      { label: "softmax of", names: a.pfc_sources, neurons: true, repeats: "the decision path" },
      { label: "judgement", names: a.judgement },
      { label: "verdict", names: a.verdict },
    ],
    neurons,
    reasonsByNeuron,
    sourceLabel: (name) => name,
    onPick: pick,
  });
  const layer = (heading, names, sourceLabel) =>
    h("section", { class: "layer" }, h("h3", {}, heading), h("div", { class: "cards" }, names.map((n) => neuronCard(n, neurons[n], a.roles, reasonsByNeuron[n] || [], sourceLabel))));
  return {
    flagged: Object.keys(reasonsByNeuron),
    sections: [
      h(
        "section",
        { "aria-labelledby": "drawing-heading" },
        h("h2", { id: "drawing-heading" }, "The negotiator, neuron by neuron"),
        h("p", { class: "legend" }, h("span", { class: "key edge-pos" }), "positive weight ", h("span", { class: "key edge-neg" }), "negative weight (dashed) ", h("span", { class: "key edge-tiny" }), `δ-sized weight; line width grows with the weight, a weight of 0 is not drawn.${screened ? " A red ring marks a neuron the screener objects to." : ""} Select a neuron to read its weights.`),
        h("figure", {}, scrolling(decisionPath, "The decision path drawing (scrolls sideways)"), h("figcaption", {}, "Decision: the inputs feed the external sensor PG, SZ, LSR, ST, which feeds buy B, hold L and quit Q.")),
        h("figure", {}, scrolling(pfcPath, "The self-judge drawing (scrolls sideways)"), h("figcaption", {}, "Self-judge: the prefrontal cortex reads the softmax of all seven and judges PGL, BC, FQ, then the verdicts T (right) and F (wrong).")),
      ),
      h(
        "section",
        { "aria-labelledby": "weights-heading" },
        h("h2", { id: "weights-heading" }, "Every weight, by name and sign"),
        layer("External sensor", a.sensor, input),
        layer("Decision", a.decision, (n) => n),
        layer("Prefrontal cortex: judgements", a.judgement, (n) => `softmax ${n}`),
        layer("Prefrontal cortex: verdicts", a.verdict, (n) => `tanh ${n}`),
        unplaced.length ? h("section", { class: "layer" }, h("h3", {}, "Reasons about the model as a whole"), reasonList(unplaced)) : null,
      ),
    ],
  };
}

/** How a manifest's numbers make, learns and judges: augmentation, fine-tuning, the PFC. */
function settingsFacts(manifest, first) {
  return facts([
    ...first,
    ["Augmentation", `${manifest.augmentation.copies} copies, noise σ ${shown("noise_std", manifest.augmentation.noise_std)}, noiseless: ${manifest.augmentation.noiseless_inputs.join(", ") || "none"}`],
    ["Fine-tuning", `${plural(manifest.fine_tuning.epochs, "epoch")}, batch ${manifest.fine_tuning.batch_size}, learning rate ${shown("learning_rate", manifest.fine_tuning.learning_rate)}`],
    ["PFC trainable", manifest.pfc.trainable ? "yes" : "no"],
  ]);
}

/**
 * The inspector's view of model ``id``. ``extra(model)``, if given, returns nodes shown after
 * the verdict (the review page's evidence and decision); ``heading`` prefixes the title.
 */
export function inspectorView(view, id, { extra = null, heading = "Model", evidence = true } = {}) {
  const title = h("h1", { tabindex: "-1" }, `${heading} ${id}`);
  const loading = h("p", { class: "liveness" }, "Loading…");
  view.root.append(title, loading);
  // Read until it can be (a server out of reach for a while, say).
  firstRead(view, () => Promise.all([getJSON(`/models/${id}`), loadAnatomy()]), {
    at: loading,
    missing: () => notFound(view.root, `Model ${id}`, ["#/models", "All models"]),
    use: ([model, a]) => {
      loading.remove();
      const manifest = model.manifest;
      fill(title, `${heading} ${model.id}: `, model.participant, ` version ${model.version}`);
      const drawn = drawnNeurons(manifest, model.reasons, a);
      view.root.append(
        verdictBanner(model, drawn.flagged),
        // Its reasons right under the verdict (each neuron's card below repeats its own).
        ...(model.reasons.length ? [h("section", { "aria-labelledby": "reasons-heading", id: "model-reasons" }, h("h2", { id: "reasons-heading" }, "The screener's reasons"), h("ul", { class: "reasons" }, model.reasons.map((r) => h("li", {}, h("strong", {}, r.neuron), ` (${r.rule}): `, r.message))))] : []),
        ...(model.reviews.length ? [auditLog(model.reviews)] : []),
        ...(extra ? extra(model) : []),
        // The participant's own words, quoted under a heading that says whose they are: a
        // description cannot pass for the screener's or an inspector's text.
        h(
          "section",
          { "aria-labelledby": "description-heading", id: "model-description" },
          h("h2", { id: "description-heading" }, "Description, in the participant's words"),
          manifest.description ? h("blockquote", { class: "description", id: "description", dir: "auto" }, manifest.description) : h("p", { class: "none-yet", id: "description" }, "None given."),
        ),
        settingsFacts(manifest, [
          ["Participant", participantLink(model.participant)],
          ["Submitted", when(model.created_at)],
          ["Auctions entered", model.auctions.length ? h("span", { id: "model-auctions" }, model.auctions.flatMap((a, i) => [i ? ", " : "", link(`#/auctions/${a}`, `auction ${a}`)]), " (newest first)") : h("span", { id: "model-auctions" }, model.auction_id !== null && model.auction_id !== undefined ? `none as a patron of its own: an upload bids for its patron, model ${model.patron_id ?? model.parent_id}, in the auction it was uploaded in, when that round accepted it` : "none yet")],
          // An upload of a remote fine-tuning round: where it was made, and from which version.
          ...(model.auction_id !== null && model.auction_id !== undefined
            ? [["Uploaded in", [link(`#/auctions/${model.auction_id}`, `auction ${model.auction_id}`), `, fine-tuning round ${model.round}, from `, link(`#/models/${model.parent_id}`, `model ${model.parent_id}`)]]]
            : []),
        ]),
        // The screener's bars (the inspection page shows them with its evidence instead).
        ...(evidence && model.evidence.length ? [h("section", { "aria-labelledby": "bars-heading", id: "bars" }, h("h2", { id: "bars-heading" }, "The screener's bars"), evidenceTable(model))] : []),
        ...drawn.sections,
      );
    },
  });
}

/** Every weight and bias of a manifest by place: "neuron ← source" or "neuron bias". */
function numbersOf(manifest) {
  const out = new Map();
  for (const [name, neuron] of Object.entries(neuronsOf(manifest))) {
    for (const [source, w] of Object.entries(neuron.weights)) out.set(`${name} ← ${source}`, w);
    out.set(`${name} bias`, neuron.bias);
  }
  return out;
}

const MOVES_SHOWN = 10;

/** Two weights as the drawing's tables show them (signed, 4 decimals), with more decimals (up
 * to 8) where the two would look alike. */
function signedApart(a, b) {
  let digits = 4;
  while (digits < 8 && signed(a, digits) === signed(b, digits)) digits += 1;
  return [signed(a, digits), signed(b, digits)];
}

/**
 * The weights that cast patron ``modelId``'s vote in iteration ``iteration`` of auction
 * ``auctionId``: its version's, or those the market had fine-tuned it to by then, with the
 * largest moves from the version it fine-tuned from.
 */
export function votedWeightsView(view, auctionId, iteration, modelId) {
  const title = h("h1", { tabindex: "-1" }, `The weights behind a vote in iteration ${iteration} of auction ${auctionId}`);
  view.root.append(title);
  const back = link(`#/auctions/${auctionId}`, `Auction ${auctionId}`);
  getJSON(`/auctions/${auctionId}/iterations/${iteration}/votes/${modelId}/weights`)
    .then((w) => Promise.all([w, w.fine_tuned_after === null ? null : getJSON(`/models/${w.version_id}`), loadAnatomy()]))
    .then(([w, version, a]) => {
      const manifest = w.manifest;
      fill(title, `${w.participant}'s weights in iteration ${iteration} of auction ${auctionId}`);
      const versionLink = link(`#/models/${w.version_id}`, `version ${w.version}`);
      const parts = [
        h(
          "p",
          { id: "weights-origin" },
          w.fine_tuned_after === null
            ? [`${w.participant} bid with `, versionLink, " as stored: these are its weights."]
            : [`${w.participant} bid with `, versionLink, ` as the market fine-tuned it inside auction ${auctionId} after iteration ${w.fine_tuned_after} (its re-screening kept the result). The auction keeps these weights; they are not a version of their own.`],
        ),
        h("p", {}, back, " · ", h("a", { href: `/auctions/${auctionId}/iterations/${iteration}/votes/${modelId}/weights` }, "the same as JSON (its manifest is one /submit takes)")),
      ];
      if (w.fine_tunings.length) {
        parts.push(
          h(
            "section",
            { "aria-labelledby": "tunings-heading" },
            h("h2", { id: "tunings-heading" }, `Fine-tuning in the market before iteration ${iteration}`),
            h(
              "ul",
              { id: "fine-tunings" },
              w.fine_tunings.map((f) =>
                h(
                  "li",
                  { "data-kept": String(f.kept) },
                  `after iteration ${f.after}: `,
                  f.kept
                    ? "kept (its re-screening accepted the weights)"
                    : f.reasons.length
                      ? ["not kept: it bid on with the weights it had. Its re-screening's reasons:", h("ul", { class: "refusal-reasons" }, f.reasons.map((r) => h("li", {}, h("code", {}, r.rule), ` (neuron ${r.neuron}): `, h("span", { class: "free-text" }, r.message))))]
                      : "not kept (the screener refused the weights, or they passed a bar by less than the review margin; this refusal was stored before its reasons were kept): it bid on with the weights it had",
                ),
              ),
            ),
          ),
        );
      }
      if (version) {
        const before = numbersOf(version.manifest);
        const moves = [...numbersOf(manifest)].map(([place, x]) => [place, before.get(place), x]).filter(([, b, x]) => b !== x);
        moves.sort((p, q) => Math.abs(q[2] - q[1]) - Math.abs(p[2] - p[1]));
        parts.push(
          h(
            "section",
            { "aria-labelledby": "moves-heading" },
            h("h2", { id: "moves-heading" }, "What fine-tuning changed"),
            moves.length
              ? scrolling(
                  table(
                    moves.length === 1 ? `The one weight that moved from version ${w.version}` : moves.length <= MOVES_SHOWN ? `The ${moves.length} weights and biases that moved from version ${w.version}` : `The ${MOVES_SHOWN} largest of the ${moves.length} weights and biases that moved from version ${w.version}`,
                    ["Weight", `Version ${w.version}`, `Voted in iteration ${iteration}`, "Change"],
                    moves.slice(0, MOVES_SHOWN).map(([place, b, x]) => [place, ...signedApart(b, x), signed(x - b, 6)]),
                    { id: "weight-moves" },
                  ),
                  "What fine-tuning changed (scrolls sideways)",
                )
              : h("p", {}, `No weight moved from version ${w.version}.`),
          ),
        );
      }
      view.root.append(...parts, settingsFacts(manifest, [["Participant", participantLink(w.participant)]]), ...drawnNeurons(manifest, [], a, { screened: false }).sections);
    })
    .catch((error) => {
      if (!isMissing(error)) {
        view.root.append(problem(error));
        return;
      }
      // The auction exists (its iteration or patron does not: say which, and go back to it), or not.
      getJSON(`/auctions/${auctionId}`)
        .then(() => view.root.append(problem(error), h("p", {}, back)))
        .catch((again) => {
          if (isMissing(again)) notFound(view.root, `Auction ${auctionId}`, ["#/", "All auctions"]);
          else view.root.append(problem(error), h("p", {}, back));
        });
    });
}
