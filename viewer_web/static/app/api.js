// The public REST API, called with the key the user pasted (Authorization: Bearer).
// Errors are RFC 9457 problem details; ApiError carries the problem and a message that
// names the field (and file) at fault, as the API's `errors[]` gives them.
import { sleep } from "./util.js";

export const auth = { key: null, onUnauthorized: null };

export class ApiError extends Error {
  constructor(status, problem) {
    const p = problem && typeof problem === "object" ? problem : {};
    const first = Array.isArray(p.errors) ? p.errors[0] : null;
    let message = p.detail || p.title || `HTTP ${status}`;
    if (first) {
      const where = [first.file, first.field].filter(Boolean).join(": ");
      if (where && !message.includes(first.field || first.file)) message += ` (${where})`;
    }
    super(message);
    this.status = status;
    this.problem = p;
    this.type = String(p.type || "").replace("urn:glint:problem:", "");
    this.field = first ? first.field || null : null;
    this.errors = Array.isArray(p.errors) ? p.errors : [];
  }
}

/** fetch() one API path; resolves with the Response when ok (or 304), else throws ApiError. */
export async function api(path, { method = "GET", json, body, headers = {}, signal } = {}) {
  const h = { ...headers };
  if (auth.key) h.Authorization = `Bearer ${auth.key}`;
  if (json !== undefined) {
    h["Content-Type"] = "application/json";
    body = JSON.stringify(json);
  }
  const r = await fetch(path, { method, headers: h, body, signal, cache: "no-store" });
  if (r.ok || r.status === 304) return r;
  const problem = await r.json().catch(() => null);
  const err = new ApiError(r.status, problem);
  if (r.status === 401 && auth.onUnauthorized) auth.onUnauthorized(err);
  throw err;
}

export async function getJson(path, opts) {
  return (await api(path, opts)).json();
}

/** Every item of a list endpoint ({items, total, limit, offset} pages). */
export async function listAll(path, { max = 10000 } = {}) {
  const items = [];
  const sep = path.includes("?") ? "&" : "?";
  for (let offset = 0; ; ) {
    const page = await getJson(`${path}${sep}limit=200&offset=${offset}`);
    items.push(...page.items);
    offset += page.limit;
    if (!page.items.length || offset >= page.total || items.length >= max) return items;
  }
}

/** A version 4 UUID (crypto.randomUUID needs a secure context; getRandomValues does not). */
export function uuid4() {
  const b = crypto.getRandomValues(new Uint8Array(16));
  b[6] = (b[6] & 0x0f) | 0x40;
  b[8] = (b[8] & 0x3f) | 0x80;
  const x = Array.from(b, (v) => v.toString(16).padStart(2, "0")).join("");
  return `${x.slice(0, 8)}-${x.slice(8, 12)}-${x.slice(12, 16)}-${x.slice(16, 20)}-${x.slice(20)}`;
}

/** POST /v1/scenes with an Idempotency-Key, retried (same key) when the network fails. */
export async function createScene(name) {
  const key = uuid4();
  for (let attempt = 0; ; attempt++) {
    try {
      return await getJson("/v1/scenes", { method: "POST", json: { name }, headers: { "Idempotency-Key": key } });
    } catch (e) {
      if (e instanceof ApiError || attempt >= 3) throw e;
      await sleep(500 * 2 ** attempt);
    }
  }
}

/**
 * Follow a server-sent event stream that needs the Authorization header (EventSource
 * cannot send one): fetch + a stream reader + the SSE line format. Calls onEvent(name,
 * data) per event; returns after `event: end` or when `signal` aborts; reconnects with
 * Last-Event-ID when the connection drops.
 */
export async function followEvents(path, onEvent, signal) {
  let lastId = null;
  let failures = 0;
  while (!signal.aborted) {
    let reader = null;
    try {
      const headers = { Accept: "text/event-stream" };
      if (lastId) headers["Last-Event-ID"] = lastId;
      const r = await api(path, { headers, signal });
      failures = 0;
      reader = r.body.getReader();
      const decoder = new TextDecoder();
      let buf = "";
      let ev = { name: "message", data: [], id: null };
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buf += decoder.decode(value, { stream: true });
        let nl;
        while ((nl = buf.indexOf("\n")) >= 0) {
          let line = buf.slice(0, nl);
          buf = buf.slice(nl + 1);
          if (line.endsWith("\r")) line = line.slice(0, -1);
          if (line === "") {
            if (ev.data.length) {
              if (ev.id != null) lastId = ev.id;
              onEvent(ev.name, ev.data.join("\n"));
              if (ev.name === "end") return;
            }
            ev = { name: "message", data: [], id: null };
            continue;
          }
          if (line.startsWith(":")) continue; // a comment: keep-alive
          const i = line.indexOf(":");
          const field = i < 0 ? line : line.slice(0, i);
          let val = i < 0 ? "" : line.slice(i + 1);
          if (val.startsWith(" ")) val = val.slice(1);
          if (field === "event") ev.name = val;
          else if (field === "data") ev.data.push(val);
          else if (field === "id") ev.id = val;
        }
      }
    } catch (e) {
      if (signal.aborted) return;
      if (e instanceof ApiError) throw e; // 404 (deleted), 401: not worth retrying
      failures += 1;
    } finally {
      if (reader) reader.cancel().catch(() => {});
    }
    if (signal.aborted) return;
    await sleep(Math.min(500 * 2 ** failures, 10000));
  }
}
