// The broker at a glance, live: the controller's GET /health/events pushes its health whenever
// it changes (no polling); each replica's fields as /health reports them, whatever they are.

import { follow } from "./api.js";
import { h } from "./dom.js";

const RETRY_MS = 2000; // before following the events again, once they broke off

function cell(value) {
  if (value === true) return "yes";
  if (value === false) return "no";
  if (typeof value === "number") return Number.isInteger(value) ? String(value) : value.toFixed(1);
  if (value && typeof value === "object") {
    const parts = Object.entries(value).map(([k, v]) => `${k} ${typeof v === "number" ? v.toFixed(0) : v} ms`);
    return parts.length ? parts.join(", ") : "—";
  }
  return value === null || value === undefined ? "—" : String(value);
}

const TITLES = { in_flight: "in flight", reported_load: "load", expected_ms: "moving-average task time", served: "served", failed: "failed" };

export function renderHealth(health) {
  const replicas = health.replicas || [];
  const keys = [];
  for (const replica of replicas) for (const key of Object.keys(replica)) if (!keys.includes(key)) keys.push(key);
  const summary = h(
    "p",
    { class: "summary" },
    h("span", { class: `badge ${health.status}` }, health.status),
    ` ${health.searches_running} running, ${health.searches_queued} queued · heuristic ${health.broker_heuristic}`,
    // the store's figures come with an admin key only
    health.store_searches == null ? null : ` · ${health.store_searches} searches stored`,
    health.unavailable_stages?.length ? h("strong", {}, ` · unavailable: ${health.unavailable_stages.join(", ")}`) : null,
  );
  const table = h(
    "table",
    { class: "replicas" },
    h("thead", {}, h("tr", {}, keys.map((key) => h("th", {}, TITLES[key] || key.replaceAll("_", " "))))),
    h(
      "tbody",
      {},
      replicas.map((replica) =>
        h(
          "tr",
          { class: replica.up === false ? "down" : "" },
          keys.map((key) => h("td", { dataset: { field: key } }, cell(replica[key]))),
        ),
      ),
    ),
  );
  return [summary, table];
}

/** Keep `body` and `badge` showing the controller's /health, as its events push it. */
export function watchBroker(body, badge) {
  let shape = ""; // the shown table's columns and replicas: while they stay, only changed text is set
  function show(health) {
    const [summary, table] = renderHealth(health);
    const now = `${[...table.querySelectorAll("th")].map((th) => th.textContent)} ${(health.replicas || []).map((r) => r.name)}`;
    const shown = body.querySelectorAll("p.summary, table.replicas td");
    if (now !== shape || !shown.length) {
      body.replaceChildren(summary, table);
      shape = now;
    } else {
      // the same table: set only the text that changed (a rebuilt panel is laid out and painted whole)
      const fresh = [summary, ...table.querySelectorAll("td")];
      shown.forEach((node, i) => {
        if (node.innerHTML !== fresh[i].innerHTML) node.replaceChildren(...fresh[i].childNodes);
        if (node.className !== fresh[i].className) node.className = fresh[i].className;
      });
      const rows = body.querySelectorAll("table.replicas tbody tr");
      table.querySelectorAll("tbody tr").forEach((row, i) => {
        if (rows[i].className !== row.className) rows[i].className = row.className;
      });
    }
    if (badge.textContent !== `broker ${health.status}`) badge.textContent = `broker ${health.status}`;
    if (badge.className !== `badge ${health.status}`) badge.className = `badge ${health.status}`;
  }

  function lost(message) {
    body.replaceChildren(h("p", { class: "notice error" }, message));
    shape = "";
    badge.textContent = "broker ?";
    badge.className = "badge degraded";
  }

  (async () => {
    for (;;) {
      try {
        await follow("/health/events", (name, data) => name === "health" && show(data));
        lost("The controller closed its health events; asking again…");
      } catch (error) {
        lost(`GET /health/events failed: ${error.detail || error.message}; asking again…`);
      }
      await new Promise((resolve) => setTimeout(resolve, RETRY_MS));
    }
  })();
}
