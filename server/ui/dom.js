// Building the page. Every value from the API enters the document as a text node or an
// attribute value, never as markup: no script of this page hands a string to the HTML parser.

const SVG_NS = "http://www.w3.org/2000/svg";

function setAttributes(node, attributes) {
  for (const [name, value] of Object.entries(attributes)) {
    if (value === null || value === undefined || value === false) continue;
    if (name.startsWith("on") && typeof value === "function") {
      node.addEventListener(name.slice(2), value);
    } else {
      node.setAttribute(name, value === true ? "" : String(value));
    }
  }
}

function appendChildren(node, children) {
  for (const child of children.flat(Infinity)) {
    if (child === null || child === undefined || child === false) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
}

/** An HTML element: h("a", {href: "#/"}, "text", otherNode). */
export function h(tag, attributes = {}, ...children) {
  const node = document.createElement(tag);
  setAttributes(node, attributes);
  appendChildren(node, children);
  return node;
}

/** An SVG element, same calling convention. */
export function svg(tag, attributes = {}, ...children) {
  const node = document.createElementNS(SVG_NS, tag);
  setAttributes(node, attributes);
  appendChildren(node, children);
  return node;
}

/** Replace a node's children. */
export function fill(node, ...children) {
  node.replaceChildren();
  appendChildren(node, children);
  return node;
}

/**
 * Make ``old`` (in the page) show what ``fresh`` (built anew for the same thing) shows, keeping
 * ``old``'s nodes where they can stay: a press that starts on a row and ends after its update
 * lands on the same element. An element of the same tag keeps its node: its attributes become
 * ``fresh``'s (an opened <details> stays open), its children are patched pairwise, the extra
 * ones removed and the missing ones added at the end; a text node takes the new text; a node
 * of another tag is replaced (that subtree only). Children that each carry a ``data-key``
 * (the items of a list whose items come and go in the middle) are matched by their key
 * instead: each keeps its node (a press on one never lands on another's that took its place),
 * the new ones are added where they belong, the gone ones removed. Listeners stay those
 * ``old`` was built with. Returns the node now in the page.
 */
export function patch(old, fresh) {
  if (old.nodeType !== fresh.nodeType || old.nodeName !== fresh.nodeName) {
    old.replaceWith(fresh);
    return fresh;
  }
  if (old.nodeType !== Node.ELEMENT_NODE) {
    if (old.nodeValue !== fresh.nodeValue) old.nodeValue = fresh.nodeValue;
    return old;
  }
  const kept = (name) => (name === "open" && old.tagName === "DETAILS") || (name === "tabindex" && old === document.activeElement);
  for (const name of old.getAttributeNames()) if (!fresh.hasAttribute(name) && !kept(name)) old.removeAttribute(name);
  for (const name of fresh.getAttributeNames()) {
    if (old.getAttribute(name) !== fresh.getAttribute(name)) old.setAttribute(name, fresh.getAttribute(name));
  }
  const mine = [...old.childNodes];
  const theirs = [...fresh.childNodes]; // a child replaced or added leaves ``fresh``
  const keyOf = (node) => (node.nodeType === Node.ELEMENT_NODE ? node.getAttribute("data-key") : null);
  if (theirs.length && theirs.every(keyOf)) {
    const wanted = new Set(theirs.map(keyOf));
    const byKey = new Map();
    for (const child of mine) {
      if (keyOf(child) !== null && wanted.has(keyOf(child)) && !byKey.has(keyOf(child))) byKey.set(keyOf(child), child);
      else child.remove();
    }
    let at = old.firstChild; // where the next of ``theirs`` goes
    for (const child of theirs) {
      const kept = byKey.get(keyOf(child));
      if (!kept) {
        old.insertBefore(child, at);
        continue;
      }
      if (kept === at) at = at.nextSibling;
      else old.insertBefore(kept, at);
      patch(kept, child);
    }
    return old;
  }
  mine.forEach((child, i) => (i < theirs.length ? patch(child, theirs[i]) : child.remove()));
  old.append(...theirs.slice(mine.length));
  return old;
}

/** A number with a fixed count of decimals ("—" for null). */
export function fixed(value, digits = 3) {
  return value === null || value === undefined ? "—" : Number(value).toFixed(digits);
}

/** A price the network read, shown as the auction's record keeps it (5 decimals) and shows it
 * (3): 5.0675029 reads 5.067, as its iteration's row (5.0675), not 5.068. */
export function recordedPrice(value) {
  return fixed(Number(Number(value).toFixed(5)));
}

/** Numbers shown side by side with `digits` decimals, or with more (up to 8) where two that
 * differ would look alike: a vote's logits never show a tie that was not one. */
export function fixedApart(values, digits = 3) {
  let d = digits;
  const alike = () => values.some((a, i) => values.some((b, j) => i < j && a !== b && a.toFixed(d) === b.toFixed(d)));
  while (d < 8 && alike()) d += 1;
  return values.map((x) => x.toFixed(d));
}

/** A count and its noun: "1 epoch", "2 epochs". */
export function plural(count, noun) {
  return `${count} ${noun}${count === 1 ? "" : "s"}`;
}

/** A weight with its sign spelled out: "+0.2026", "−1.0000". */
export function signed(value, digits = 4) {
  const text = Math.abs(value).toFixed(digits);
  if (value > 0) return `+${text}`;
  if (value < 0) return `\u2212${text}`;
  return text;
}

/** A timestamp in the reader's locale ("—" for null). */
export function when(iso) {
  return iso ? new Date(iso).toLocaleString(undefined, { dateStyle: "short", timeStyle: "long" }) : "—";
}

/** Whether a time is past by the reader's clock: a deadline shown while its round is still open
 * or its auction still enrolling (the server closing it, or restarting) is said as passed,
 * never as "until" a time already gone. */
export function passed(iso) {
  return Boolean(iso) && new Date(iso).getTime() <= Date.now();
}

/** The fills that tell buy, hold and quit apart by more than their colours (WCAG 1.4.1; green
 * and amber are alike in grey): buy solid, hold hatched, quit dotted, as the legends' keys
 * (style.css, .key.vote-*). ``defs`` goes once into the chart (its patterns' ids begin with
 * ``chart``, the chart's own id: unique on the page); ``fill(kind)`` is a mark's fill. */
export function votePatterns(chart) {
  const id = (kind) => `${chart}-${kind}`;
  const tile = (kind, size, attributes, ...marks) =>
    svg("pattern", { id: id(kind), width: size, height: size, patternUnits: "userSpaceOnUse", ...attributes }, svg("rect", { class: `ink-${kind}`, width: size, height: size }), marks);
  const defs = svg(
    "defs",
    {},
    tile("buy", 6, {}),
    tile("hold", 6, { patternTransform: "rotate(45)" }, svg("rect", { class: "ink-gap", width: 2, height: 6 })),
    tile("quit", 5, {}, svg("circle", { class: "ink-gap", cx: 2.5, cy: 2.5, r: 1.3 })),
  );
  return { defs, fill: (kind) => `url(#${id(kind)})` };
}

/** A link inside the page. */
export function link(hash, ...children) {
  return h("a", { href: hash }, ...children);
}

/** A table with a caption, column headers and rows (each row: a list of cells). */
export function table(caption, headers, rows, attributes = {}) {
  return h(
    "table",
    attributes,
    h("caption", {}, caption),
    h("thead", {}, h("tr", {}, headers.map((text) => h("th", { scope: "col" }, text)))),
    h("tbody", {}, rows.map((cells) => tableRow(cells))),
  );
}

/** A wide table in a container that scrolls on a narrow screen, sideways only unless
 * ``tall`` (a keyboard can scroll it too: it takes the focus). ``label`` names it, uniquely
 * on its page. */
export function scrolling(node, label, tall = false) {
  const frame = h("div", { class: tall ? "scroll" : "scroll wide", tabindex: "0", role: "region", "aria-label": label }, node);
  frames.observe(frame);
  if (node instanceof Element) frames.observe(node); // rows added inside a frame of full height
  return frame;
}

/** A frame is a tab stop (for the keyboard to scroll it) only while its content overflows it:
 * one that shows everything would be a stop that does nothing. Frames that left the page are
 * no longer watched. */
const frames = new ResizeObserver((entries) => {
  for (const { target } of entries) {
    const frame = target.closest(".scroll");
    if (!target.isConnected || !frame) {
      frames.unobserve(target);
      continue;
    }
    const overflows = frame.scrollWidth > frame.clientWidth + 1 || frame.scrollHeight > frame.clientHeight + 1;
    if (overflows) frame.setAttribute("tabindex", "0");
    else if (document.activeElement !== frame) frame.removeAttribute("tabindex");
  }
});

/** One body row of ``table``. */
export function tableRow(cells, attributes = {}) {
  return h("tr", attributes, cells.map((cell) => h("td", {}, cell)));
}

/** A description list from [term, description] pairs. */
export function facts(pairs, attributes = {}) {
  return h(
    "dl",
    { class: "facts", ...attributes },
    pairs.map(([term, description]) => h("div", {}, h("dt", {}, term), h("dd", {}, description))),
  );
}

/** Whether the view on show was opened by a link or the history (not the page's first load):
 * then a heading drawn later takes the focus, as every view's heading does when drawn. */
export function navigated() {
  return document.getElementById("main")?.dataset.navigated === "yes";
}

/** A line of text for a failure, shown where the content would have been. */
export function problem(error) {
  return h("p", { class: "problem", role: "alert" }, String(error.message || error));
}

/** Whether an API error says the thing asked for does not exist (404, or an id no resource
 * can have: 422). */
export function isMissing(error) {
  return error && (error.status === 404 || error.status === 422);
}

/** Replace a view whose subject does not exist with a "Not found" page: what was asked for,
 * and a way back. The new heading takes the focus only if the view had it (after a
 * navigation), as every view's heading does. */
export function notFound(root, what, [href, words]) {
  const focused = root.contains(document.activeElement);
  const title = h("h1", { tabindex: "-1" }, "Not found");
  root.replaceChildren(title, h("p", { class: "problem", role: "alert", id: "not-found" }, `${what} does not exist.`), h("p", {}, link(href, words)));
  document.title = "Not found · srd-auction";
  if (focused) title.focus();
}
