// The controller's page: a new search, a search live or replayed, past searches, the broker.
// Hash routes: #/ (new search; #/?scene=demo picks a scene), #/searches/<id>, #/searches?page=N.

import { api, apiKey, onKeyNeeded, setApiKey } from "./api.js";
import { watchBroker } from "./broker.js";
import { notice } from "./dom.js";
import { showNewSearch } from "./new-search.js";
import { showSearchList } from "./search-list.js";
import { showSearch } from "./search-view.js";

const view = document.getElementById("view");
let leave = null; // what the current view stops when the route changes

function askForKey(reason) {
  const dialog = document.getElementById("key-dialog");
  const input = document.getElementById("key-input");
  const why = document.getElementById("key-why");
  if (reason) why.dataset.reason = reason;
  input.value = apiKey();
  return new Promise((resolve) => {
    dialog.addEventListener(
      "close",
      () => {
        if (input.value.trim()) setApiKey(input.value);
        resolve();
      },
      { once: true },
    );
    if (!dialog.open) dialog.showModal();
    input.focus();
  });
}

function route() {
  if (leave) leave();
  leave = null;
  const [path, query = ""] = location.hash.replace(/^#/, "").split("?");
  const params = new URLSearchParams(query || location.search.slice(1));
  const parts = path.split("/").filter(Boolean);
  for (const link of document.querySelectorAll("[data-nav]")) {
    link.classList.toggle("active", link.dataset.nav === (parts[0] === "searches" ? "searches" : "new"));
  }
  const context = { view, api };
  try {
    if (parts[0] === "searches" && parts[1]) leave = showSearch(context, decodeURIComponent(parts[1]));
    else if (parts[0] === "searches") leave = showSearchList(context, Number(params.get("page") || 1), Number(params.get("per") || 15));
    else leave = showNewSearch(context, params);
  } catch (error) {
    view.replaceChildren(notice(`The page failed: ${error.message}`, "error"));
  }
}

function start() {
  onKeyNeeded(askForKey);
  document.getElementById("key-button").addEventListener("click", () => askForKey().then(route));
  window.addEventListener("hashchange", route);
  watchBroker(document.getElementById("broker-body"), document.getElementById("broker-badge"));
  route();
}

// The skeleton in index.html is painted first; the views are built in the task after that frame.
requestAnimationFrame(() => setTimeout(start, 0));
