// Past searches, newest first, a page at a time.

import { h, notice, when } from "./dom.js";

const PER_PAGE = 15;

/** Page `page` of the searches, `per` a page (`#/searches?page=2&per=5`). */
export function showSearchList({ view, api }, page, per = PER_PAGE) {
  const controller = new AbortController();
  page = Number.isInteger(page) && page > 0 ? page : 1;
  const PER = Number.isInteger(per) && per > 0 && per <= 200 ? per : PER_PAGE;
  const link = (n) => `#/searches?page=${n}${PER === PER_PAGE ? "" : `&per=${PER}`}`;
  view.replaceChildren(h("h2", { class: "title" }, "Past searches"), h("p", { class: "muted" }, "Loading…"));
  (async () => {
    let listing;
    try {
      listing = await api(`/searches?limit=${PER}&offset=${(page - 1) * PER}`, { signal: controller.signal });
    } catch (error) {
      if (error.name !== "AbortError") view.replaceChildren(h("h2", { class: "title" }, "Past searches"), notice(`Could not list the searches: ${error.detail || error.message}`, "error"));
      return;
    }
    const pages = Math.max(1, Math.ceil(listing.total / PER));
    const rows = listing.items.map((s) => {
      const finished = ["succeeded", "failed", "cancelled"].includes(s.status);
      const wall = finished ? `${((new Date(s.updated_at) - new Date(s.created_at)) / 1000).toFixed(1)} s` : "—";
      return h(
        "tr",
        {},
        h("td", {}, h("a", { href: `#/searches/${s.id}` }, s.id.slice(0, 12))),
        h("td", {}, h("span", { class: `badge ${s.status}` }, s.status)),
        h("td", {}, s.scene),
        h("td", {}, s.mode === "free" ? "free camera" : s.strategy),
        h("td", {}, s.result ? s.result.renders : "—"),
        h("td", {}, wall),
        h("td", {}, when(s.created_at)),
      );
    });
    const first = listing.total ? (page - 1) * PER + 1 : 0;
    view.replaceChildren(
      h("h2", { class: "title" }, "Past searches"),
      listing.total
        ? h(
            "table",
            { id: "searches", class: "searches" },
            h("thead", {}, h("tr", {}, ["search", "status", "scene", "method", "renders", "wall time", "created"].map((t) => h("th", {}, t)))),
            h("tbody", {}, rows),
          )
        : h("p", { class: "muted" }, "No search yet."),
      h(
        "p",
        { class: "pager" },
        page > 1 ? h("a", { href: link(page - 1), id: "newer" }, "← newer") : null,
        ` ${first}–${Math.max(first, first + listing.items.length - 1)} of ${listing.total} (page ${page} of ${pages}) `,
        page < pages ? h("a", { href: link(page + 1), id: "older" }, "older →") : null,
      ),
    );
  })();
  return () => controller.abort();
}
