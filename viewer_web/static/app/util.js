// Small DOM and formatting helpers shared by the dashboard's modules.

/** h("button", {class: "x", onclick: f, disabled: true}, "text", child, ...) */
export function h(tag, props, ...kids) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(props || {})) {
    if (v == null || v === false) continue;
    if (k === "class") el.className = v;
    else if (k === "dataset") Object.assign(el.dataset, v);
    else if (k.startsWith("on") && typeof v === "function") el.addEventListener(k.slice(2), v);
    else el.setAttribute(k, v === true ? "" : String(v));
  }
  append(el, kids);
  return el;
}

/** Append children, skipping null/false and flattening arrays (DOM append writes "null"). */
export function append(el, kids) {
  for (const kid of kids) {
    if (kid == null || kid === false) continue;
    if (Array.isArray(kid)) append(el, kid);
    else el.append(kid instanceof Node ? kid : String(kid));
  }
}

export const $ = (sel, root = document) => root.querySelector(sel);
export const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));
export const enc = encodeURIComponent;

export function fmtBytes(n) {
  if (n == null) return "—";
  if (n < 1024) return `${n} B`;
  const units = ["KB", "MB", "GB", "TB"];
  let v = n, i = -1;
  do { v /= 1024; i += 1; } while (v >= 1024 && i < units.length - 1);
  return `${v < 10 ? v.toFixed(1) : Math.round(v)} ${units[i]}`;
}

export function fmtDuration(s) {
  if (s == null || !Number.isFinite(s)) return "—";
  if (s < 9.95) return `${Math.max(0, s).toFixed(1)}s`;
  s = Math.round(s);
  if (s < 60) return `${s}s`;
  const m = Math.floor(s / 60), r = s % 60;
  if (m < 60) return `${m}m ${String(r).padStart(2, "0")}s`;
  return `${Math.floor(m / 60)}h ${String(m % 60).padStart(2, "0")}m`;
}

export function fmtAgo(iso) {
  if (!iso) return "";
  const s = (Date.now() - Date.parse(iso)) / 1000;
  if (s < 45) return "just now";
  if (s < 3600) return `${Math.round(s / 60)} min ago`;
  if (s < 86400) return `${Math.round(s / 3600)} h ago`;
  return new Date(iso).toLocaleDateString();
}

export const TERMINAL = new Set(["succeeded", "failed", "cancelled"]);

/** A scene name the API accepts (letters, digits, space . _ -; starts alphanumeric). */
export function sceneName(raw) {
  const s = String(raw || "").replace(/\.(zip|tar|tgz|tar\.gz|tar\.bz2|tar\.xz|gz|bz2|xz)$/i, "")
    .replace(/[^A-Za-z0-9 ._-]+/g, "_").replace(/^[^A-Za-z0-9]+/, "").slice(0, 200).trim();
  return s || "scene";
}
