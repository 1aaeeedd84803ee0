// Glint dashboard: scenes, uploads, jobs, charts, artifacts and meshes, on the public REST
// API only, with the key the user pastes (docs/dashboard.md). Plain ES modules, no build.
import { ApiError, api, auth, createScene, followEvents, getJson, listAll } from "./api.js";
import { drawChart } from "./chart.js";
import {
  SceneUpload, dropRecord, loadRecords, openUploads, readDrop, readInput, recordOf, uploadArchive,
} from "./upload.js";
import { $, TERMINAL, append, enc, fmtAgo, fmtBytes, fmtDuration, h, sceneName } from "./util.js";

const KEY_STORE = "glint-dashboard-key";
const POLL_MS = 3000;

const S = {
  me: null, scenes: [], jobs: [], sceneTotal: 0, jobTotal: 0, view: null,
  uploads: new Map(), // scene id → the upload running in this tab (SceneUpload or ArchiveUpload)
  pollTimer: null, lists: 0,
};
window.glintDashboard = S; // for debugging and the browser test

// ---- messages ---------------------------------------------------------------------------

function showError(e, prefix = "") {
  const msg = e instanceof Error ? e.message : String(e);
  $("#alert-text").textContent = prefix ? `${prefix}: ${msg}` : msg;
  $("#alert").hidden = false;
}
$("#alert-close").addEventListener("click", () => { $("#alert").hidden = true; });
function announce(text) { $("#status").textContent = text; }

function pill(el, state, text = state) {
  el.className = `pill ${state}`;
  el.textContent = text;
  return el;
}

function problemBox(box, err, heading) {
  box.replaceChildren();
  if (!err) { box.hidden = true; return; }
  const p = err.problem || err; // an ApiError or a stored problem (scene.last_error)
  box.append(h("p", null, h("strong", null, heading), " ", p.detail || err.message || p.title || ""));
  const errors = Array.isArray(p.errors) ? p.errors : [];
  if (errors.length) {
    box.append(h("ul", null, errors.map((e) => h("li", null,
      h("code", null, [e.file, e.field].filter(Boolean).join(" · ") || "—"), " ", e.message || ""))));
  }
  box.hidden = false;
}

function confirmDialog(text, ok = "Delete") {
  const dlg = $("#confirm");
  $("#confirm-text").textContent = text;
  $("#confirm-ok").textContent = ok;
  dlg.returnValue = "";
  return new Promise((resolve) => {
    dlg.addEventListener("close", () => resolve(dlg.returnValue === "ok"), { once: true });
    dlg.showModal();
  });
}

function saveBlob(blob, filename) {
  const url = URL.createObjectURL(blob);
  const a = h("a", { href: url, download: filename, hidden: true });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60000);
}

/** Download an artifact through fetch (the key in the header), with progress on the button. */
async function download(jobId, art, btn) {
  const label = btn.textContent;
  btn.disabled = true;
  try {
    const r = await api(art.url);
    const total = Number(r.headers.get("Content-Length")) || art.size || 1;
    const reader = r.body.getReader();
    const parts = [];
    let got = 0;
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      parts.push(value);
      got += value.length;
      btn.textContent = `${Math.floor((100 * got) / total)} %`;
    }
    saveBlob(new Blob(parts, { type: art.content_type }), `${jobId}_${art.name.replaceAll("/", "_")}`);
    announce(`Downloaded ${art.name}`);
  } catch (e) {
    showError(e, `Download of ${art.name} failed`);
  } finally {
    btn.disabled = false;
    btn.textContent = label;
  }
}

function downloadButton(jobId, art, text = "Download") {
  const b = h("button", {
    type: "button", class: "small", dataset: { download: art.name },
    "aria-label": `Download ${art.name} (${fmtBytes(art.size)})`,
  }, text);
  b.addEventListener("click", () => download(jobId, art, b));
  return b;
}

// ---- key ----------------------------------------------------------------------------------

let signingIn = false;

function showLogin(message = "") {
  stopPolling();
  if (S.view) { S.view.destroy(); S.view = null; }
  $("#shell").hidden = true;
  $("#forget").hidden = true;
  $("#who").textContent = "";
  $("#login").hidden = false;
  $("#login-error").textContent = message;
  $("#login-key").value = "";
  $("#login-key").focus();
}

async function signIn(key) {
  auth.key = key;
  signingIn = true;
  try {
    S.me = await getJson("/v1/keys/me");
  } catch (e) {
    auth.key = null;
    if (e instanceof ApiError && e.status === 401) localStorage.removeItem(KEY_STORE);
    showLogin(e instanceof ApiError ? `This key was refused: ${e.message}` : `Cannot reach the server: ${e.message}`);
    return false;
  } finally {
    signingIn = false;
  }
  localStorage.setItem(KEY_STORE, key);
  $("#login").hidden = true;
  $("#shell").hidden = false;
  $("#forget").hidden = false;
  const ro = S.me.scope === "read" ? " — read only: uploads, training and deletions are refused" : "";
  $("#who").textContent = `${S.me.owner} · key “${S.me.name}” · ${S.me.scope}${ro}`;
  startPolling();
  route();
  return true;
}

auth.onUnauthorized = (e) => {
  if (signingIn) return;
  auth.key = null;
  localStorage.removeItem(KEY_STORE);
  showLogin(`The server refused the key: ${e.message}`);
};

$("#login-form").addEventListener("submit", (e) => {
  e.preventDefault();
  const key = $("#login-key").value.trim();
  if (key) signIn(key);
});

$("#forget").addEventListener("click", () => {
  for (const up of S.uploads.values()) if (up.stop) up.stop();
  S.uploads.clear();
  localStorage.removeItem(KEY_STORE);
  auth.key = null;
  S.me = null;
  history.replaceState(null, "", `${location.pathname}#/`);
  showLogin("The key was removed from this browser.");
});

// ---- lists (polled) ---------------------------------------------------------------------

function startPolling() {
  stopPolling();
  refreshLists();
  S.pollTimer = setInterval(() => { if (!document.hidden) refreshLists(); }, POLL_MS);
}
function stopPolling() { clearInterval(S.pollTimer); S.pollTimer = null; }

let listsBusy = false;
async function refreshLists() {
  if (listsBusy || !auth.key) return;
  listsBusy = true;
  try {
    const [sc, jb] = await Promise.all([
      getJson("/v1/scenes?limit=100"), getJson("/v1/jobs?kind=train&limit=100"),
    ]);
    S.scenes = sc.items;
    S.sceneTotal = sc.total;
    S.jobs = jb.items;
    S.jobTotal = jb.total;
    S.lists += 1;
    renderLists();
    if (S.view && S.view.onLists) S.view.onLists();
  } catch (e) {
    if (!(e instanceof ApiError && e.status === 401)) console.warn("lists:", e);
  } finally {
    listsBusy = false;
  }
}

