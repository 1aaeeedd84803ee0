// Glint viewer client: camera controls, the frame stream, job status, env map.
// No build step: plain ES2020 in one file. The protocol is in docs/viewer.md.
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);
  const jobId = decodeURIComponent(location.pathname.split("/").filter(Boolean).pop() || "");
  const KEY_STORE = "glint-api-key";

  // ---- small vector helpers (arrays of 3 numbers) ---------------------------------
  const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const mul = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const norm = (a) => { const n = Math.hypot(...a) || 1; return mul(a, 1 / n); };

  // ---- state -------------------------------------------------------------------
  const state = {
    token: null, ws: null, seq: 0, channel: "final", channels: [],
    up: [0, 0, 1], home: null,             // world up and the reset pose
    target: [0, 0, 0], dist: 4, yaw: 0, pitch: 0.3, fovY: 40,
    exact: null,                           // {w2c, fov_y} of a training camera until the user moves
    dirty: true, lastChange: 0, stillSent: false, keys: new Set(),
    sentAt: new Map(), frames: 0, frameTimes: [], lastHeader: null, model: null,
    cameras: [], reconnects: 0,
  };
  window.glintViewer = state; // for debugging and browser tests

  const canvas = $("view");
  const ctx = canvas.getContext("2d");

  // ---- orbit camera ---------------------------------------------------------------
  // Basis around the world up: e1, e2 span the horizontal plane, yaw turns in it,
  // pitch lifts toward up. The eye sits on a sphere of radius dist around target.
  function basis() {
    const u = norm(state.up);
    const ref = Math.abs(u[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
    const e1 = norm(sub(ref, mul(u, dot(ref, u))));
    return [e1, cross(u, e1), u];
  }
  function eye() {
    const [e1, e2, u] = basis();
    const c = Math.cos(state.pitch);
    const dir = add(add(mul(e1, c * Math.cos(state.yaw)), mul(e2, c * Math.sin(state.yaw))), mul(u, Math.sin(state.pitch)));
    return add(state.target, mul(dir, state.dist));
  }
  function setEye(e) { // keep target, aim from e
    const [e1, e2, u] = basis();
    const d = sub(e, state.target);
    state.dist = Math.max(Math.hypot(...d), 1e-6);
    const n = mul(d, 1 / state.dist);
    state.pitch = Math.asin(Math.max(-1, Math.min(1, dot(n, u))));
    state.yaw = Math.atan2(dot(n, e2), dot(n, e1));
  }
  function changed() { state.dirty = true; state.exact = null; state.lastChange = performance.now(); state.stillSent = false; }

  function orbit(dx, dy) {
    state.yaw -= dx * 0.008;
    state.pitch = Math.max(-1.55, Math.min(1.55, state.pitch + dy * 0.008));
    changed();
  }
  function pan(dx, dy) {
    const e = eye();
    const f = norm(sub(state.target, e));
    const r = norm(cross(f, state.up));
    const u = cross(r, f);
    const k = state.dist * Math.tan((state.fovY * Math.PI) / 360) * 2 / Math.max(canvas.clientHeight, 1);
    state.target = add(state.target, add(mul(r, -dx * k), mul(u, dy * k)));
    changed();
  }
  function zoom(factor) { state.dist = Math.max(1e-4, state.dist * factor); changed(); }
  function fly(dt) { // WASD moves eye and target together; QE down/up
    const e = eye();
    const f = norm(sub(state.target, e));
    const r = norm(cross(f, state.up));
    let m = [0, 0, 0];
    const k = state.keys;
    if (k.has("w")) m = add(m, f);
    if (k.has("s")) m = sub(m, f);
    if (k.has("d")) m = add(m, r);
    if (k.has("a")) m = sub(m, r);
    if (k.has("e")) m = add(m, norm(state.up));
    if (k.has("q")) m = sub(m, norm(state.up));
    if (dot(m, m) === 0) return;
    const speed = (state.model ? state.model.radius : 1) * 0.8 * dt;
    state.target = add(state.target, mul(norm(m), speed));
    changed();
  }

  function resetView() {
    if (state.home) Object.assign(state, structuredClone(state.home));
    changed();
    if (state.home && state.home.exact) state.exact = state.home.exact;
  }

  // A training camera: eye = its centre, target along its optical axis, exact pose kept
  // (roll included) until the user moves.
  function jumpTo(cam) {
    const w = cam.w2c; // row-major 4x4, OpenCV axes
    const R = [[w[0], w[1], w[2]], [w[4], w[5], w[6]], [w[8], w[9], w[10]]];
    const t = [w[3], w[7], w[11]];
    const c = mul([R[0][0] * t[0] + R[1][0] * t[1] + R[2][0] * t[2], R[0][1] * t[0] + R[1][1] * t[1] + R[2][1] * t[2], R[0][2] * t[0] + R[1][2] * t[1] + R[2][2] * t[2]], -1);
    const fwd = R[2];
    const center = state.model ? state.model.center : [0, 0, 0];
    const d = Math.max(dot(sub(center, c), fwd), 1e-3);
    state.target = add(c, mul(fwd, d));
    setEye(c);
    state.fovY = cam.fov_y;
    changed();
    state.exact = { w2c: w, fov_y: cam.fov_y };
  }

  // ---- input ------------------------------------------------------------------------
  const stage = $("stage");
  const pointers = new Map();
  let pinch = null;
  stage.addEventListener("contextmenu", (e) => e.preventDefault());
  stage.addEventListener("pointerdown", (e) => {
    stage.focus();
    stage.setPointerCapture(e.pointerId);
    pointers.set(e.pointerId, { x: e.clientX, y: e.clientY, button: e.button, shift: e.shiftKey });
    pinch = null;
  });
  stage.addEventListener("pointermove", (e) => {
    const p = pointers.get(e.pointerId);
    if (!p) return;
    const dx = e.clientX - p.x, dy = e.clientY - p.y;
    p.x = e.clientX; p.y = e.clientY;
    if (pointers.size === 2) { // two fingers: pinch zoom + pan by the midpoint
      const [a, b] = [...pointers.values()];
      const span = Math.hypot(a.x - b.x, a.y - b.y);
      const mid = [(a.x + b.x) / 2, (a.y + b.y) / 2];
      if (pinch) { zoom(pinch.span / Math.max(span, 1)); pan(mid[0] - pinch.mid[0], mid[1] - pinch.mid[1]); }
      pinch = { span, mid };
    } else if (p.button === 2 || p.button === 1 || p.shift) {
      pan(dx, dy);
    } else {
      orbit(dx, dy);
    }
  });
  const up = (e) => { pointers.delete(e.pointerId); pinch = null; };
  stage.addEventListener("pointerup", up);
  stage.addEventListener("pointercancel", up);
  stage.addEventListener("wheel", (e) => { e.preventDefault(); zoom(Math.exp(e.deltaY * 0.001)); }, { passive: false });
  window.addEventListener("keydown", (e) => {
    if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
    const k = e.key.toLowerCase();
    if ("wasdqe".includes(k) && k.length === 1) state.keys.add(k);
    if (k === "r") resetView();
  });
  window.addEventListener("keyup", (e) => state.keys.delete(e.key.toLowerCase()));
  window.addEventListener("blur", () => state.keys.clear());
  $("reset").addEventListener("click", resetView);
  $("max-res").addEventListener("change", () => changed());
  $("cameras").addEventListener("change", (e) => {
    const cam = state.cameras[Number(e.target.value)];
    if (cam) jumpTo(cam);
  });

  // ---- sending cameras ---------------------------------------------------------------
  // One message per animation frame at most, only when something changed; once the
  // camera has rested for 150 ms a 'still' message asks for full resolution.
  function viewSize() {
    const scale = Number($("max-res").value) * Math.min(window.devicePixelRatio || 1, 2);
    return [Math.max(16, Math.round(stage.clientWidth * scale)), Math.max(16, Math.round(stage.clientHeight * scale))];
  }
  function sendCamera(still) {
    const ws = state.ws;
    if (!ws || ws.readyState !== WebSocket.OPEN || !state.model) return;
    const [width, height] = viewSize();
    const msg = { type: "camera", seq: ++state.seq, width, height, channel: state.channel, still };
    if (state.exact) { msg.w2c = state.exact.w2c; msg.fov_y = state.exact.fov_y; }
    else { msg.eye = eye(); msg.target = state.target; msg.up = state.up; msg.fov_y = state.fovY; }
    state.sentAt.set(msg.seq, performance.now());
    if (state.sentAt.size > 200) state.sentAt.delete(state.sentAt.keys().next().value);
    ws.send(JSON.stringify(msg));
  }
  let lastTick = performance.now();
  function tick(now) {
    fly(Math.min((now - lastTick) / 1000, 0.1));
    lastTick = now;
    if (state.dirty) { state.dirty = false; sendCamera(false); }
    else if (!state.stillSent && now - state.lastChange > 150) { state.stillSent = true; sendCamera(true); }
    requestAnimationFrame(tick);
  }
  requestAnimationFrame(tick);
  new ResizeObserver(() => changed()).observe(stage);

  // ---- receiving -----------------------------------------------------------------------
  async function onFrame(buf) {
    const view = new DataView(buf);
    const n = view.getUint32(0, false);
    const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
    const bitmap = await createImageBitmap(new Blob([new Uint8Array(buf, 4 + n)], { type: "image/jpeg" }));
    // The canvas keeps the full size; reduced frames are scaled up (smoothly) to fill it.
    if (canvas.width !== header.full_width || canvas.height !== header.full_height) {
      canvas.width = header.full_width; canvas.height = header.full_height;
    }
    ctx.imageSmoothingEnabled = true;
    ctx.drawImage(bitmap, 0, 0, canvas.width, canvas.height);
    bitmap.close();
    state.frames += 1;
    state.lastHeader = header;
    $("overlay").hidden = true;
    const now = performance.now();
    state.frameTimes.push(now);
    while (state.frameTimes.length && now - state.frameTimes[0] > 1000) state.frameTimes.shift();
    const sent = state.sentAt.get(header.seq);
    $("hud-ms").textContent = `${header.render_ms.toFixed(0)} ms`;
    $("hud-res").textContent = `${header.width}×${header.height}${header.full ? "" : ` (${Math.round(header.scale * 100)} %)`}`;
    $("hud-fps").textContent = `${state.frameTimes.length} fps`;
    $("st-render").textContent = `${header.render_ms.toFixed(1)} ms`;
    $("st-encode").textContent = `${header.encode_ms.toFixed(1)} ms`;
    $("st-latency").textContent = sent ? `${(now - sent).toFixed(0)} ms` : "—";
    $("st-res").textContent = `${header.width}×${header.height} / ${header.full_width}×${header.full_height}`;
  }

  function onModel(model, first) {
    const hadModel = !!state.model;
    state.model = model;
    $("st-model").textContent = `${model.n_gaussians.toLocaleString()} G · it ${model.iteration}`;
    $("st-device").textContent = model.backend ? `${model.device} · ${model.backend}` : model.device;
    refreshEnvmap(model);
    if (first || !hadModel) { // frame the model until training cameras arrive
      state.target = model.center.slice();
      state.dist = model.radius * 3.2;
      state.home = { target: state.target.slice(), dist: state.dist, yaw: state.yaw, pitch: state.pitch, fovY: state.fovY, exact: null };
      changed();
    } else {
      state.stillSent = false; // a newer checkpoint: the server re-renders by itself
    }
  }

  function refreshEnvmap(model) {
    const img = $("envmap"), note = $("envmap-note");
    if (!model.envmap) { img.hidden = true; note.textContent = "no environment map (not used yet, or the scene is diffuse)"; return; }
    const url = `/v1/jobs/${encodeURIComponent(jobId)}/viewer/envmap.png?token=${encodeURIComponent(state.token)}&it=${model.iteration}`;
    img.onload = () => { img.hidden = false; note.textContent = `lat-long · iteration ${model.iteration}`; };
    img.onerror = () => { img.hidden = true; note.textContent = "environment map unavailable"; };
    img.src = url;
  }

  function onCameras(cams) {
    state.cameras = cams;
    const sel = $("cameras");
    sel.length = 1;
    cams.forEach((c, i) => sel.add(new Option(`${c.split} · ${c.name}`, String(i))));
    if (!cams.length) return;
    // World up = the mean of the cameras' up vectors (−y of OpenCV cameras).
    let u = [0, 0, 0];
    for (const c of cams) u = add(u, [-c.w2c[4], -c.w2c[5], -c.w2c[6]]);
    if (Math.hypot(...u) > 1e-6) state.up = norm(u);
    const first = cams.find((c) => c.split === "train") || cams[0];
    jumpTo(first);
    state.home = { target: state.target.slice(), dist: state.dist, yaw: state.yaw, pitch: state.pitch, fovY: state.fovY, exact: state.exact };
  }

  function onJob(job) {
    $("job-id").textContent = job.id;
    const pill = $("job-state");
    pill.textContent = job.state;
    pill.className = `pill ${job.state}`;
    const st = job.stage;  // e.g. mesh: integrate 3/24, sfm: matching 40/66
    const count = st && st.total ? ` ${st.done}/${st.total}` : "";
    const stage = st && job.state === "running" ? ` · ${st.name}: ${st.step}${count}` : "";
    $("job-phase").textContent = job.phase ? `phase: ${job.phase}${stage}` : "";
    if (job.state === "succeeded" && state.lastJobState !== "succeeded" && sessionStorage.getItem(KEY_STORE)) {
      setTimeout(() => state.refreshMeshes && state.refreshMeshes(), 0);
    }
    state.lastJobState = job.state;
    $("job-progress").style.width = `${Math.round((job.progress || 0) * 100)}%`;
    $("job-iter").textContent = `${job.iteration} / ${job.total_iterations}`;
    $("job-psnr").textContent = qualityText(job);
  }

  // The latest held-out figures: image error, then geometry error (or consistency
  // when the scene has no ground truth), then what is left of a time budget.
  function qualityText(job) {
    const m = job.metrics || {};
    const parts = [];
    if (m.psnr != null) parts.push(`PSNR ${m.psnr.toFixed(2)} dB`);
    if (m.normal_error_deg != null) parts.push(`normal err ${m.normal_error_deg.toFixed(1)}°`);
    if (m.cd_x100 != null) state.lastCd = m.cd_x100; // probed at a few points of the run
    if (state.lastCd != null) parts.push(`CD×10² ${state.lastCd.toFixed(3)}`);
    if (m.depth_normal_consistency_deg != null) parts.push(`depth–normal ${m.depth_normal_consistency_deg.toFixed(1)}°`);
    if (job.time_left_s != null && job.state === "running") {
      const s = Math.round(job.time_left_s);
      parts.push(`${Math.floor(s / 60)}m${String(s % 60).padStart(2, "0")}s left`);
    }
    return parts.join(" · ");
  }

  function onMessage(ev) {
    if (ev.data instanceof ArrayBuffer) { onFrame(ev.data).catch((e) => console.error(e)); return; }
    const msg = JSON.parse(ev.data);
    switch (msg.type) {
      case "hello":
        state.channels = msg.channels;
        buildChannels();
        onJob(msg.job);
        if (msg.model) onModel(msg.model, true);
        else $("overlay").textContent = "Waiting for the first checkpoint…";
        state.ws.send(JSON.stringify({ type: "cameras" }));
        break;
      case "model": onModel(msg, false); break;
      case "job": onJob(msg.job); break;
      case "cameras": onCameras(msg.cameras); break;
      case "waiting": $("overlay").hidden = false; $("overlay").textContent = msg.message; break;
      case "error": console.warn("viewer:", msg.message); break;
      default: break;
    }
  }

  function buildChannels() {
    const box = $("channels");
    box.textContent = "";
    const labels = { final: "Final", base: "Base colour", specular: "Specular", normal: "Normal", depth: "Depth", w_r: "Reflectance w_r", roughness: "Roughness", alpha: "Alpha" };
    for (const ch of state.channels) {
      const b = document.createElement("button");
      b.type = "button";
      b.dataset.channel = ch;
      b.setAttribute("role", "radio");
      b.setAttribute("aria-checked", String(ch === state.channel));
      b.textContent = labels[ch] || ch;
      b.addEventListener("click", () => {
        state.channel = ch;
        for (const o of box.children) o.setAttribute("aria-checked", String(o === b));
        state.dirty = true; state.stillSent = false; state.lastChange = performance.now();
      });
      box.appendChild(b);
    }
  }

  // ---- connection and auth -----------------------------------------------------------
  function showError(text) { const o = $("overlay"); o.hidden = false; o.textContent = text; const p = $("job-state"); p.textContent = "error"; p.className = "pill error"; }

  async function getToken() {
    // A token in the fragment (#token=gvt_...) is used as is; a key (#key=glk_...) is
    // kept in sessionStorage and exchanged. Either way the fragment is removed at once.
    const frag = new URLSearchParams(location.hash.slice(1));
    if (frag.has("token") || frag.has("key")) history.replaceState(null, "", location.pathname);
    if (frag.get("token")) return frag.get("token");
    if (frag.get("key")) sessionStorage.setItem(KEY_STORE, frag.get("key"));
    let key = sessionStorage.getItem(KEY_STORE);
    for (;;) {
      if (!key) key = await askKey();
      const r = await fetch(`/v1/jobs/${encodeURIComponent(jobId)}/viewer-token`, { method: "POST", headers: { Authorization: `Bearer ${key}` } });
      if (r.ok) { sessionStorage.setItem(KEY_STORE, key); return (await r.json()).token; }
      const problem = await r.json().catch(() => ({}));
      sessionStorage.removeItem(KEY_STORE);
      $("login-error").textContent = problem.detail || `HTTP ${r.status}`;
      key = null;
    }
  }
  function askKey() {
    return new Promise((resolve) => {
      const dlg = $("login");
      $("login-form").onsubmit = () => resolve($("login-key").value.trim());
      dlg.showModal();
    });
  }

  async function connect() {
    try { state.token = await getToken(); } catch (e) { showError(`Cannot get a viewer token: ${e}`); return; }
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    const ws = new WebSocket(`${proto}//${location.host}/v1/jobs/${encodeURIComponent(jobId)}/viewer/ws?token=${encodeURIComponent(state.token)}`);
    ws.binaryType = "arraybuffer";
    state.ws = ws;
    ws.onmessage = onMessage;
    ws.onclose = (ev) => {
      state.ws = null;
      if (ev.code === 4401 && state.reconnects < 5 && sessionStorage.getItem(KEY_STORE)) { // expired: new token
        state.reconnects += 1; connect(); return;
      }
      if (ev.code === 1013) { showError(`Server busy: ${ev.reason}. Retrying…`); setTimeout(connect, 3000); return; }
      showError(ev.reason ? `Disconnected: ${ev.reason}` : "Disconnected. Reload to reconnect.");
    };
  }
  // ---- meshes: the job's own, re-extractions, downloads (API key calls) -------------
  // The viewer token only grants viewing; listing and starting extractions use the
  // API key this tab was given (asked for when missing). Downloads go through fetch
  // so the key travels in the Authorization header, never in a URL.
  const MESH_FILES = ["mesh.glb", "mesh.ply", "mesh.obj"];
  async function api(path, opts = {}) {
    let key = sessionStorage.getItem(KEY_STORE);
    if (!key) { key = await askKey(); sessionStorage.setItem(KEY_STORE, key); }
    const r = await fetch(path, { ...opts, headers: { ...(opts.headers || {}), Authorization: `Bearer ${key}` } });
    if (!r.ok) {
      const p = await r.json().catch(() => ({}));
      const field = p.errors && p.errors[0] && p.errors[0].field ? ` (${p.errors[0].field})` : "";
      throw new Error((p.detail || `HTTP ${r.status}`) + field);
    }
    return r;
  }
  async function listAll(path) {
    // every item of a list endpoint: pages of {items, total, limit, offset}
    const items = [];
    for (let offset = 0; ; ) {
      const sep = path.includes("?") ? "&" : "?";
      const page = await (await api(`${path}${sep}limit=200&offset=${offset}`)).json();
      items.push(...page.items);
      offset += page.limit;
      if (!page.items.length || offset >= page.total) return items;
    }
  }
  function downloadLink(id, name) {
    const a = document.createElement("a");
    a.href = "#"; a.textContent = name.replace("mesh.", ""); a.dataset.file = name; a.title = `download ${name}`;
    a.addEventListener("click", async (ev) => {
      ev.preventDefault();
      try {
        const blob = await (await api(`/v1/jobs/${encodeURIComponent(id)}/artifacts/${name}`)).blob();
        const url = URL.createObjectURL(blob);
        const tmp = document.createElement("a");
        tmp.href = url; tmp.download = `${id}_${name}`;
        document.body.appendChild(tmp); tmp.click(); tmp.remove();
        setTimeout(() => URL.revokeObjectURL(url), 30000);
      } catch (e) { $("mesh-note").textContent = `Download failed: ${e.message}`; }
    });
    return a;
  }
  function meshItem(id, label, meta, done, asset) {
    const li = document.createElement("li");
    li.dataset.job = id; li.dataset.state = meta.state;
    const head = document.createElement("div");
    head.textContent = `${label} · ${meta.text}`;
    li.appendChild(head);
    if (done) {
      const links = document.createElement("div");
      links.className = "links";
      for (const f of MESH_FILES) links.appendChild(downloadLink(id, f));
      if (asset) { // the relightable asset, drawn in the browser (mesh.html)
        const a = document.createElement("a");
        a.href = `/viewer/${encodeURIComponent(id)}/mesh`; a.textContent = "asset view";
        a.dataset.asset = id; a.title = "asset.glb lit by its environment (three.js)";
        links.appendChild(a);
      }
      li.appendChild(links);
    }
    return li;
  }
  let meshTimer = null;
  async function refreshMeshes() {
    clearTimeout(meshTimer);
    const box = $("meshes");
    try {
      const own = await listAll(`/v1/jobs/${encodeURIComponent(jobId)}/artifacts`);
      const list = await (await api(`/v1/jobs/${encodeURIComponent(jobId)}/meshes?limit=20`)).json();
      box.replaceChildren();
      if (own.some((a) => a.name === "mesh.ply")) {
        const asset = own.some((a) => a.name === "asset.glb");
        box.appendChild(meshItem(jobId, "from training", { state: "succeeded", text: "done" }, true, asset));
      }
      let active = false;
      for (const m of list.items) {
        const c = m.config || {};
        const pct = Math.round((m.progress || 0) * 100);
        const text = m.state === "running" ? `${m.stage ? m.stage.step : "starting"} ${pct} %` : m.state;
        active = active || m.state === "queued" || m.state === "running";
        const label = `${c.resolution || 256}³ ${c.color || "base"}${c.asset ? " + asset" : ""}`;
        box.appendChild(meshItem(m.id, label, { state: m.state, text }, m.state === "succeeded", !!c.asset));
      }
      if (!box.children.length) $("mesh-note").textContent = "No mesh yet.";
      else if ($("mesh-note").textContent === "No mesh yet.") $("mesh-note").textContent = "";
      if (active) meshTimer = setTimeout(refreshMeshes, 1000);
    } catch (e) { $("mesh-note").textContent = `Meshes: ${e.message}`; }
  }
  $("mesh-start").addEventListener("click", async () => {
    $("mesh-note").textContent = "";
    try {
      await api(`/v1/jobs/${encodeURIComponent(jobId)}/meshes`, {
        method: "POST",
        headers: { "Content-Type": "application/json" },
        body: JSON.stringify({
          resolution: Number($("mesh-res").value), color: $("mesh-color").value,
          ...($("mesh-asset").checked ? { asset: {} } : {}),
        }),
      });
      refreshMeshes();
    } catch (e) { $("mesh-note").textContent = `Cannot extract: ${e.message}`; }
  });
  state.refreshMeshes = refreshMeshes;

  $("job-id").textContent = jobId;
  connect().then(() => { if (sessionStorage.getItem(KEY_STORE)) refreshMeshes(); });
})();
