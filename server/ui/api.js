// Talking to the API: JSON reads, paginated lists and event streams. Only the review pages
// send a token (the operator's, pasted once and kept in memory), always in the Authorization
// header, never in a URL.

import { h, isMissing, patch, plural } from "./dom.js";

const RETRY_MS = 5000; // after the server refused a stream (503) or it broke for good
export const LIST_REFRESH_MS = 5000; // a list's first page is read again this often
const OPEN_MS = 8000; // a stream not open by then is given up (the browser may be holding it
// back: at most six connections to one server, each live view holding one) and read instead

export class ApiError extends Error {
  constructor(message, status) {
    super(message);
    this.status = status;
  }
}

/** GET a JSON document (with the bearer ``token``, if given); an error answer becomes an
 * ApiError carrying the server's words. */
export async function getJSON(path, token = null) {
  return answer(await reach(path, { headers: headers(token) }, "try again"));
}

/** POST a JSON body with the bearer ``token``; the answer as ``getJSON``'s. */
export async function postJSON(path, body, token) {
  const init = { method: "POST", headers: { ...headers(token), "Content-Type": "application/json" }, body: JSON.stringify(body) };
  const unknown = "whether it was recorded is unknown: reload this page to see, then try again if it was not";
  return answer(await reach(path, init, unknown));
}

/** ``fetch``, a network failure said in words (the browser's own is "Failed to fetch"). */
async function reach(path, init, then) {
  try {
    return await fetch(path, init);
  } catch {
    throw new ApiError(`The server could not be reached (the network, or the server is down); ${then}.`, 0);
  }
}

function headers(token) {
  return token ? { Accept: "application/json", Authorization: `Bearer ${token}` } : { Accept: "application/json" };
}

async function answer(response) {
  const body = await response.json().catch(() => null);
  if (!response.ok) {
    const words = body && Array.isArray(body.detail) ? body.detail.map((d) => d.msg) : [];
    const plain = `The server answered ${response.status} ${response.statusText} without saying why (a proxy in front of it, or the server restarting); try again shortly.`;
    throw new ApiError(words.join("; ") || plain, response.status);
  }
  return body;
}

/** A path with query parameters (empty ones left out). */
export function withQuery(path, params) {
  const mark = path.indexOf("?"); // a path may carry a query of its own
  const [base, given] = mark < 0 ? [path, ""] : [path.slice(0, mark), path.slice(mark + 1)];
  const query = new URLSearchParams(given);
  for (const [name, value] of Object.entries(params)) {
    if (value !== null && value !== undefined && value !== "") query.set(name, String(value));
  }
  const text = query.toString();
  return text ? `${base}?${text}` : base;
}

/**
 * A view's first read: ``read()`` (a promise), its answer handed to ``use``, or to ``missing``
 * the error saying its subject does not exist. Any other failure is said in a line that takes
 * the place of ``at`` (the view's live line, say), with a "Try again now" button; the read is
 * tried again every few seconds while the tab is shown, until it works (``at`` is back, the
 * line gone) or the view is left. ``refused(error)``, if given, ends the tries on an error no
 * read again can mend (a token refused: the view asks for another) by returning true.
 */
export function firstRead(view, read, { use, missing, at, refused = () => false }) {
  const words = h("span");
  const again = h("button", { type: "button", id: "read-again" }, "Try again now");
  const line = h("p", { class: "problem", role: "alert", id: "read-failed" }, words, " ", again);
  let timer = null;
  let left = false;
  // What the page laid out after the line, hidden while nothing is read: its "none yet" would
  // say something false about a subject the page could not read.
  const unread = [];
  const hideRest = () => {
    for (let node = line.nextElementSibling; node; node = node.nextElementSibling) {
      if (!node.hidden) unread.push(node);
      node.hidden = true;
    }
  };
  const attempt = () => {
    clearTimeout(timer);
    if (document.visibilityState !== "visible") {
      timer = setTimeout(attempt, RETRY_MS); // read once the tab is shown
      return;
    }
    const pressed = document.activeElement === again;
    again.disabled = true;
    read().then(
      (answer) => {
        if (left) return;
        if (line.isConnected) line.replaceWith(at);
        for (const node of unread.splice(0)) node.hidden = false;
        use(answer);
        if (pressed) view.root.querySelector("h1")?.focus(); // its button is gone
      },
      (error) => {
        if (left) return;
        if (isMissing(error)) return missing(error);
        if (refused(error)) return;
        const text = `${String(error.message || error)} The page tries again every few seconds.`;
        if (words.textContent !== text) words.textContent = text;
        again.disabled = false;
        if (pressed) again.focus();
        if (at.isConnected) at.replaceWith(line);
        hideRest();
        timer = setTimeout(attempt, RETRY_MS);
      },
    );
  };
  again.addEventListener("click", attempt);
  view.onLeave(() => {
    left = true;
    clearTimeout(timer);
  });
  attempt();
}

