// A small helper to build DOM nodes: h("p", { class: "x" }, "text", child).

export function h(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (name.startsWith("on")) node.addEventListener(name.slice(2), value);
    else if (name === "dataset") Object.assign(node.dataset, value);
    else node.setAttribute(name, value === true ? "" : value);
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined || child === false) continue;
    node.append(child instanceof Node ? child : String(child));
  }
  return node;
}

/** A message box; `kind` "error" is announced (role alert). */
export function notice(text, kind = "info") {
  return h("p", { class: `notice ${kind}`, role: kind === "error" ? "alert" : "status" }, text);
}

export const ms = (value) => (value === undefined || value === null ? "—" : value.toFixed(0));
// one formatter for every date: Date.toLocaleString builds a new Intl formatter at each call
const DATES = new Intl.DateTimeFormat(undefined, { dateStyle: "short", timeStyle: "medium" });
export const when = (iso) => DATES.format(new Date(iso));

/** Set `node[prop]` only if it differs: an equal text or attribute set again still makes the
 * browser lay the page out again. */
export function update(node, prop, value) {
  if (node[prop] !== value) node[prop] = value;
}