/** Keyed update of a list: items keep their element (and focus) across refreshes. */
function syncList(ul, items, keyOf, make, update) {
  const old = new Map(Array.from(ul.children, (li) => [li.dataset.key, li]));
  let prev = null;
  for (const item of items) {
    const k = keyOf(item);
    let li = old.get(k);
    if (li) old.delete(k);
    else { li = make(item); li.dataset.key = k; }
    update(li, item);
    const want = prev ? prev.nextSibling : ul.firstChild;
    if (li !== want) ul.insertBefore(li, want);
    prev = li;
  }
  for (const li of old.values()) li.remove();
}

const sceneNameOf = (id) => (S.scenes.find((s) => s.id === id) || {}).name || id;

function jobLine(j) {
  const parts = [];
  if (j.state === "running" || j.state === "queued") {
    if (j.total_iterations) parts.push(`it ${j.iteration.toLocaleString()} / ${j.total_iterations.toLocaleString()}`);
    const left = j.time_left_s ?? j.eta_s;
    if (j.state === "running" && left != null) parts.push(`${fmtDuration(left)} left`);
  }
  const m = j.metrics || {};
  if (m.psnr != null) parts.push(`${m.psnr.toFixed(2)} dB`);
  if (TERMINAL.has(j.state)) parts.push(fmtAgo(j.finished_at || j.updated_at));
  return parts.join(" · ");
}

function renderLists() {
  $("#scene-count").textContent = S.sceneTotal ? `(${S.sceneTotal})` : "";
  $("#job-count").textContent = S.jobTotal ? `(${S.jobTotal})` : "";
  const records = loadRecords();
  syncList($("#scene-list"), S.scenes, (s) => s.id,
    () => h("li", null, h("a", { class: "item" },
      h("span", { class: "line" }, h("span", { class: "name" }), h("span", { class: "pill" })),
      h("span", { class: "meta" }))),
    (li, s) => {
      const a = li.firstChild;
      a.href = `#/scenes/${s.id}`;
      a.querySelector(".name").textContent = s.name;
      pill(a.querySelector(".pill"), s.state);
      const unfinished = S.uploads.has(s.id) && !S.uploads.get(s.id).finished ? " · uploading"
        : records[s.id] ? " · upload unfinished" : "";
      a.querySelector(".meta").textContent = `${s.file_count} files · ${fmtBytes(s.total_bytes)}${unfinished}`;
    });
  if (!S.scenes.length) $("#scene-list").replaceChildren(h("li", { class: "empty muted" }, "No scenes yet."));
  syncList($("#job-list"), S.jobs, (j) => j.id,
    () => h("li", null, h("a", { class: "item" },
      h("span", { class: "line" }, h("span", { class: "name" }), h("span", { class: "pill" })),
      h("span", { class: "bar" }, h("span")),
      h("span", { class: "meta" }))),
    (li, j) => {
      const a = li.firstChild;
      a.href = `#/jobs/${j.id}`;
      a.querySelector(".name").textContent = sceneNameOf(j.scene_id);
      a.title = j.id;
      pill(a.querySelector(".pill"), j.state, j.cancel_requested && j.state === "running" ? "cancelling" : j.state);
      a.querySelector(".bar > span").style.width = `${Math.round((j.progress || 0) * 100)}%`;
      a.querySelector(".meta").textContent = [`…${j.id.slice(-6)}`, jobLine(j)].filter(Boolean).join(" · ");
    });
  if (!S.jobs.length) $("#job-list").replaceChildren(h("li", { class: "empty muted" }, "No jobs yet."));
  markCurrent();
}

function markCurrent() {
  for (const a of document.querySelectorAll(".side a.item")) {
    if (a.getAttribute("href") === location.hash) a.setAttribute("aria-current", "page");
    else a.removeAttribute("aria-current");
  }
}

// ---- routes -------------------------------------------------------------------------------