/**
 * A list page by page: ``render(items)`` is called for each page (it returns the first row it
 * added, if any), and a "Show older" button fetches the next one while there is one. The
 * button keeps the focus while it stays; after the last page it goes, and the focus moves to
 * the first row it added. Returns the button's container.
 */
export function pager(path, params, render) {
  const more = h("button", { type: "button" }, "Show older");
  const box = h("p", { class: "pager" });
  let cursor = null;
  async function load() {
    const focused = document.activeElement === more;
    more.disabled = true;
    const page = await getJSON(withQuery(path, { ...params, cursor }));
    const first = render(page.items);
    cursor = page.next_cursor;
    box.replaceChildren(...(cursor ? [more] : []));
    more.disabled = false;
    if (focused && cursor) more.focus();
    else if (focused && first) {
      first.setAttribute("tabindex", "-1");
      first.focus();
    }
    return page;
  }
  more.addEventListener("click", () => load().catch((error) => box.replaceChildren(String(error))));
  return { box, load };
}

/**
 * Keep a list's first page current while its view is shown: ``path`` with ``params`` is read
 * again every LIST_REFRESH_MS while the tab is visible. A listed item whose JSON changed has
 * its row (``rowFor(item)``) brought up to date in place (``patch``: the row stays the same
 * element, so a press on it lands, and the focus stays on the same control of it). New items
 * (when ``newestFirst``) appear at the top at once while the list shows none; while it shows
 * rows they are held back, and a button in the slot ``news`` (its room kept whether it shows
 * or not, so the rows never move under the pointer) offers them: "2 new auctions — show" (the
 * ``noun``), said once by a polite live region when it appears; pressed, it adds them at the
 * top and the focus moves to the first one's link. A listed (or held) one the first page now
 * leaves out, within the ids it covers, goes (it no longer matches the filter), as a reload
 * would show. A status line in the same slot says when a read failed and when the rows shown
 * were read (the slot grows to hold it whole on a narrow screen); ``empty`` (what the list
 * says when it lists nothing) shows while it lists nothing. ``add`` renders a page's items
 * (the pager's render); ``onRead()`` hears every read that worked.
 */
export function keepCurrent(view, { path, params, newestFirst, rows, rowFor, noun, empty, onRead = () => {} }) {
  const state = h("p", { class: "none-yet", id: "list-state", role: "status", hidden: true });
  const offer = h("button", { type: "button", id: "show-new", hidden: true });
  const said = h("span", { class: "visually-hidden", id: "news-said", role: "status" }); // there from the start: a region added with its words is not read out
  const news = h("div", { class: "news", id: "list-news" }, state, offer, said); // the failure line too: it moves nothing either
  const rowOf = new Map(); // item id -> its row
  const held = new Map(); // item id -> a new item not shown yet
  let readAt = null;
  const draw = (item) => {
    const row = rowFor(item);
    row.dataset.seen = JSON.stringify(item);
    return row;
  };
  const show = (item) => {
    const row = draw(item);
    rowOf.set(item.id, row);
    return row;
  };
  const redraw = (old, item) => {
    const row = patch(old, draw(item)); // the same row, unless its tag changed
    rowOf.set(item.id, row);
    return row;
  };
  const read = () => {
    readAt = new Date();
    state.hidden = true;
    empty.hidden = rowOf.size > 0;
    onRead();
  };
  /** The held items added at the top, newest first; their first row. */
  const showHeld = () => {
    const added = [...held.values()].sort((a, b) => b.id - a.id).map(show);
    held.clear();
    rows.prepend(...added);
    offered();
    return added[0];
  };
  /** The button says how many are held, and shows while some are; said when it appears. */
  const offered = () => {
    const words = `${plural(held.size, `new ${noun.replace(/s$/, "")}`)} — show`;
    if (held.size && offer.hidden) said.textContent = words;
    if (!held.size) said.textContent = "";
    // the offer gone (its items left the filter) while it had the focus: the list takes it
    if (!held.size && document.activeElement === offer) rows.querySelector("a")?.focus();
    offer.hidden = !held.size;
    if (offer.textContent !== words) offer.textContent = words;
  };
  offer.addEventListener("click", () => {
    const first = showHeld();
    empty.hidden = rowOf.size > 0;
    first?.querySelector("a")?.focus();
  });
  function refresh() {
    if (document.visibilityState !== "visible") return;
    getJSON(withQuery(path, params))
      .then((page) => {
        const top = Math.max(0, ...rowOf.keys());
        for (const item of page.items) {
          const old = rowOf.get(item.id);
          if (old && old.dataset.seen === JSON.stringify(item)) continue; // unchanged: left alone
          if (old) {
            const controls = (row) => [...row.querySelectorAll("a, input, button, summary")];
            const place = controls(old).indexOf(document.activeElement);
            const row = redraw(old, item);
            if (place >= 0 && !row.contains(document.activeElement)) controls(row)[place]?.focus();
          } else if (newestFirst && item.id > top) held.set(item.id, item);
        }
        const here = new Set(page.items.map((item) => item.id));
        const ids = [...here];
        const covered = (id) => page.next_cursor === null || (newestFirst ? id >= Math.min(...ids) : id <= Math.max(...ids));
        for (const [id, row] of rowOf) {
          if (!here.has(id) && covered(id)) {
            row.remove();
            rowOf.delete(id);
          }
        }
        for (const id of held.keys()) if (!here.has(id) && covered(id)) held.delete(id);
        if (rowOf.size) offered();
        else showHeld(); // nothing listed to push down
        read();
      })
      .catch((error) => {
        const why = error.status ? `the server answered ${error.status}` : "the server could not be reached";
        const shown = readAt ? `Not updated: ${why}. Shown as read at ${readAt.toLocaleTimeString()}` : `Not read: ${why}`;
        state.hidden = false;
        state.textContent = `${shown}; trying again every few seconds.`;
      });
  }
  const timer = setInterval(refresh, LIST_REFRESH_MS);
  view.onLeave(() => clearInterval(timer));
  return {
    news,
    add(items) {
      // a page read after a refresh drew some of its items (a slow first page): those are
      // brought up to date in place, not listed twice
      const added = [];
      for (const item of items) {
        const old = rowOf.get(item.id);
        held.delete(item.id);
        if (old) redraw(old, item);
        else added.push(show(item));
      }
      rows.append(...added);
      offered();
      return added[0];
    },
    read,
  };
}

