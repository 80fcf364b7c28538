// The page's router: the part of the URL after "#" names the view (#/auctions/3). Each view
// renders into its own container and registers what must stop when the reader leaves it.

import { auctionList, auctionView } from "./auctions.js";
import { h, notFound } from "./dom.js";
import { compareView, jobList, jobView } from "./jobs.js";
import { inspectorView, modelList, participantView, votedWeightsView } from "./models.js";
import { reviewList, reviewView } from "./reviews.js";

// An id is at most 15 digits (JavaScript counts exactly to 2^53): a longer one names no view.
const ROUTES = [
  [/^#\/(?:auctions)?(?:\?(.*))?$/, "auctions", (view, [, query]) => auctionList(view, new URLSearchParams(query || ""))],
  [/^#\/auctions\/(\d{1,15})$/, "auctions", (view, [, id]) => auctionView(view, Number(id))],
  [/^#\/auctions\/(\d{1,15})\/iterations\/(\d{1,15})\/votes\/(\d{1,15})\/weights$/, "auctions", (view, [, id, n, model]) => votedWeightsView(view, Number(id), Number(n), Number(model))],
  [/^#\/models(?:\?(.*))?$/, "models", (view, [, query]) => modelList(view, new URLSearchParams(query || ""))],
  [/^#\/models\/(\d{1,15})$/, "models", (view, [, id]) => inspectorView(view, Number(id))],
  [/^#\/participants\/([^/?]+)$/, "models", (view, [, name]) => participantView(view, decoded(name))],
  [/^#\/jobs(?:\?(.*))?$/, "jobs", (view, [, query]) => jobList(view, new URLSearchParams(query || ""))],
  [/^#\/jobs\/compare\?(.*)$/, "jobs", (view, [, query]) => compareView(view, new URLSearchParams(query))],
  [/^#\/jobs\/(\d{1,15})$/, "jobs", (view, [, id]) => jobView(view, Number(id))],
  [/^#\/reviews$/, "reviews", (view) => reviewList(view)],
  [/^#\/reviews\/(\d{1,15})$/, "reviews", (view, [, id]) => reviewView(view, Number(id))],
];

/** What an address no view has names, by its first part: ``#/auctions/abc`` an auction (no id
 * has that form), with the way back to its list. */
const KINDS = {
  auctions: ["Auction", "#/", "All auctions"],
  models: ["Model", "#/models", "All models"],
  participants: ["Participant", "#/models", "All models"],
  jobs: ["Job", "#/jobs", "All jobs"],
  reviews: ["Model", "#/reviews", "Every held model"],
};

function nowhere(root, hash) {
  const [kind, name, ...more] = hash.slice(2).split("?")[0].split("/");
  const [noun, href, words] = KINDS[kind] || [null, "#/", "All auctions"];
  notFound(root, noun && name && !more.length ? `${noun} ${decoded(name)}` : `A view at ${hash}`, [href, words]);
}

/** A name from the address as written, or as it stands when it is not valid percent-encoding
 * (the participant view then says no such participant exists). */
function decoded(text) {
  try {
    return decodeURIComponent(text);
  } catch {
    return text;
  }
}

/** What a view gets: its container, and ``onLeave`` for what to stop when it is replaced. */
class View {
  constructor(root) {
    this.root = root;
    this.stops = [];
  }

  onLeave(stop) {
    this.stops.push(stop);
  }

  leave() {
    for (const stop of this.stops) stop();
  }
}

let current = null;

function show(firstLoad) {
  const hash = location.hash || "#/";
  if (!hash.startsWith("#/")) return; // an in-page anchor such as the skip link
  if (current) current.leave();
  const main = document.getElementById("main");
  main.dataset.navigated = firstLoad ? "" : "yes"; // a view drawn later focuses its heading then
  const root = h("div", { class: "view" });
  main.replaceChildren(root);
  current = new View(root);
  const found = ROUTES.map(([pattern, section, render]) => [hash.match(pattern), section, render]).find(([m]) => m);
  for (const anchor of document.querySelectorAll("nav a[data-section]")) {
    const here = found && anchor.dataset.section === found[1];
    if (here) anchor.setAttribute("aria-current", "page");
    else anchor.removeAttribute("aria-current");
  }
  document.title = "srd-auction"; // a view without a heading yet may set its own
  if (!found) {
    nowhere(root, hash);
  } else {
    found[2](current, found[0]);
  }
  const heading = root.querySelector("h1")?.textContent;
  if (heading) document.title = `${heading} · srd-auction`;
  if (!firstLoad) root.querySelector("h1")?.focus();
}

document.getElementById("skip").addEventListener("click", (event) => {
  event.preventDefault();
  document.getElementById("main").focus();
});
window.addEventListener("hashchange", () => show(false));
show(true);
