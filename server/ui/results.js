// A job's result read generically: its headline numbers, its tables (rows of objects) and the
// curves those rows draw. What each kind shows first comes from /ui/kinds.json (the registry).

import { getJSON } from "./api.js";
import { h, scrolling, svg } from "./dom.js";

const WORDS = {
  lr: "learning rate",
  srd: "SRD",
  n: "runs",
  n_fish: "fish",
  n_runs: "runs",
  sd_final_displacement: "SD of final displacement",
  price_std: "SD of price",
  elapsed_s: "elapsed (s)",
  eval_maps: "evaluation maps",
  train_maps: "training maps",
  accuracy_srd: "accuracy after SRD",
  lava_entered_srd: "lava entered after SRD",
  mean_energy_first_1000: "mean energy, first 1000 steps",
  mean_energy_last_1000: "mean energy, last 1000 steps",
};
/** Columns that say which condition a row is (the rest are its measures). */
const KEYS = new Set(["setting", "rarity", "backswing", "inhibitor", "srd", "lr", "repeat", "trial", "saboteurs", "screen", "fine_tune", "project", "preset"]);
const LINE_COLOURS = ["#1d5fbf", "#b3261e", "#1b7f3b", "#9a5b00", "#6a3d9a", "#00707a"];
/** Each line's dashes beside its colour, and their name in its legend: lines told apart
 * without their colours too (in grey, or by a reader who does not see red from green). */
const LINE_DASHES = [
  [null, ""],
  ["6 3", "dashed"],
  ["1.5 3", "dotted"],
  ["9 3 2 3", "dash-dot"],
  ["14 4", "long dashes"],
  ["6 2 1.5 2 1.5 2", "dash-dot-dot"],
];

let layouts = null;
/** The layouts of every kind (fetched once). */
export function kindLayouts() {
  layouts =
    layouts ||
    getJSON("/ui/kinds.json").catch((error) => {
      layouts = null; // a read that failed is not kept: the next call reads again
      throw error;
    });
  return layouts;
}

/** A column or field name in words: "mean_price" → "Mean price", "sd_price" → "SD of price". */
export function words(name) {
  const text = WORDS[name] || name.replace(/^sd_/, "SD of ").replaceAll("_", " ");
  return text.charAt(0).toUpperCase() + text.slice(1);
}

/** A value as a person reads it: learning rates to 3 significant digits, other fractions to 4. */
export function shown(name, value) {
  if (value === null || value === undefined) return "—";
  if (typeof value === "boolean") return value ? "yes" : "no";
  if (typeof value !== "number") return typeof value === "object" ? JSON.stringify(value) : String(value);
  if (Number.isInteger(value)) return value.toLocaleString("en");
  const digits = name === "lr" || name.endsWith("learning_rate") ? 3 : 4;
  return String(Number(value.toPrecision(digits)));
}

function isRows(value) {
  return Array.isArray(value) && value.length > 0 && value.every((r) => r && typeof r === "object" && !Array.isArray(r));
}

/** The scalar fields of the result a person reads first: the kind's headline, then elapsed. */
export function headline(result, layout) {
  const names = [...(layout?.headline || []), "elapsed_s"].filter((n) => n in result);
  const scalar = (n) => result[n] === null || typeof result[n] !== "object";
  const chosen = names.filter(scalar);
  return chosen.length ? chosen : Object.keys(result).filter((n) => scalar(n) && n !== "out_dir");
}

/**
 * The result's tables, each {name, caption, rows, columns}: every top-level list of rows, and
 * for a result of several configurations (``configurations: {name: {rows, ...}}``) one per
 * configuration, whatever configurations it has.
 */