/**
 * Follow an event stream. ``handlers`` maps event names to functions of the parsed data; the
 * ``end`` event closes the stream. A dropped connection is resumed by the browser itself
 * (EventSource sends Last-Event-ID); one the server refused or closed for good is opened
 * again after RETRY_MS, continuing after the last event received (or ``after``, the place a
 * view already read up to without the stream). A hidden tab lets go of its stream and
 * resumes where it left off when shown again: a browser holds at most six connections to one
 * server over HTTP/1.1, so six open live views would otherwise block every other page.
 * ``onState`` hears "connecting", "live", "waiting" (a dropped stream the browser resumes),
 * "refused" (the stream could not be had, or did not open within OPEN_MS: the view may read
 * what it shows another way meanwhile), "paused" and "ended". Returns a function that
 * stops following.
 */
export function follow(path, handlers, onState = () => {}, after = null) {
  let lastId = after;
  let source = null;
  let timer = null;
  let stopped = false;

  let opening = null;

  function close() {
    clearTimeout(timer);
    clearTimeout(opening);
    if (source) source.close();
    source = null;
  }

  function refused() {
    close();
    onState("refused");
    timer = setTimeout(open, RETRY_MS);
  }

  function stop() {
    stopped = true;
    close();
    document.removeEventListener("visibilitychange", onVisibility);
  }

  function onVisibility() {
    if (stopped) return;
    if (document.visibilityState === "hidden") {
      close();
      onState("paused");
    } else if (!source) {
      open();
    }
  }

  function open() {
    clearTimeout(timer);
    if (document.visibilityState === "hidden") {
      onState("paused");
      return; // opened when the tab is shown
    }
    source = new EventSource(lastId === null ? path : withQuery(path, { after: lastId }));
    onState("connecting");
    opening = setTimeout(refused, OPEN_MS);
    source.addEventListener("open", () => {
      clearTimeout(opening);
      onState("live");
    });
    source.addEventListener("error", () => {
      if (stopped || !source) return;
      if (source.readyState === EventSource.CLOSED) refused();
      else onState("waiting");
    });
    for (const [name, handle] of Object.entries(handlers)) {
      source.addEventListener(name, (event) => {
        if (event.lastEventId) lastId = event.lastEventId;
        if (name === "end") {
          stop();
          onState("ended");
        }
        handle(JSON.parse(event.data));
      });
    }
  }

  document.addEventListener("visibilitychange", onVisibility);
  open();
  return {
    stop,
    /** The place to resume from, once the view has read up to it another way. */
    readUpTo(id) {
      lastId = id;
    },
  };
}
