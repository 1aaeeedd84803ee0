// Scene uploads: reading what the user dropped or chose, the resumable chunked upload
// (POST/PATCH /v1/scenes/{id}/uploads), archives in one request, and the record in
// localStorage that lets the page say what is left after a reload (docs/dashboard.md).
import { ApiError, auth, getJson } from "./api.js";
import { HASH_WHOLE_MAX, hashFile } from "./sha256.js";
import { enc, sleep } from "./util.js";

export const ARCHIVE_RE = /\.(zip|tar|tgz|tar\.gz|tar\.bz2|tbz2|tar\.xz|txz)$/i;
const CHUNK_BYTES = 4 * 1024 * 1024;
const CONCURRENCY = 3;
const RECORDS = "glint-dashboard-uploads";
// system clutter that is never part of a capture
const JUNK = /(^|\/)(\.[^/]*|__MACOSX|Thumbs\.db|desktop\.ini)(\/|$)/i;

// ---- what was dropped or chosen -------------------------------------------------------

function selection(entries, name) {
  const keep = [], skipped = [];
  for (const e of entries) (JUNK.test(e.path) ? skipped : keep).push(e);
  if (keep.length === 1 && ARCHIVE_RE.test(keep[0].path)) {
    return { kind: "archive", file: keep[0].file, name: name || keep[0].file.name, skipped };
  }
  keep.sort((a, b) => (a.path < b.path ? -1 : a.path > b.path ? 1 : 0));
  return { kind: "files", entries: keep, name, skipped };
}

function stripTop(entries) {
  // one folder holding everything (a dropped or chosen folder): paths start inside it
  const tops = new Set(entries.map((e) => e.path.split("/")[0]));
  if (tops.size !== 1 || !entries.every((e) => e.path.includes("/"))) return { entries, top: null };
  const [top] = tops;
  return { entries: entries.map((e) => ({ ...e, path: e.path.slice(top.length + 1) })), top };
}

async function walk(entry, out) {
  if (entry.isFile) {
    const file = await new Promise((resolve, reject) => entry.file(resolve, reject));
    out.push({ path: entry.fullPath.replace(/^\/+/, ""), file });
    return;
  }
  const reader = entry.createReader();
  for (;;) { // readEntries answers in batches until it answers none
    const batch = await new Promise((resolve, reject) => reader.readEntries(resolve, reject));
    if (!batch.length) return;
    for (const e of batch) await walk(e, out);
  }
}

/**
 * What a drop event carries. Must be called inside the drop handler, before any await:
 * the DataTransfer's items are readable only while the event is dispatched.
 */
export function readDrop(dt) {
  const items = Array.from(dt.items || []).filter((i) => i.kind === "file");
  const roots = items.map((i) => (i.webkitGetAsEntry ? i.webkitGetAsEntry() : null));
  const files = Array.from(dt.files || []);
  return (async () => {
    if (roots.length && roots.every(Boolean)) {
      const out = [];
      for (const r of roots) await walk(r, out);
      const { entries, top } = stripTop(out);
      return selection(entries, top || (roots.length === 1 ? roots[0].name : null));
    }
    return selection(files.map((f) => ({ path: f.name, file: f })), files.length === 1 ? files[0].name : null);
  })();
}

/** What an <input type=file> holds (a folder input: paths inside the chosen folder). */
export function readInput(input) {
  const files = Array.from(input.files || []);
  if (input.webkitdirectory) {
    const { entries, top } = stripTop(files.map((f) => ({ path: f.webkitRelativePath || f.name, file: f })));
    return selection(entries, top);
  }
  return selection(files.map((f) => ({ path: f.name, file: f })), files.length === 1 ? files[0].name : null);
}

// ---- the record that survives a reload ----------------------------------------------------

export function loadRecords() {
  try {
    return JSON.parse(localStorage.getItem(RECORDS) || "{}") || {};
  } catch {
    return {};
  }
}

export function recordOf(sceneId, owner) {
  const r = loadRecords()[sceneId];
  return r && r.owner === owner ? r : null;
}

function writeRecords(all) {
  try {
    localStorage.setItem(RECORDS, JSON.stringify(all));
  } catch {
    // storage full or disabled: the upload still works, only the after-reload list is lost
  }
}

export function saveRecord(sceneId, rec) {
  const all = loadRecords();
  all[sceneId] = rec;
  writeRecords(all);
}

export function dropRecord(sceneId) {
  const all = loadRecords();
  if (sceneId in all) {
    delete all[sceneId];
    writeRecords(all);
  }
}

// ---- resumable upload of many files -------------------------------------------------------