function route() {
  if (!S.me) return;
  const m = location.hash.match(/^#\/(scenes|jobs)\/([A-Za-z0-9_-]+)/);
  if (S.view) S.view.destroy();
  const main = $("#main");
  main.replaceChildren();
  S.view = !m ? overview() : m[1] === "scenes" ? sceneView(m[2]) : jobView(m[2]);
  main.append(S.view.el);
  markCurrent();
}
window.addEventListener("hashchange", () => {
  route();
  const h1 = $("#main h1");
  if (h1) h1.focus({ preventScroll: true });
});
// a file dropped outside a drop zone must not navigate away from the page
window.addEventListener("dragover", (e) => e.preventDefault());
window.addEventListener("drop", (e) => e.preventDefault());

// ---- drop zones and uploads ---------------------------------------------------------------

function dropzone(onSelect, title) {
  const inputs = {
    folder: h("input", { type: "file", id: "pick-folder", webkitdirectory: true, multiple: true }),
    files: h("input", { type: "file", id: "pick-files", multiple: true }),
    archive: h("input", { type: "file", id: "pick-archive", accept: ".zip,.tar,.tgz,.gz,.tbz2,.bz2,.txz,.xz" }),
  };
  for (const inp of Object.values(inputs)) {
    inp.className = "visually-hidden";
    inp.tabIndex = -1;
    inp.setAttribute("aria-hidden", "true");
    inp.addEventListener("change", () => {
      if (!inp.files.length) return;
      const sel = readInput(inp);
      inp.value = "";
      onSelect(sel);
    });
  }
  const zone = h("div", { class: "dropzone", id: "dropzone" },
    h("p", { class: "drop-title" }, title),
    h("p", { class: "muted small" },
      "A scene folder (NeRF/Blender, nerfstudio, COLMAP, LLFF, NeRO) or plain photos. Files go up in ",
      "resumable chunks, three at a time: after a reload or a dropped connection, drop the same ",
      "folder again and only what is missing is sent. A .zip or .tar(.gz) archive goes up in one ",
      "request and is not resumable."),
    h("div", { class: "row wrap" },
      h("button", { type: "button", onclick: () => inputs.folder.click() }, "Choose a folder…"),
      h("button", { type: "button", onclick: () => inputs.files.click() }, "Choose files…"),
      h("button", { type: "button", onclick: () => inputs.archive.click() }, "Choose an archive…")),
    Object.values(inputs));
  zone.addEventListener("dragover", (e) => {
    e.preventDefault();
    e.dataTransfer.dropEffect = "copy";
    zone.classList.add("over");
  });
  zone.addEventListener("dragleave", () => zone.classList.remove("over"));
  zone.addEventListener("drop", (e) => {
    e.preventDefault();
    e.stopPropagation();
    zone.classList.remove("over");
    readDrop(e.dataTransfer).then(onSelect, (err) => showError(err, "Cannot read the dropped files"));
  });
  return zone;
}

/** An archive upload's state, shaped like SceneUpload's for the panel. */
class ArchiveUpload {
  constructor(sceneId, file) {
    this.archive = true;
    this.sceneId = sceneId;
    this.file = file;
    this.loaded = 0;
    this.total = file.size;
    this.finished = false;
    this.error = null;
    this.result = null;
    this.listeners = new Set();
  }
  on(fn) { this.listeners.add(fn); return () => this.listeners.delete(fn); }
  emit() { for (const fn of this.listeners) fn(null); }
  async run() {
    try {
      this.result = await uploadArchive(this.sceneId, this.file, (loaded, total) => {
        this.loaded = loaded;
        this.total = total;
        this.emit();
      });
    } catch (e) {
      this.error = e;
    }
    this.finished = true;
    this.emit();
  }
}

function startUpload(scene, sel) {
  const cur = S.uploads.get(scene.id);
  if (cur && !cur.finished) {
    showError("An upload into this scene is already running in this tab: wait for it, or pause it first.");
    return null;
  }
  if (sel.skipped.length) {
    announce(`Left out ${sel.skipped.length} system file(s): ${sel.skipped.slice(0, 3).map((e) => e.path).join(", ")}`);
  }
  let up;
  if (sel.kind === "archive") {
    up = new ArchiveUpload(scene.id, sel.file);
  } else {
    if (!sel.entries.length) { showError("Nothing to upload: the selection holds no files."); return null; }
    up = new SceneUpload(scene.id, sel.entries, {
      owner: S.me.owner, sceneName: scene.name, tuning: window.__glintUploadTuning || {},
    });
  }
  S.uploads.set(scene.id, up);
  announce(`Uploading ${sel.kind === "archive" ? sel.file.name : `${sel.entries.length} files`} into ${scene.name}`);
  up.run().then(() => {
    const t = up.archive ? null : up.totals;
    if (up.archive) announce(up.error ? `Archive upload failed: ${up.error.message}` : "Archive uploaded");
    else announce(`Upload finished: ${t.done} of ${t.files} files on the server${t.failed ? `, ${t.failed} failed` : ""}`);
    refreshLists();
    if (S.view && S.view.onUploadDone) S.view.onUploadDone(scene.id);
  });
  if (S.view && S.view.onUpload) S.view.onUpload(scene.id, up);
  renderLists();
  return up;
}

const FILE_STATES = {
  queued: () => "waiting",
  hashing: (f) => `checking ${f.size ? Math.floor((100 * f.hashed) / f.size) : 100} %`,
  uploading: (f) => `${Math.floor((100 * f.offset) / (f.size || 1))} %${f.resumedFrom ? " (resumed)" : ""}`,
  retrying: (f) => `retrying: ${f.error}`,
  done: (f) => (f.resumedFrom ? "uploaded (resumed)" : "uploaded"),
  present: () => "already on the server",
  stopped: () => "stopped",
  error: (f) => `failed: ${f.error}`,
};

/** Progress of one upload: a summary, a bar, pause/resume, a row per file. */
function uploadPanel(up) {
  const summary = h("p", { class: "upl-summary", id: "upload-summary" });
  const bar = h("progress", { max: 1, value: 0, id: "upload-bar", "aria-label": "upload progress" });
  const el = h("div", { class: "upload", id: "upload-panel", dataset: { state: "running" } }, summary, bar);
  let frame = 0;
  const dirty = new Set();
  if (up.archive) {
    const paint = () => {
      frame = 0;
      bar.max = up.total || 1;
      bar.value = up.loaded;
      const pct = Math.floor((100 * up.loaded) / (up.total || 1));
      summary.textContent = up.error ? `${up.file.name}: failed: ${up.error.message}`
        : up.finished ? `${up.file.name}: uploaded and unpacked (${up.result ? up.result.files.length : 0} files)`
          : up.loaded >= up.total ? `${up.file.name}: unpacking on the server…`
            : `${up.file.name}: ${pct} % of ${fmtBytes(up.total)} (one request, not resumable)`;
      el.dataset.state = up.error ? "error" : up.finished ? "done" : "running";
    };
    up.on(() => { if (!frame) frame = requestAnimationFrame(paint); });
    paint();
    return { el, destroy: () => up.listeners.clear() };
  }
  const pauseBtn = h("button", { type: "button", id: "upload-pause", class: "small" }, "Pause");
  pauseBtn.addEventListener("click", () => (up.paused ? up.resume() : up.pause()));
  el.replaceChildren(h("div", { class: "row spread" }, summary, pauseBtn), bar);
  const list = h("ul", { class: "files", "aria-label": "files being uploaded" });
  const rows = new Map();
  for (const f of up.files) {
    const li = h("li", { dataset: { path: f.path, state: f.state } },
      h("span", { class: "path" }, f.path), h("span", { class: "size muted" }, fmtBytes(f.size)),
      h("progress", { max: f.size || 1, value: 0, "aria-label": f.path }), h("span", { class: "st" }));
    rows.set(f, li);
    list.append(li);
  }
  el.append(list);
  const paintFile = (f) => {
    const li = rows.get(f);
    li.dataset.state = f.state;
    li.querySelector("progress").value = f.state === "done" || f.state === "present" ? f.size || 1 : f.offset;
    li.querySelector(".st").textContent = FILE_STATES[f.state](f);
  };
  const paint = () => {
    frame = 0;
    for (const f of dirty) paintFile(f);
    dirty.clear();
    const t = up.totals;
    bar.max = t.bytes || 1;
    bar.value = t.onServer;
    const state = up.finished ? (t.done === t.files ? "done" : "incomplete")
      : up.paused ? (up.inflight ? "pausing" : "paused") : "running";
    el.dataset.state = state;
    pauseBtn.textContent = up.paused ? "Resume" : "Pause";
    pauseBtn.hidden = up.finished;
    const extra = state === "paused" ? " · paused" : state === "pausing" ? " · pausing after the chunks under way"
      : state === "incomplete"
      ? ` · ${t.failed} failed: fix them and drop the files again` : state === "done" ? " · done" : "";
    summary.textContent = `${t.done} of ${t.files} files · ${fmtBytes(t.onServer)} of ${fmtBytes(t.bytes)} on the server` +
      `${t.present ? ` (${t.present} were already there)` : ""}${up.fatal ? ` · stopped: ${up.fatal}` : ""}${extra}`;
  };
  up.files.forEach((f) => dirty.add(f));
  up.on((f) => {
    if (f) dirty.add(f);
    if (!frame) frame = requestAnimationFrame(paint);
  });
  paint();
  return { el, destroy: () => up.listeners.clear() };
}

// ---- overview -------------------------------------------------------------------------------

function overview() {
  const el = h("article", { class: "view" });
  const nameInput = $("#new-scene-name");
  const onSelect = async (sel) => {
    try {
      const scene = await createScene(nameInput.value.trim() || sceneName(sel.name || "scene"));
      nameInput.value = "";
      location.hash = `#/scenes/${scene.id}`;
      startUpload(scene, sel);
    } catch (e) {
      showError(e, "Cannot create the scene");
    }
  };
  const records = Object.entries(loadRecords()).filter(([, r]) => r.owner === S.me.owner);
  const running = h("p", { class: "muted" });
  append(el, [
    h("h1", { tabindex: -1 }, "Overview"),
    h("section", { class: "card" },
      h("h2", null, "Start a scene"),
      dropzone(onSelect, "Drop a folder, a zip or photos here to make a new scene"),
      h("p", { class: "muted small" }, "The scene is named after the folder (or the name typed under ",
        h("em", null, "New scene"), "). Then commit it to validate, and train.")),
    records.length ? h("section", { class: "card" },
      h("h2", null, "Unfinished uploads"),
      h("ul", { class: "plain" }, records.map(([id, r]) => h("li", null,
        h("a", { href: `#/scenes/${id}` }, r.sceneName || id), ` — ${r.files.length} files; open the scene and drop the same folder again to go on`))))
      : null,
    h("section", { class: "card" }, h("h2", null, "Jobs"), running,
      h("p", { class: "muted small" }, "Open a job on the left for its chart, stages, artifacts, mesh and live viewer."))]);
  const onLists = () => {
    const by = (st) => S.jobs.filter((j) => j.state === st).length;
    running.textContent = `${by("running")} running · ${by("queued")} queued · ${by("succeeded")} succeeded · ${by("failed")} failed (of the latest ${S.jobs.length})`;
  };
  if (S.lists) onLists();
  return { el, destroy() {}, onLists };
}

// ---- scene ----------------------------------------------------------------------------------

function reportList(r) {
  const rows = [
    ["format", r.format + (r.needs_sfm ? " (photos without poses: jobs start with structure from motion)" : "")],
    ["views", `${r.views} (${r.train_views} train, ${r.test_views} test)`],
    ["resolution", r.resolution ? r.resolution.join(" × ") : "—"],
    ["masks", r.masks ? "yes" : "no"],
  ];
  if (r.points) rows.push(["points", r.points.toLocaleString()]);
  if (r.intrinsics) rows.push(["focal", `${r.intrinsics.fx.toFixed(1)} px`]);
  const dl = h("dl", { class: "kv" }, rows.map(([k, v]) => [h("dt", null, k), h("dd", null, v)]));
  if (r.warnings && r.warnings.length) {
    return [dl, h("ul", { class: "warnings" }, r.warnings.map((w) => h("li", null, w)))];
  }
  return dl;
}

function sceneView(id) {
  const el = h("article", { class: "view", dataset: { scene: id } });
  let scene = null;
  let alive = true;
  let shownState = null;
  let panel = null;
  const title = h("h1", { tabindex: -1 }, "Scene");
  const statePill = h("span", { class: "pill", id: "scene-state", "aria-live": "polite" });
  const meta = h("p", { class: "muted meta" });
  const delBtn = h("button", { type: "button", class: "danger", id: "scene-delete" }, "Delete scene");
  const lastError = h("div", { class: "problem", hidden: true, id: "scene-error" });

  // open: add files, then commit
  const uploadSlot = h("div");
  const resumeBox = h("div", { class: "resume", id: "resume", hidden: true });
  const commitBtn = h("button", { type: "button", class: "primary", id: "commit" }, "Commit and validate");
  const commitNote = h("span", { class: "muted small" }, "Freezes the files and checks the scene (its format is detected).");
  const commitError = h("div", { class: "problem", role: "alert", hidden: true, id: "commit-error" });
  const uploadSec = h("section", { class: "card", hidden: true },
    h("h2", null, "Files"),
    dropzone((sel) => scene && startUpload(scene, sel), "Drop a folder, a zip or photos here to add them"),
    resumeBox, uploadSlot,
    h("div", { class: "row commit" }, commitBtn, commitNote), commitError);

  // ready: the report and a training form
  const reportBox = h("div");
  const trainError = h("div", { class: "problem", role: "alert", hidden: true, id: "train-error" });
  const iterations = h("input", { id: "train-iterations", type: "number", min: 1, max: 10000000, step: 1, value: 7000 });
  const budget = h("input", { id: "train-budget", placeholder: "e.g. 5m, 90s, 1h30m", autocomplete: "off" });
  const device = h("select", { id: "train-device" }, h("option", { value: "cpu" }, "cpu"), h("option", { value: "cuda" }, "cuda (GPU worker)"));
  const configText = h("textarea", { id: "train-config", rows: 5, spellcheck: "false", placeholder: '{"outputs": {"mesh_resolution": 384}}' });
  const trainForm = h("form", { id: "train-form", class: "train" },
    h("div", { class: "fields" },
      h("label", null, "Iterations", iterations),
      h("label", null, "Time budget (optional)", budget),
      h("label", null, "Device", device)),
    h("details", null, h("summary", null, "More settings (training config as JSON)"),
      h("label", { for: "train-config", class: "muted small" },
        "Any field of the training config (docs/api.md, Jobs); the fields above override it."),
      configText),
    h("div", { class: "row" }, h("button", { type: "submit", class: "primary", id: "train-start" }, "Train"),
      h("span", { class: "muted small" }, "With both limits, whichever comes first ends the run. Empty iterations with a budget: the budget sizes the run.")),
    trainError);
  const readySec = h("section", { class: "card", hidden: true },
    h("h2", null, "Validation report"), reportBox, h("h2", null, "Train"), trainForm);

  const jobList = h("ul", { class: "list inline", id: "scene-jobs" });
  const jobsSec = h("section", { class: "card" }, h("h2", null, "Jobs on this scene"), jobList);
  const filesList = h("div", { class: "filelist" });
  const filesSec = h("details", { class: "card", id: "scene-files" }, h("summary", null, "Files on the server"), filesList);

  el.append(
    h("header", { class: "viewhead" },
      h("div", { class: "titles" }, title, statePill),
      h("div", { class: "actions" }, delBtn)),
    meta, lastError, uploadSec, readySec, jobsSec, filesSec);

  function render() {
    title.textContent = scene.name;
    pill(statePill, scene.state);
    meta.textContent = [scene.id, scene.format, `${scene.file_count} files`, fmtBytes(scene.total_bytes),
      `created ${fmtAgo(scene.created_at)}`].filter(Boolean).join(" · ");
    const open = scene.state === "open";
    uploadSec.hidden = !open;
    readySec.hidden = scene.state !== "ready";
    const busy = S.uploads.has(id) && !S.uploads.get(id).finished;
    commitBtn.disabled = !open || busy || scene.file_count === 0;
    if (open && scene.last_error) problemBox(lastError, scene.last_error, "The last commit failed:");
    else problemBox(lastError, null);
    if (scene.state !== shownState) {
      shownState = scene.state;
      if (scene.state === "ready" && scene.report) reportBox.replaceChildren(reportList(scene.report));
      if (open) renderResume();
    }
  }

  async function load() {
    try {
      scene = await getJson(`/v1/scenes/${enc(id)}`);
      if (alive) render();
    } catch (e) {
      if (e instanceof ApiError && e.status === 404) {
        el.replaceChildren(h("h1", { tabindex: -1 }, "Scene not found"),
          h("p", null, `No scene ${id} for this key (deleted, or another owner's).`));
        alive = false;
      } else showError(e, "Cannot load the scene");
    }
  }

  async function loadJobs() {
    try {
      const page = await getJson(`/v1/jobs?scene_id=${enc(id)}&kind=train&limit=50`);
      if (!alive) return;
      syncList(jobList, page.items, (j) => j.id,
        () => h("li", null, h("a", { class: "item" },
          h("span", { class: "line" }, h("span", { class: "name" }), h("span", { class: "pill" })), h("span", { class: "meta" }))),
        (li, j) => {
          const a = li.firstChild;
          a.href = `#/jobs/${j.id}`;
          a.querySelector(".name").textContent = j.id;
          pill(a.querySelector(".pill"), j.state);
          a.querySelector(".meta").textContent = jobLine(j) || fmtAgo(j.created_at);
        });
      if (!page.items.length) jobList.replaceChildren(h("li", { class: "empty muted" }, "No jobs yet."));
    } catch (e) {
      console.warn(e);
    }
  }

  // after a reload: what the local record and the server say is left to send
  async function renderResume() {
    const running = () => S.uploads.has(id) && !S.uploads.get(id).finished;
    if (running()) { resumeBox.hidden = true; return; }
    const rec = recordOf(id, S.me.owner);
    let open = [];
    try { open = await openUploads(id); } catch (e) { console.warn(e); }
    if (!alive) return;
    if (!rec && !open.length) { resumeBox.hidden = true; return; }
    const partial = new Map(open.map((u) => [u.path, u]));
    let rows = [];
    let done = 0;
    if (rec) {
      const files = new Map((await listAll(`/v1/scenes/${enc(id)}/files`)).map((f) => [f.path, f]));
      for (const [path, size, sha] of rec.files) {
        const f = files.get(path), u = partial.get(path);
        if (f && f.size === size && (!sha || f.sha256 === sha)) { done += 1; rows.push([path, size, size, "on the server"]); }
        else if (u) rows.push([path, size, u.offset, `${Math.floor((100 * u.offset) / (size || 1))} % sent`]);
        else rows.push([path, size, 0, "not started"]);
      }
    } else {
      rows = open.map((u) => [u.path, u.size, u.offset, `${Math.floor((100 * u.offset) / (u.size || 1))} % sent`]);
    }
    if (!alive || running()) return; // the files were chosen again meanwhile
    const total = rows.length;
    const forget = h("button", { type: "button", class: "small" }, "Forget this upload");
    forget.addEventListener("click", () => { dropRecord(id); resumeBox.hidden = true; renderLists(); });
    resumeBox.replaceChildren();
    append(resumeBox, [
      h("p", null, h("strong", null, "Unfinished upload. "),
        rec ? `${done} of ${total} files are on the server, ${rows.filter((r) => r[2] > 0 && r[2] < r[1]).length} partly. `
          : `The server holds ${total} unfinished file(s) for this scene. `,
        "Drop the same folder (or choose it again) to go on: complete files are skipped, partial ones continue where they stopped."),
      h("ul", { class: "files", "aria-label": "files of the unfinished upload" }, rows.slice(0, 500).map(([path, size, got, text]) =>
        h("li", { dataset: { path } }, h("span", { class: "path" }, path), h("span", { class: "size muted" }, fmtBytes(size)),
          h("progress", { max: size || 1, value: got, "aria-label": path }), h("span", { class: "st" }, text)))),
      rec ? h("div", { class: "row" }, forget) : null]);
    resumeBox.hidden = false;
  }

  function attach(up) {
    if (panel) panel.destroy();
    panel = uploadPanel(up);
    uploadSlot.replaceChildren(panel.el);
    resumeBox.hidden = true;
  }

  commitBtn.addEventListener("click", async () => {
    commitBtn.disabled = true;
    commitNote.textContent = "Validating…";
    problemBox(commitError, null);
    try {
      scene = await getJson(`/v1/scenes/${enc(id)}/commit`, { method: "POST" });
      dropRecord(id);
      announce(`Scene ${scene.name} is ready to train`);
      refreshLists();
    } catch (e) {
      problemBox(commitError, e, "Commit failed:");
      await load();
    } finally {
      commitNote.textContent = "Freezes the files and checks the scene (its format is detected).";
      if (scene) render();
    }
  });

  delBtn.addEventListener("click", async () => {
    if (!scene) return;
    if (!(await confirmDialog(`Delete scene “${scene.name}” and its ${scene.file_count} files? Jobs that use it must be deleted first.`))) return;
    try {
      await api(`/v1/scenes/${enc(id)}`, { method: "DELETE" });
      dropRecord(id);
      announce(`Scene ${scene.name} deleted`);
      location.hash = "#/";
      refreshLists();
    } catch (e) {
      showError(e, "Cannot delete the scene");
    }
  });

  trainForm.addEventListener("submit", async (e) => {
    e.preventDefault();
    problemBox(trainError, null);
    let config = {};
    try {
      const text = configText.value.trim();
      config = text ? JSON.parse(text) : {};
      if (!config || typeof config !== "object" || Array.isArray(config)) throw new Error("it must be a JSON object");
    } catch (err) {
      problemBox(trainError, { detail: `The config is not valid JSON: ${err.message}` }, "");
      configText.focus();
      return;
    }
    if (iterations.value) config.iterations = Number(iterations.value);
    else if (budget.value.trim()) delete config.iterations;
    const b = budget.value.trim();
    if (b) config.time_budget = /^\d+(\.\d+)?$/.test(b) ? Number(b) : b;
    config.device = device.value;
    const btn = $("#train-start", trainForm);
    btn.disabled = true;
    try {
      const job = await getJson("/v1/jobs", { method: "POST", json: { scene_id: id, config } });
      announce(`Job ${job.id} queued`);
      refreshLists();
      location.hash = `#/jobs/${job.id}`;
    } catch (err) {
      problemBox(trainError, err, "Cannot start the job:");
      const field = err.field || "";
      const target = field.endsWith(".time_budget") ? budget : field.endsWith(".iterations") ? iterations
        : field.endsWith(".device") ? device : field.startsWith("body.config") ? configText : null;
      if (target) { target.setAttribute("aria-invalid", "true"); target.focus(); }
    } finally {
      btn.disabled = false;
    }
  });
  for (const inp of [iterations, budget, device, configText]) inp.addEventListener("input", () => inp.removeAttribute("aria-invalid"));

  filesSec.addEventListener("toggle", async () => {
    if (!filesSec.open) return;
    filesList.replaceChildren(h("p", { class: "muted" }, "Loading…"));
    try {
      const files = await listAll(`/v1/scenes/${enc(id)}/files`, { max: 2000 });
      filesList.replaceChildren(files.length
        ? h("table", { class: "table" }, h("thead", null, h("tr", null, h("th", null, "path"), h("th", { class: "num" }, "size"))),
          h("tbody", null, files.map((f) => h("tr", null, h("td", null, f.path), h("td", { class: "num" }, fmtBytes(f.size))))))
        : h("p", { class: "muted" }, "No files yet."));
    } catch (e) {
      filesList.replaceChildren(h("p", { class: "error" }, e.message));
    }
  });

  // a GPU worker on the queue: default to cuda
  getJson("/v1/workers?limit=50").then((page) => {
    if (page.items.some((w) => String(w.device).startsWith("cuda"))) device.value = "cuda";
  }).catch(() => {});

  load().then(() => {
    const up = S.uploads.get(id);
    if (up) attach(up);
  });
  loadJobs();
  return {
    el,
    destroy() { alive = false; if (panel) panel.destroy(); },
    onLists() { if (alive) { load(); loadJobs(); } },
    onUpload(sceneId, up) { if (sceneId === id && alive) { attach(up); if (scene) render(); } },
    onUploadDone(sceneId) { if (sceneId === id && alive) load(); },
  };
}

// ---- job ------------------------------------------------------------------------------------

const PHASES = [
  ["sfm", "Cameras (SfM)"], ["rgb", "RGB"], ["geometry", "+ single view & env map"],
  ["multiview", "+ multi-view"], ["mesh", "Mesh"], ["asset", "Asset"],
];

function stagesOf(job) {
  const outputs = job.config.outputs || {};
  const asset = job.kind === "mesh" ? !!job.config.asset : !!outputs.asset; // a relightable asset after the mesh
  const want = PHASES.filter(([k]) => (k === "sfm" ? !!job.sfm : k === "mesh" ? job.kind === "mesh" || outputs.mesh !== false
    : k === "asset" ? asset : job.kind !== "mesh"));
  const st = job.stage;
  let cur = job.kind === "mesh" ? (job.phase === "asset" ? "asset" : "mesh") : job.phase;
  if (st && st.name && job.state === "running") cur = ["sfm", "mesh", "asset"].includes(st.name) ? st.name : cur;
  let idx = want.findIndex(([k]) => k === cur);
  if (job.state === "succeeded") idx = want.length;
  if (job.state === "queued" && idx < 0) idx = -1;
  return want.map(([k, label], i) => {
    let status = "next";
    if (job.state !== "queued" && i < idx) status = "done";
    else if (job.state !== "queued" && i === idx) status = job.state === "running" ? "current" : "stopped";
    const detail = i === idx && st && st.name === k && job.state === "running"
      ? `${st.step || ""}${st.total ? ` ${st.done}/${st.total}` : ""}` : "";
    return { key: k, label, status, detail };
  });
}

function jobView(id) {
  const ctrl = new AbortController();
  const el = h("article", { class: "view", dataset: { job: id } });
  let job = null;
  let alive = true;
  let following = false;
  let metricsIt; // undefined: the first update always reads the metrics
  let metricsRows = [];
  let previewUrl = null;
  let previewSha = null;
  let meshTimer = null;
  const meshArtifacts = new Map();

  const title = h("h1", { tabindex: -1 }, `Job ${id}`);
  const statePill = h("span", { class: "pill", id: "job-state", "aria-live": "polite" });
  const meta = h("p", { class: "muted meta" });
  const viewer = h("a", { class: "button", id: "open-viewer", target: "_blank", rel: "noopener" }, "Open live viewer ↗");
  const meshView = h("a", { class: "button", id: "open-mesh-view", target: "_blank", rel: "noopener", hidden: true,
    title: "the relightable asset (asset.glb) lit by its environment, in the browser" }, "Asset view ↗");
  const cancelBtn = h("button", { type: "button", id: "job-cancel" }, "Cancel");
  const resumeBtn = h("button", { type: "button", id: "job-resume" }, "Resume");
  const deleteBtn = h("button", { type: "button", class: "danger", id: "job-delete" }, "Delete job");
  const progress = h("progress", { id: "job-progress", max: 1, value: 0, "aria-label": "training progress" });
  const progText = h("span", { class: "mono", id: "job-iter" });
  const timeText = h("span", { id: "job-time" });
  const stages = h("ol", { class: "stages", id: "job-stages", "aria-label": "stages" });
  const errBox = h("div", { class: "problem", id: "job-error", hidden: true });

  const canvas = h("canvas", { id: "chart", role: "img", "aria-label": "error against training time: no data yet" });
  const chartNote = h("p", { class: "muted small", id: "chart-note" });
  const chartTable = h("tbody");
  const chartSec = h("section", { class: "card chart-card" },
    h("h2", null, "Error against training time"), h("div", { class: "chart-box" }, canvas), chartNote,
    h("details", null, h("summary", null, "As a table"),
      h("table", { class: "table" }, h("thead", null, h("tr", null, ["iteration", "time", "phase", "PSNR dB", "SSIM", "CD×10²", "Gaussians"].map((t) => h("th", { class: "num" }, t)))), chartTable)));

  const preview = h("img", { id: "mesh-preview", alt: "mesh preview: normals and colour from two viewpoints", hidden: true });
  const previewNote = h("p", { class: "muted small", id: "mesh-preview-note" }, "The mesh preview appears when the job has made a mesh.");
  const meshRes = h("select", { id: "mesh-res" }, [64, 128, 256, 384, 512].map((r) => h("option", { value: r, selected: r === 256 }, `${r}³`)));
  const meshColor = h("select", { id: "mesh-color" }, h("option", { value: "base" }, "base colour"), h("option", { value: "radiance" }, "radiance"));
  const meshStart = h("button", { type: "submit", id: "mesh-start" }, "Extract mesh");
  const meshAsset = h("input", { type: "checkbox", id: "mesh-asset" });
  const meshForm = h("form", { class: "row wrap", id: "mesh-form" },
    h("label", null, "Grid ", meshRes), h("label", null, "Colour ", meshColor),
    h("label", { title: "also bake a relightable asset (glTF + environment HDR) from the mesh" }, meshAsset, " + asset"), meshStart);
  const meshError = h("div", { class: "problem", role: "alert", hidden: true });
  const meshList = h("ul", { class: "meshes", id: "meshes" });
  const meshSec = h("section", { class: "card mesh-card" }, h("h2", null, "Mesh"), preview, previewNote,
    h("h3", null, "Extract again"), meshForm, meshError, meshList);

  const artTotal = h("span", { class: "count" });
  const artBody = h("tbody");
  const artNote = h("p", { class: "muted small" }, "Loading…");
  const artTable = h("div", { class: "scroll", hidden: true }, h("table", { class: "table", id: "artifacts" },
    h("thead", null, h("tr", null, h("th", null, "name"), h("th", { class: "num" }, "size"), h("th", null, h("span", { class: "visually-hidden" }, "download")))),
    artBody));
  const artSec = h("section", { class: "card" }, h("h2", null, "Artifacts ", artTotal), artNote,
    artTable);

  el.append(
    h("header", { class: "viewhead" }, h("div", { class: "titles" }, title, statePill),
      h("div", { class: "actions" }, viewer, meshView, cancelBtn, resumeBtn, deleteBtn)),
    meta,
    h("div", { class: "progressline" }, progress, progText, timeText),
    stages, errBox,
    h("div", { class: "grid2" }, chartSec, meshSec),
    artSec);

  function update(j) {
    const prev = job;
    job = j;
    const cancelling = j.cancel_requested && j.state === "running";
    pill(statePill, j.state, cancelling ? "cancelling" : j.state);
    statePill.dataset.state = j.state;
    const scene = S.scenes.find((s) => s.id === j.scene_id);
    meta.replaceChildren(
      ...(j.kind === "mesh" ? ["mesh of ", h("a", { href: `#/jobs/${j.parent_id}` }, j.parent_id), " · "] : []),
      "scene ", h("a", { href: `#/scenes/${j.scene_id}` }, scene ? scene.name : j.scene_id),
      ` · ${[j.config.iterations ? `${j.config.iterations.toLocaleString()} iterations` : null,
        j.time_budget_s ? `budget ${fmtDuration(j.time_budget_s)}` : null, j.config.device,
        `created ${fmtAgo(j.created_at)}`, j.attempts > 1 ? `${j.attempts} attempts` : null].filter(Boolean).join(" · ")}`);
    progress.value = j.progress || 0;
    progText.textContent = j.kind === "mesh" ? `${Math.round((j.progress || 0) * 100)} %`
      : `it ${j.iteration.toLocaleString()} / ${j.total_iterations.toLocaleString()} (${Math.round((j.progress || 0) * 100)} %)`;
    const left = j.time_left_s ?? j.eta_s;
    timeText.textContent = [j.elapsed_s != null ? `${fmtDuration(j.elapsed_s)} elapsed` : null,
      j.state === "running" && left != null ? `about ${fmtDuration(left)} left${j.time_left_s != null ? " of the budget" : ""}` : null,
      j.state === "queued" ? "waiting for a worker" : null].filter(Boolean).join(" · ");
    stages.replaceChildren(...stagesOf(j).map((s) => h("li", { class: s.status, dataset: { stage: s.key } },
      h("span", { class: "label" }, s.label), s.detail ? h("span", { class: "detail muted" }, s.detail) : null,
      h("span", { class: "visually-hidden" }, ` (${s.status})`))));
    if (j.error) problemBox(errBox, { detail: j.error }, j.state === "failed" ? "Failed:" : "Note:");
    else problemBox(errBox, null);
    viewer.href = `/viewer/${enc(id)}#key=${enc(auth.key)}`;
    viewer.hidden = j.kind === "mesh";
    cancelBtn.hidden = TERMINAL.has(j.state);
    cancelBtn.disabled = j.cancel_requested;
    resumeBtn.hidden = !(j.state === "failed" || j.state === "cancelled");
    deleteBtn.hidden = !TERMINAL.has(j.state);
    chartSec.hidden = j.kind === "mesh";
    meshForm.hidden = j.kind === "mesh";
    meshStart.disabled = j.state !== "succeeded";
    const it = j.metrics ? j.metrics.iteration : null;
    if (it !== metricsIt) { metricsIt = it; loadMetrics(); }
    if (TERMINAL.has(j.state) && !(prev && TERMINAL.has(prev.state))) {
      loadArtifacts();
      loadMeshes();
      if (prev) { loadMetrics(); refreshLists(); }
    }
  }

  async function loadMetrics() {
    if (job && job.kind === "mesh") return;
    try {
      const page = await getJson(`/v1/jobs/${enc(id)}/metrics?points=400`);
      if (!alive) return;
      metricsRows = page.items;
      paintChart();
      chartTable.replaceChildren(...metricsRows.map((r) => h("tr", null,
        [r.iteration, fmtDuration(r.wall_time), r.phase, r.psnr?.toFixed(2), r.ssim?.toFixed(3), r.cd_x100?.toFixed(3), r.n_gaussians?.toLocaleString()]
          .map((v, i) => h("td", { class: i === 2 ? null : "num" }, v ?? "—")))));
      const last = metricsRows[metricsRows.length - 1];
      const cd = [...metricsRows].reverse().find((r) => r.cd_x100 != null);
      chartNote.textContent = last ? [
        `latest: iteration ${last.iteration} at ${fmtDuration(last.wall_time)}`,
        last.psnr != null ? `PSNR ${last.psnr.toFixed(2)} dB` : null,
        last.ssim != null ? `SSIM ${last.ssim.toFixed(3)}` : null,
        cd ? `Chamfer ×10² ${cd.cd_x100.toFixed(3)}` : null,
        last.normal_error_deg != null ? `normal error ${last.normal_error_deg.toFixed(1)}°` : null,
        last.depth_normal_consistency_deg != null ? `depth–normal ${last.depth_normal_consistency_deg.toFixed(1)}°` : null,
      ].filter(Boolean).join(" · ") : "No evaluation yet.";
      canvas.setAttribute("aria-label", `error against training time: ${metricsRows.length} evaluations; ${chartNote.textContent}`);
    } catch (e) {
      if (!(e instanceof ApiError && e.status === 404)) console.warn("metrics:", e);
    }
  }
  function paintChart() {
    if (chartSec.hidden) return;
    S.chart = drawChart(canvas, metricsRows, { budgetS: job ? job.time_budget_s : null });
  }
  const resize = new ResizeObserver(() => paintChart());
  resize.observe(canvas);

  async function showPreview(jobId, art) {
    if (!art) return;
    if (previewSha === art.sha256) return;
    try {
      const blob = await (await api(art.url)).blob();
      if (!alive) return;
      if (previewUrl) URL.revokeObjectURL(previewUrl);
      previewUrl = URL.createObjectURL(blob);
      previewSha = art.sha256;
      preview.src = previewUrl;
      preview.hidden = false;
      previewNote.textContent = jobId === id ? "From the training job's mesh." : `From mesh job ${jobId}.`;
    } catch (e) {
      previewNote.textContent = `No preview: ${e.message}`;
    }
  }

  async function loadArtifacts() {
    try {
      const arts = await listAll(`/v1/jobs/${enc(id)}/artifacts`);
      if (!alive) return;
      artTotal.textContent = arts.length ? `(${arts.length} files, ${fmtBytes(arts.reduce((n, a) => n + a.size, 0))})` : "";
      artNote.textContent = arts.length ? "" : job && !TERMINAL.has(job.state) ? "Listed when the job ends." : "None.";
      artNote.hidden = !!arts.length;
      artTable.hidden = !arts.length;
      artBody.replaceChildren(...arts.map((a) => h("tr", { dataset: { name: a.name } },
        h("td", null, a.name), h("td", { class: "num" }, fmtBytes(a.size)), h("td", null, downloadButton(id, a)))));
      meshArtifacts.set(id, arts);
      meshView.hidden = !arts.some((a) => a.name === "asset.glb");
      meshView.href = `/viewer/${enc(id)}/mesh#key=${enc(auth.key)}`;
      await showPreview(id, arts.find((a) => a.name === "mesh_preview.png"));
    } catch (e) {
      showError(e, "Cannot list the artifacts");
    }
  }

  async function meshFiles(m) {
    if (!meshArtifacts.has(m.id)) meshArtifacts.set(m.id, await listAll(`/v1/jobs/${enc(m.id)}/artifacts`));
    return meshArtifacts.get(m.id);
  }

  async function loadMeshes() {
    clearTimeout(meshTimer);
    if (!job || job.kind === "mesh") return;
    try {
      const page = await getJson(`/v1/jobs/${enc(id)}/meshes?limit=50`);
      if (!alive) return;
      let active = false;
      const items = [];
      for (const m of page.items) {
        const c = m.config || {};
        const running = !TERMINAL.has(m.state);
        active = active || running;
        const st = m.stage;
        const text = m.state === "running" ? `${st ? st.step : "starting"} ${Math.round((m.progress || 0) * 100)} %` : m.state;
        const li = h("li", { dataset: { job: m.id, state: m.state } },
          h("div", { class: "line" }, h("span", null, `${c.resolution || 256}³ ${c.color || "base"}${c.asset ? " + asset" : ""}`),
            pill(h("span"), m.state, text)));
        const links = h("div", { class: "row wrap" });
        if (m.state === "succeeded") {
          const arts = await meshFiles(m);
          for (const name of ["mesh.glb", "mesh.ply", "mesh.obj"]) {
            const a = arts.find((x) => x.name === name);
            if (a) links.append(downloadButton(m.id, a, `${name.slice(5).toUpperCase()} ${fmtBytes(a.size)}`));
          }
          if (arts.some((x) => x.name === "asset.glb")) {
            links.append(h("a", { class: "button small", target: "_blank", rel: "noopener", dataset: { asset: m.id },
              href: `/viewer/${enc(m.id)}/mesh#key=${enc(auth.key)}` }, "Asset view ↗"));
          }
          const pv = arts.find((x) => x.name === "mesh_preview.png");
          if (pv) {
            const b = h("button", { type: "button", class: "small" }, "Preview");
            b.addEventListener("click", () => showPreview(m.id, pv));
            links.append(b);
          }
        } else if (running) {
          const b = h("button", { type: "button", class: "small" }, "Cancel");
          b.addEventListener("click", () => api(`/v1/jobs/${enc(m.id)}/cancel`, { method: "POST" }).then(loadMeshes, (e) => showError(e)));
          links.append(b);
        } else if (m.error) {
          links.append(h("span", { class: "muted small" }, m.error));
        }
        li.append(links);
        items.push(li);
      }
      meshList.replaceChildren(...items);
      if (active) meshTimer = setTimeout(loadMeshes, 1500);
    } catch (e) {
      console.warn("meshes:", e);
    }
  }

  meshForm.addEventListener("submit", async (e) => {
    e.preventDefault();
    problemBox(meshError, null);
    meshStart.disabled = true;
    try {
      const body = { resolution: Number(meshRes.value), color: meshColor.value, ...(meshAsset.checked ? { asset: {} } : {}) };
      await getJson(`/v1/jobs/${enc(id)}/meshes`, { method: "POST", json: body });
      announce("Mesh extraction queued");
      loadMeshes();
    } catch (err) {
      problemBox(meshError, err, "Cannot extract:");
    } finally {
      meshStart.disabled = !job || job.state !== "succeeded";
    }
  });

  cancelBtn.addEventListener("click", async () => {
    try {
      update(await getJson(`/v1/jobs/${enc(id)}/cancel`, { method: "POST" }));
      announce("Cancel requested");
    } catch (e) { showError(e, "Cannot cancel"); }
  });
  resumeBtn.addEventListener("click", async () => {
    try {
      update(await getJson(`/v1/jobs/${enc(id)}/resume`, { method: "POST" }));
      announce("Job resumed");
      follow();
    } catch (e) { showError(e, "Cannot resume"); }
  });
  deleteBtn.addEventListener("click", async () => {
    if (!(await confirmDialog(`Delete job ${id} with its run folder, artifacts and meshes?`))) return;
    try {
      await api(`/v1/jobs/${enc(id)}`, { method: "DELETE" });
      announce(`Job ${id} deleted`);
      location.hash = job ? `#/scenes/${job.scene_id}` : "#/";
      refreshLists();
    } catch (e) { showError(e, "Cannot delete the job"); }
  });

  async function follow() {
    if (following || !alive) return;
    following = true;
    try {
      await followEvents(`/v1/jobs/${enc(id)}/events`, (name, data) => {
        if (name === "job" && alive) update(JSON.parse(data));
      }, ctrl.signal);
    } catch (e) {
      if (alive && !(e instanceof ApiError && e.status === 404)) showError(e, "Live updates stopped");
    } finally {
      following = false;
    }
    if (!alive) return;
    try { update(await getJson(`/v1/jobs/${enc(id)}`)); } catch (e) { /* deleted meanwhile */ }
  }

  (async () => {
    try {
      update(await getJson(`/v1/jobs/${enc(id)}`));
      if (!TERMINAL.has(job.state)) {
        artNote.textContent = "Listed when the job ends.";
        follow();
      }
    } catch (e) {
      if (e instanceof ApiError && e.status === 404) {
        el.replaceChildren(h("h1", { tabindex: -1 }, "Job not found"),
          h("p", null, `No job ${id} for this key (deleted, or another owner's).`));
      } else showError(e, "Cannot load the job");
    }
  })();

  return {
    el,
    destroy() {
      alive = false;
      ctrl.abort();
      clearTimeout(meshTimer);
      resize.disconnect();
      if (previewUrl) URL.revokeObjectURL(previewUrl);
    },
  };
}

// ---- start ----------------------------------------------------------------------------------

$("#new-scene").addEventListener("submit", async (e) => {
  e.preventDefault();
  const input = $("#new-scene-name");
  try {
    const scene = await createScene(input.value.trim());
    input.value = "";
    announce(`Scene ${scene.name} created`);
    await refreshLists();
    location.hash = `#/scenes/${scene.id}`;
  } catch (err) {
    showError(err, "Cannot create the scene");
  }
});

(function boot() {
  // #key=glk_... (as the viewer takes it): kept, then removed from the address bar at once
  const frag = new URLSearchParams(location.hash.slice(1));
  if (frag.get("key")) {
    localStorage.setItem(KEY_STORE, frag.get("key"));
    history.replaceState(null, "", `${location.pathname}#/`);
  }
  const key = localStorage.getItem(KEY_STORE);
  if (key) signIn(key);
  else showLogin();
})();
