// Calls of the controller's API: the API key (asked once, kept in this browser), problem+json
// errors (RFC 9457) as exceptions, and server-sent events read from a fetch stream (EventSource
// cannot send an Authorization header).

const KEY = "cosmos.apiKey";

/** A problem+json answer (or a network failure) as an Error: `detail`, `field`, `status`. */
export class Problem extends Error {
  constructor(status, body) {
    const detail = body?.detail || body?.title || `HTTP ${status}`;
    super(detail);
    this.status = status;
    this.title = body?.title || "";
    this.detail = detail;
    this.field = body?.field || null;
    this.type = body?.type || "about:blank";
  }
}

export const apiKey = () => localStorage.getItem(KEY) || "";
export const setApiKey = (key) => localStorage.setItem(KEY, key.trim());

let askForKey = null;
/** `ask(reason)` resolves once the user gave a key (the page's dialog). */
export function onKeyNeeded(ask) {
  askForKey = ask;
}

async function problemOf(response) {
  let body = null;
  try {
    body = await response.json();
  } catch {
    body = { detail: `${response.status} ${response.statusText}` };
  }
  return new Problem(response.status, body);
}

/**
 * `path` on the controller with the key; the answer as `as` ("json", "blob", "response").
 * A 401 asks for a key (once per call) and tries again; any other error throws a Problem.
 */
export async function api(path, { method = "GET", body, headers = {}, signal, as = "json" } = {}) {
  for (let asked = false; ; asked = true) {
    const sent = new Headers(headers);
    if (apiKey()) sent.set("Authorization", `Bearer ${apiKey()}`);
    let response;
    try {
      response = await fetch(path, { method, body, headers: sent, signal });
    } catch (error) {
      if (error.name === "AbortError") throw error;
      throw new Problem(0, { detail: `the controller did not answer (${error.message})` });
    }
    if (response.status === 401 && !asked && askForKey) {
      await askForKey((await problemOf(response)).detail);
      continue;
    }
    if (!response.ok) throw await problemOf(response);
    if (as === "json") return response.json();
    if (as === "blob") return response.blob();
    return response;
  }
}

/** An image of the API (PNG, JPEG) as an object URL: the caller revokes it when done with it. */
export async function imageURL(path, signal) {
  return URL.createObjectURL(await api(path, { as: "blob", signal }));
}

/**
 * Follow server-sent events at `path`: `onEvent(name, data)` for each, data parsed as JSON.
 * Resolves when the stream ends (the controller closes it after `end`).
 */
export async function follow(path, onEvent, signal) {
  const response = await api(path, { as: "response", signal, headers: { Accept: "text/event-stream" } });
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += value.replaceAll("\r\n", "\n");
    let end;
    while ((end = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, end);
      buffer = buffer.slice(end + 2);
      let name = "message";
      const data = [];
      for (const line of block.split("\n")) {
        if (line.startsWith("event:")) name = line.slice(6).trim();
        else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
      }
      if (data.length) onEvent(name, JSON.parse(data.join("\n")));
    }
  }
}