/**
 * Uploads files into an open scene, CONCURRENCY at a time, each in chunks from the offset
 * the server holds. Every file is announced with its path, size and SHA-256: the server
 * answers a new upload, the unfinished one it already holds (from a page that was
 * reloaded or closed), or "complete" when the scene has that exact file. `tuning`
 * (window.__glintUploadTuning) may set chunkBytes, concurrency, hashWholeMax and
 * pauseAfterChunks (pause once that many chunks were sent: the browser test reloads the
 * page there).
 */
export class SceneUpload {
  constructor(sceneId, entries, { owner, sceneName, tuning = {} }) {
    this.sceneId = sceneId;
    this.owner = owner;
    this.sceneName = sceneName;
    this.files = entries.map((e) => ({
      path: e.path, size: e.file.size, file: e.file, sha256: null, offset: 0,
      state: "queued", error: null, sentHere: 0, resumedFrom: null, hashed: 0,
    }));
    this.chunkBytes = tuning.chunkBytes || CHUNK_BYTES;
    this.concurrency = tuning.concurrency || CONCURRENCY;
    this.hashWholeMax = tuning.hashWholeMax ?? HASH_WHOLE_MAX;
    this.pauseAfterChunks = tuning.pauseAfterChunks ?? null;
    this.chunks = 0;
    this.inflight = 0; // PATCH requests under way (a pause waits for them)
    this.bytesSent = 0;
    this.paused = false;
    this.stopped = false;
    this.finished = false;
    this.fatal = null;
    this.listeners = new Set();
    this.waiters = [];
    this.savedAt = 0;
  }

  on(fn) { this.listeners.add(fn); return () => this.listeners.delete(fn); }
  emit(file) { for (const fn of this.listeners) fn(file); }

  get totals() {
    let bytes = 0, onServer = 0, done = 0, failed = 0, present = 0;
    for (const f of this.files) {
      bytes += f.size;
      onServer += f.state === "done" || f.state === "present" ? f.size : f.offset;
      if (f.state === "done" || f.state === "present") done += 1;
      if (f.state === "present") present += 1;
      if (f.state === "error") failed += 1;
    }
    return { files: this.files.length, bytes, onServer, done, failed, present };
  }

  save(force = false) {
    const now = Date.now();
    if (!force && now - this.savedAt < 2000) return;
    this.savedAt = now;
    saveRecord(this.sceneId, {
      owner: this.owner, sceneName: this.sceneName, updatedAt: new Date().toISOString(),
      files: this.files.map((f) => [f.path, f.size, f.sha256]),
    });
  }

  pause() { this.paused = true; this.emit(null); }
  resume() {
    this.paused = false;
    const w = this.waiters;
    this.waiters = [];
    w.forEach((fn) => fn());
    this.emit(null);
  }
  stop() { this.stopped = true; this.resume(); }

  async gate() {
    if (this.pauseAfterChunks != null && this.chunks >= this.pauseAfterChunks) {
      this.pauseAfterChunks = null;
      this.pause();
    }
    while (this.paused && !this.stopped) await new Promise((resolve) => this.waiters.push(resolve));
  }

  async run() {
    this.save(true);
    const queue = this.files.slice();
    const worker = async () => {
      while (queue.length && !this.stopped && !this.fatal) await this.one(queue.shift());
    };
    await Promise.all(Array.from({ length: Math.min(this.concurrency, queue.length) }, worker));
    this.finished = true;
    const t = this.totals;
    if (t.done === t.files) dropRecord(this.sceneId);
    else this.save(true);
    this.emit(null);
    return t;
  }

  async one(f) {
    try {
      await this.gate();
      if (this.stopped) return;
      f.state = "hashing";
      this.emit(f);
      f.sha256 = await hashFile(f.file, {
        wholeMax: this.hashWholeMax,
        onProgress: (n) => { f.hashed = n; this.emit(f); },
      });
      this.save();
      for (let attempt = 1; ; attempt++) {
        try {
          if (await this.send(f)) return;
          attempt = 0; // the server asked for a fresh start (checksum, expired upload)
        } catch (e) {
          const transient = !(e instanceof ApiError) || e.status >= 500 || e.status === 429;
          if (!transient || attempt >= 6) throw e;
          f.state = "retrying";
          f.error = e.message;
          this.emit(f);
          await sleep(Math.min(1000 * 2 ** (attempt - 1), 15000));
        }
      }
    } catch (e) {
      f.state = "error";
      f.error = e.message;
      if (e instanceof ApiError && ["scene-committed", "scene-validating", "not-found"].includes(e.type)) {
        this.fatal = e.message; // the scene itself refuses files: stop every worker
      }
      this.emit(f);
    }
  }