export function tablesOf(result, layout) {
  const found = [];
  // Every column of every table (``columns``); in the kind's own table, those it names as the
  // ones a person scans come first, and a comparison of jobs reads only them (``scanned``).
  const columnsOf = (rows, own) => {
    const present = Object.keys(rows[0]).filter((c) => rows.every((r) => r[c] === null || typeof r[c] !== "object"));
    const preferred = own ? (layout?.columns || []).filter((c) => present.includes(c)) : [];
    return {
      columns: [...preferred, ...present.filter((c) => !preferred.includes(c))],
      scanned: preferred.length ? preferred : present,
    };
  };
  for (const [name, value] of Object.entries(result)) {
    if (isRows(value)) found.push({ name, caption: words(name), rows: value, ...columnsOf(value, name === layout?.table) });
  }
  const configurations = result.configurations;
  // A comparison's caption says what each configuration is, a line each ("name: what it is").
  const lines = typeof result.caption === "string" ? result.caption.split("\n") : [];
  const saidOf = (name) => lines.find((line) => line.startsWith(`${name}: `))?.slice(name.length + 2);
  const setting = ([k, v]) => (k === "refused" ? `patrons the screening refused, over all its auctions: ${v}` : `${words(k).toLowerCase()} ${shown(k, v)}`);
  if (configurations && typeof configurations === "object") {
    for (const [name, config] of Object.entries(configurations)) {
      if (config && isRows(config.rows)) {
        const about = Object.entries(config).filter(([k, v]) => k !== "rows" && (v === null || typeof v !== "object"));
        const said = saidOf(name);
        const caption = `Configuration ${name}${said ? `: ${said}` : ""}${about.length ? ` (${about.map(setting).join("; ")})` : ""}`;
        found.push({ name: `configurations.${name}`, caption, rows: config.rows, ...columnsOf(config.rows, layout?.table === "rows") });
      }
    }
  }
  return found;
}

/** The columns of ``columns`` that name a row's condition, and those that measure it. */
export function splitColumns(rows, columns) {
  const keys = columns.filter((c) => KEYS.has(c) || rows.some((r) => typeof r[c] === "string" || typeof r[c] === "boolean"));
  return { keys, measures: columns.filter((c) => !keys.includes(c)) };
}

/** One headline number as a card. */
export function card(name, value) {
  return h("div", { class: "card" }, h("dt", {}, words(name)), h("dd", { title: String(value) }, shown(name, value)));
}

/** A table of rows with word headers. */
export function rowsTable(spec, attributes = {}) {
  return scrolling(
    h(
      "table",
      { class: "list", "data-table": spec.name, ...attributes },
      h("caption", {}, spec.caption),
      h("thead", {}, h("tr", {}, spec.columns.map((c) => h("th", { scope: "col", "data-column": c }, words(c))))),
      h("tbody", {}, spec.rows.map((row) => h("tr", {}, spec.columns.map((c) => h("td", {}, shown(c, row[c])))))),
    ),
    `${spec.caption} (scrolls)`,
    true,
  );
}

/**
 * Lines of (x, y) points overlaid in one inline SVG chart: ``lines`` is [{label, points}], ``x``
 * and ``y`` name the axes. Each line has its colour and its dashes (not colour alone), its
 * legend's key drawn alike.
 * ``subject`` names the chart apart from the page's others of the same axes (in its scroll
 * frame's label: two landmarks of one name cannot be told apart).
 */