  /** One create-then-PATCH pass; true when the file is complete on the server. */
  async send(f) {
    const base = `/v1/scenes/${enc(this.sceneId)}/uploads`;
    const upl = await getJson(base, { method: "POST", json: { path: f.path, size: f.size, sha256: f.sha256 } });
    f.offset = upl.offset;
    f.error = null;
    if (upl.state === "complete") {
      f.state = f.sentHere || !f.size ? "done" : "present";
      this.emit(f);
      return true;
    }
    if (f.resumedFrom == null) f.resumedFrom = upl.offset;
    const chunk = Math.max(1, Math.min(this.chunkBytes, upl.chunk_max_bytes || this.chunkBytes));
    f.state = "uploading";
    this.emit(f);
    for (;;) {
      await this.gate();
      if (this.stopped) { f.state = "stopped"; this.emit(f); return true; }
      const from = f.offset;
      const to = Math.min(from + chunk, f.size);
      let next;
      try {
        // read the chunk first: a file that changed or vanished on disk fails here, not mid-request
        const body = await f.file.slice(from, to).arrayBuffer();
        this.inflight += 1;
        try {
          next = await getJson(`${base}/${enc(upl.id)}`, {
            method: "PATCH",
            headers: { "Upload-Offset": String(from), "Content-Type": "application/offset+octet-stream" },
            body,
          });
        } finally {
          this.inflight -= 1;
          if (this.paused) this.emit(f);
        }
      } catch (e) {
        if (e instanceof ApiError && e.type === "offset-mismatch" && Number.isFinite(e.problem.offset)) {
          f.offset = e.problem.offset; // the server holds more (or less): go on from there
          continue;
        }
        if (e instanceof ApiError && e.type === "checksum-mismatch") {
          // the server reset the upload: the bytes sent do not match the announced SHA-256
          // (the file changed while it was sent). Hash again; a new digest starts afresh.
          const again = await hashFile(f.file, { wholeMax: this.hashWholeMax });
          if (again === f.sha256) throw e;
          f.sha256 = again;
          f.offset = 0;
          return false;
        }
        if (e instanceof ApiError && e.status === 404) return false; // expired: announce again
        throw e;
      }
      this.chunks += 1;
      const sent = to - from;
      f.sentHere += sent;
      this.bytesSent += sent;
      f.offset = next.offset;
      if (next.state === "complete") {
        f.state = "done";
        f.offset = f.size;
        this.emit(f);
        return true;
      }
      if (sent === 0) throw new Error("the server did not complete the file after its last byte");
      this.emit(f);
    }
  }
}

// ---- one archive, one request -----------------------------------------------------------

const ARCHIVE_TYPES = [
  [/\.zip$/i, "application/zip"],
  [/\.(tgz|tar\.gz|gz)$/i, "application/gzip"],
  [/\.(tbz2|tar\.bz2|bz2)$/i, "application/x-bzip2"],
  [/\.(txz|tar\.xz|xz)$/i, "application/x-xz"],
  [/\.tar$/i, "application/x-tar"],
];

/**
 * POST /v1/scenes/{id}/archive with the whole archive as the body. XMLHttpRequest, not
 * fetch, because it reports upload progress: onProgress(loaded, total). Not resumable.
 */
export function uploadArchive(sceneId, file, onProgress) {
  const type = (ARCHIVE_TYPES.find(([re]) => re.test(file.name)) || [null, "application/octet-stream"])[1];
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open("POST", `/v1/scenes/${enc(sceneId)}/archive`);
    xhr.setRequestHeader("Authorization", `Bearer ${auth.key}`);
    xhr.setRequestHeader("Content-Type", type);
    xhr.upload.onprogress = (ev) => onProgress(ev.loaded, ev.lengthComputable ? ev.total : file.size);
    xhr.onload = () => {
      let body = null;
      try { body = JSON.parse(xhr.responseText); } catch { /* not JSON */ }
      if (xhr.status >= 200 && xhr.status < 300) resolve(body);
      else {
        const err = new ApiError(xhr.status, body);
        if (xhr.status === 401 && auth.onUnauthorized) auth.onUnauthorized(err);
        reject(err);
      }
    };
    xhr.onerror = () => reject(new Error("the connection failed during the upload"));
    xhr.send(file);
  });
}

/** The scene's open uploads on the server (GET /v1/scenes/{id}/uploads), every page. */
export async function openUploads(sceneId) {
  try {
    const items = [];
    for (let offset = 0; ; ) {
      const page = await getJson(`/v1/scenes/${enc(sceneId)}/uploads?limit=200&offset=${offset}`);
      items.push(...page.items);
      offset += page.limit;
      if (!page.items.length || offset >= page.total) return items;
    }
  } catch (e) {
    if (e instanceof ApiError && (e.status === 404 || e.status === 405)) return [];
    throw e;
  }
}