export function lineChart(lines, x, y, id, subject = null) {
  const width = 640;
  const height = 260;
  const left = 64;
  const right = 16;
  const top = 16;
  const bottom = 40;
  // Each curve's points with a value, in x order: drawn, and said in words.
  const curves = lines.map((line) => line.points.filter(([, v]) => Number.isFinite(v)).sort((a, b) => a[0] - b[0]));
  const all = curves.flat();
  const xs = all.map(([u]) => u);
  const ys = all.map(([, v]) => v);
  const [x0, x1] = [Math.min(...xs), Math.max(...xs)];
  const pad = (Math.max(...ys) - Math.min(...ys)) * 0.08 || Math.abs(ys[0] || 1) * 0.05 || 0.05;
  const [y0, y1] = [Math.min(...ys) - pad, Math.max(...ys) + pad];
  const px = (u) => left + ((width - left - right) * (u - x0)) / (x1 - x0 || 1);
  const py = (v) => top + ((height - top - bottom) * (y1 - v)) / (y1 - y0 || 1);
  const title = `${words(y)} against ${words(x).toLowerCase()}`;
  const parts = [svg("title", { id: `${id}-title` }, title), svg("rect", { class: "plot", x: left, y: top, width: width - left - right, height: height - top - bottom })];
  for (let k = 0; k <= 4; k += 1) {
    const v = y0 + ((y1 - y0) * k) / 4;
    parts.push(svg("line", { class: "grid", x1: left, x2: width - right, y1: py(v), y2: py(v) }), svg("text", { class: "tick", x: left - 6, y: py(v) + 4, "text-anchor": "end" }, shown("", v)));
  }
  for (const u of [...new Set(xs)].sort((a, b) => a - b).slice(0, 12)) {
    parts.push(svg("text", { class: "tick", x: px(u), y: height - bottom + 16, "text-anchor": "middle" }, shown(x, u)));
  }
  parts.push(
    svg("text", { class: "axis-label", x: (left + width - right) / 2, y: height - 4, "text-anchor": "middle" }, words(x)),
    svg("text", { class: "axis-label", x: 12, y: top + (height - top - bottom) / 2, transform: `rotate(-90 12 ${top + (height - top - bottom) / 2})`, "text-anchor": "middle" }, words(y)),
  );
  lines.forEach((line, i) => {
    const points = curves[i];
    const colour = LINE_COLOURS[i % LINE_COLOURS.length];
    const [dashes] = LINE_DASHES[i % LINE_DASHES.length];
    parts.push(
      svg(
        "polyline",
        { class: "curve", points: points.map(([u, v]) => `${px(u).toFixed(1)},${py(v).toFixed(1)}`).join(" "), stroke: colour, "stroke-dasharray": dashes, "data-line": line.label, "data-points": points.length },
        svg("title", {}, line.label),
      ),
      points.map(([u, v]) => svg("circle", { class: "curve-point", cx: px(u), cy: py(v), r: 3, fill: colour }, svg("title", {}, `${line.label}: ${words(x).toLowerCase()} ${shown(x, u)}, ${words(y).toLowerCase()} ${shown(y, v)}`))),
    );
  });
  const legend = h(
    "ul",
    { class: "legend-list" },
    lines.map((line, i) => {
      const [dashes, named] = LINE_DASHES[i % LINE_DASHES.length];
      const key = svg("svg", { class: "key line-key", viewBox: "0 0 26 6", preserveAspectRatio: "none", "aria-hidden": "true" }, svg("line", { x1: 0, y1: 3, x2: 26, y2: 3, stroke: LINE_COLOURS[i % LINE_COLOURS.length], "stroke-width": 3, "stroke-dasharray": dashes }));
      return h("li", {}, key, named ? `(${named}) ` : "", line.label);
    }),
  );
  // Its accessible name says each curve in words (where it begins and ends, its range); the
  // tables beside it hold every value.
  const said = lines.map((line, i) => {
    const points = curves[i];
    if (!points.length) return `${line.label}: no value`;
    const [[u0, v0], [u1, v1]] = [points[0], points[points.length - 1]];
    const values = points.map(([, v]) => v);
    const at = (u, v) => `${shown(y, v)} at ${words(x).toLowerCase()} ${shown(x, u)}`;
    return `${line.label}: ${at(u0, v0)} to ${at(u1, v1)}, lowest ${shown(y, Math.min(...values))}, highest ${shown(y, Math.max(...values))}`;
  });
  const label = `${title}. ${said.join("; ")}.`;
  return h("figure", {}, scrolling(svg("svg", { class: "chart", id, viewBox: `0 0 ${width} ${height}`, role: "img", "aria-label": label }, parts), `${subject ? `${subject}: ` : ""}${title} (scrolls sideways on a narrow screen)`), h("figcaption", {}, title, legend));
}
