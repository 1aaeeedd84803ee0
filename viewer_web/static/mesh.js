// Glint mesh view: a job's relightable asset (asset.glb) lit by its environment
// (asset_env.hdr) with three.js, rendered in the browser. No build step: an ES module;
// three.js is vendored under /viewer/static/vendor/three (the page's import map).
//
// The files come from the public artifacts API with the API key of this tab (in the
// Authorization header, never in a URL), like the live viewer's mesh downloads.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { HDRLoader } from "three/addons/loaders/HDRLoader.js";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

const $ = (id) => document.getElementById(id);
const parts = location.pathname.split("/").filter(Boolean); // viewer, {job}, mesh
const jobId = decodeURIComponent(parts[1] || "");
const enc = encodeURIComponent;
const KEY_STORE = "glint-api-key"; // the live viewer's: one key per tab
const BACKGROUND = 0x202124;
const ASSET = { glb: "asset.glb", json: "asset.json", hdr: "asset_env.hdr" };
const ASSET_FILES = ["asset.glb", "asset.json", "asset_env.hdr", "asset_env.exr", "asset_preview.png"];

const state = { state: "loading", vertices: 0, faces: 0, job: null, info: null, hasEnv: false, renders: 0 };
window.glintMeshView = state; // for debugging and browser tests

// ---- status --------------------------------------------------------------------------
function setStatus(kind, text) {
  state.state = kind;
  const el = $("mesh-status");
  el.dataset.state = kind;
  el.textContent = text;
  const overlay = $("overlay");
  overlay.hidden = kind === "loaded";
  if (kind !== "loaded") overlay.textContent = text;
}
function showJob(job) {
  $("job-id").textContent = job.id;
  const pill = $("job-state");
  pill.textContent = job.state;
  pill.className = `pill ${job.state}`;
  const st = job.stage;
  const count = st && st.total ? ` ${st.done}/${st.total}` : "";
  $("job-phase").textContent = job.state === "running" && st
    ? `${st.name}: ${st.step}${count} · ${Math.round((job.progress || 0) * 100)} %` : "";
}

// ---- API (Bearer key) ----------------------------------------------------------------
function takeFragment() {
  // #key=glk_... is kept in sessionStorage (this tab), then removed from the address bar
  const frag = new URLSearchParams(location.hash.slice(1));
  if (frag.get("key")) sessionStorage.setItem(KEY_STORE, frag.get("key"));
  if (frag.has("key") || frag.has("token")) history.replaceState(null, "", location.pathname);
  return frag.has("token") && !sessionStorage.getItem(KEY_STORE);
}
function askKey(note) {
  return new Promise((resolve) => {
    if (note) $("login-error").textContent = note;
    $("login-form").onsubmit = () => resolve($("login-key").value.trim());
    $("login").showModal();
  });
}
class ApiError extends Error {
  constructor(status, problem) {
    const field = problem.errors && problem.errors[0] && problem.errors[0].field ? ` (${problem.errors[0].field})` : "";
    super((problem.detail || `HTTP ${status}`) + field);
    this.status = status;
  }
}
async function api(path, opts = {}) {
  for (;;) {
    let key = sessionStorage.getItem(KEY_STORE);
    if (!key) { key = await askKey(); sessionStorage.setItem(KEY_STORE, key); }
    const r = await fetch(path, { ...opts, headers: { ...(opts.headers || {}), Authorization: `Bearer ${key}` } });
    if (r.status === 401) { // a wrong or revoked key: ask again
      const p = await r.json().catch(() => ({}));
      sessionStorage.removeItem(KEY_STORE);
      $("login-error").textContent = p.detail || "this key is not valid";
      continue;
    }
    if (!r.ok) throw new ApiError(r.status, await r.json().catch(() => ({})));
    return r;
  }
}
async function listAll(path) {
  const items = [];
  for (let offset = 0; ; ) {
    const page = await (await api(`${path}?limit=200&offset=${offset}`)).json();
    items.push(...page.items);
    offset += page.limit;
    if (!page.items.length || offset >= page.total) return items;
  }
}

// ---- three.js scene ------------------------------------------------------------------
const canvas = $("view");
const stage = $("stage");
let renderer = null;
try {
  renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
} catch (e) {
  console.error(e);
}
const scene = new THREE.Scene();
scene.background = new THREE.Color(BACKGROUND);
const camera = new THREE.PerspectiveCamera(40, 1, 0.01, 100);
let controls = null;
let envEquirect = null; // the HDR as loaded (the background when asked)
let home = null;
let pending = false; // a render is asked for the next animation frame

if (renderer) {
  // Glint's renders are linear radiance written as sRGB: no tone mapping by default.
  // LinearToneMapping at 0 EV is exactly that, and lets the exposure slider act.
  renderer.outputColorSpace = THREE.SRGBColorSpace;
  renderer.toneMapping = THREE.LinearToneMapping;
  renderer.toneMappingExposure = 1;
  renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
  controls = new OrbitControls(camera, canvas);
  controls.addEventListener("change", requestRender);
  new ResizeObserver(resize).observe(stage);
  resize();
}

function requestRender() {
  if (pending || !renderer) return;
  pending = true;
  requestAnimationFrame(() => { pending = false; render(); });
}
function render() {
  renderer.render(scene, camera);
  state.renders += 1;
}
state.render = () => { if (renderer) render(); };
function resize() {
  const w = Math.max(stage.clientWidth, 16), h = Math.max(stage.clientHeight, 16);
  renderer.setSize(w, h, false);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
  requestRender();
}

function frame(object) {
  // camera on the bounding sphere's outside, a little above; near/far from its size
  const box = new THREE.Box3().setFromObject(object);
  const sphere = box.getBoundingSphere(new THREE.Sphere());
  const r = Math.max(sphere.radius, 1e-6);
  const dist = (r / Math.sin(THREE.MathUtils.degToRad(camera.fov) / 2)) * 1.15;
  const dir = new THREE.Vector3(0.55, 0.45, 1).normalize();
  camera.position.copy(sphere.center).addScaledVector(dir, dist);
  camera.near = dist / 100;
  camera.far = dist * 100;
  camera.updateProjectionMatrix();
  controls.target.copy(sphere.center);
  controls.update();
  home = { position: camera.position.clone(), target: sphere.center.clone() };
}
$("reset").addEventListener("click", () => {
  if (!home || !controls) return;
  camera.position.copy(home.position);
  controls.target.copy(home.target);
  controls.update();
});

function applyLighting() {
  if (!renderer) return;
  const ev = Number($("exposure").value);
  $("exposure-value").textContent = `${ev >= 0 ? "+" : ""}${ev.toFixed(1)} EV`;
  renderer.toneMappingExposure = 2 ** ev;
  renderer.toneMapping = $("tone-mapping").value === "aces" ? THREE.ACESFilmicToneMapping : THREE.LinearToneMapping;
  scene.background = $("env-bg").checked && envEquirect ? envEquirect : new THREE.Color(BACKGROUND);
  requestRender();
}
for (const id of ["exposure", "tone-mapping", "env-bg"]) $(id).addEventListener("input", applyLighting);

function hdrTexture(buffer) {
  // HDRLoader.parse + what DataTextureLoader.load would set, without a blob URL
  const d = new HDRLoader().setDataType(THREE.HalfFloatType).parse(buffer);
  const tex = new THREE.DataTexture(d.data, d.width, d.height, THREE.RGBAFormat, d.type);
  tex.colorSpace = THREE.LinearSRGBColorSpace;
  tex.minFilter = tex.magFilter = THREE.LinearFilter;
  tex.generateMipmaps = false;
  tex.flipY = true;
  tex.mapping = THREE.EquirectangularReflectionMapping;
  tex.needsUpdate = true;
  return tex;
}
function uniformEnvironment() {
  // a diffuse scene has no env map: a uniform white one (radiance 1) shows the baked
  // base colour as it is, the way Glint shades a surface with no reflection
  const one = THREE.DataUtils.toHalfFloat(1);
  const tex = new THREE.DataTexture(new Uint16Array(4 * 2).fill(one), 2, 1, THREE.RGBAFormat, THREE.HalfFloatType);
  tex.mapping = THREE.EquirectangularReflectionMapping;
  tex.colorSpace = THREE.LinearSRGBColorSpace;
  tex.needsUpdate = true;
  return tex;
}
function setEnvironment(equirect, rotationY) {
  const pmrem = new THREE.PMREMGenerator(renderer);
  scene.environment = pmrem.fromEquirectangular(equirect).texture;
  pmrem.dispose();
  scene.environmentRotation.y = rotationY;
  scene.backgroundRotation.y = rotationY;
}
function parseGlb(buffer) {
  return new Promise((resolve, reject) => new GLTFLoader().parse(buffer, "", resolve, reject));
}
function countGeometry(root) {
  let vertices = 0, faces = 0, meshes = 0;
  root.traverse((o) => {
    if (!o.isMesh) return;
    const g = o.geometry;
    const n = g.attributes.position ? g.attributes.position.count : 0;
    meshes += 1;
    vertices += n;
    faces += Math.floor((g.index ? g.index.count : n) / 3);
  });
  return { vertices, faces, meshes };
}

// ---- the job's asset -----------------------------------------------------------------
function fileLinks(artifacts) {
  const box = $("asset-files");
  box.replaceChildren();
  for (const a of artifacts.filter((x) => ASSET_FILES.includes(x.name))) {
    const li = document.createElement("li");
    const link = document.createElement("a");
    link.href = "#"; link.textContent = a.name; link.dataset.file = a.name;
    link.title = `download ${a.name} (${a.size.toLocaleString()} bytes)`;
    link.addEventListener("click", async (ev) => {
      ev.preventDefault();
      const url = URL.createObjectURL(await (await api(a.url)).blob());
      const tmp = document.createElement("a");
      tmp.href = url; tmp.download = `${jobId}_${a.name}`;
      document.body.appendChild(tmp); tmp.click(); tmp.remove();
      setTimeout(() => URL.revokeObjectURL(url), 30000);
    });
    li.appendChild(link);
    box.appendChild(li);
  }
}

async function showMissing(job) {
  // no asset.glb: say so, and how to make one (the mesh endpoint's `asset` field)
  // the state turns "missing" once the box is complete (links to mesh jobs included),
  // so whoever waits on the state reads the whole box
  const train = job.kind === "mesh" ? job.parent_id : job.id;
  const box = $("missing");
  box.replaceChildren();
  const p = (text) => { const el = document.createElement("p"); el.textContent = text; box.appendChild(el); return el; };
  p(`Make one with a mesh job that also bakes the asset: POST /v1/jobs/${train}/meshes with `
    + `{"asset": {}} (fields: faces, texture_size, views, occlusion), or train with `
    + `"outputs": {"asset": true}.`);
  try {
    if (job.kind === "train" && job.state === "succeeded") await offerAssetJobs(train, box, p);
  } finally {
    box.hidden = false;
    setStatus("missing", `Job ${job.id} has no relightable asset (asset.glb).`);
  }
}

async function offerAssetJobs(train, box, p) {
  // the training job's mesh jobs that bake an asset, and a button to start one
  const others = (await api(`/v1/jobs/${enc(train)}/meshes?limit=50`).then((r) => r.json())).items
    .filter((m) => m.config && m.config.asset && m.state !== "failed" && m.state !== "cancelled");
  for (const m of others) {
    const a = document.createElement("a");
    a.href = `/viewer/${enc(m.id)}/mesh`; a.dataset.job = m.id;
    a.textContent = `asset of mesh job ${m.id} (${m.state}) ↗`;
    box.appendChild(a);
  }
  const btn = document.createElement("button");
  btn.type = "button"; btn.id = "make-asset"; btn.textContent = "Bake an asset (mesh job)";
  btn.addEventListener("click", async () => {
    btn.disabled = true;
    try {
      const r = await api(`/v1/jobs/${enc(train)}/meshes`, {
        method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ asset: {} }),
      });
      location.assign(`/viewer/${enc((await r.json()).id)}/mesh`);
    } catch (e) { p(`Cannot start it: ${e.message}`); btn.disabled = false; }
  });
  box.appendChild(btn);
}

async function loadAsset(artifacts) {
  const byName = new Map(artifacts.map((a) => [a.name, a]));
  const bytes = async (name) => (await api(byName.get(name).url)).arrayBuffer();
  setStatus("loading", "Downloading the asset…");
  const [glb, info, hdr] = await Promise.all([
    bytes(ASSET.glb),
    byName.has(ASSET.json) ? api(byName.get(ASSET.json).url).then((r) => r.json()) : {},
    byName.has(ASSET.hdr) ? bytes(ASSET.hdr) : null,
  ]);
  state.info = info;
  setStatus("loading", "Decoding the asset…");
  const gltf = await parseGlb(glb);
  const env = info.environment || {};
  const rotation = Number(env.three_rotation_y) || 0;
  if (hdr) {
    envEquirect = hdrTexture(hdr);
    setEnvironment(envEquirect, rotation);
    state.hasEnv = true;
    $("env-note").textContent = `lit by asset_env.hdr (${envEquirect.image.width}×${envEquirect.image.height}, through PMREM)`;
  } else {
    setEnvironment(uniformEnvironment(), 0);
    $("env-bg").disabled = true;
    $("env-note").textContent = "no environment map in this asset (a diffuse scene): lit by a uniform white environment";
  }
  scene.add(gltf.scene);
  frame(gltf.scene);
  const n = countGeometry(gltf.scene);
  Object.assign(state, { vertices: n.vertices, faces: n.faces, gltf });
  const el = $("mesh-status");
  el.dataset.vertices = String(n.vertices);
  el.dataset.faces = String(n.faces);
  applyLighting();
  render();
  setStatus("loaded", `${n.vertices.toLocaleString()} vertices · ${n.faces.toLocaleString()} faces`);
}

let waitTimer = null;
async function main() {
  $("job-id").textContent = jobId;
  $("live-link").href = `/viewer/${enc(jobId)}`;
  if (takeFragment()) $("login-error").textContent = "a viewer token does not open the artifacts API: paste an API key";
  if (!renderer) { setStatus("error", "WebGL is not available in this browser: the mesh view needs it."); return; }
  let job;
  try {
    job = await (await api(`/v1/jobs/${enc(jobId)}`)).json();
  } catch (e) {
    setStatus("error", e.status === 404 ? `Job ${jobId} not found (or not this key's).` : `Cannot read the job: ${e.message}`);
    return;
  }
  state.job = job;
  showJob(job);
  if (job.kind === "mesh") $("live-link").href = `/viewer/${enc(job.parent_id)}`;
  if (job.state === "queued" || job.state === "running") { // its files come at its end
    setStatus("waiting", `Job ${job.id} is ${job.state}; the asset is listed when it ends.`);
    waitTimer = setTimeout(main, 1500);
    return;
  }
  const artifacts = await listAll(`/v1/jobs/${enc(jobId)}/artifacts`);
  fileLinks(artifacts);
  if (!artifacts.some((a) => a.name === ASSET.glb)) {
    await showMissing(job);
    if (job.state === "failed" && job.error) $("missing").prepend(Object.assign(document.createElement("p"), { className: "error", textContent: job.error }));
    return;
  }
  await loadAsset(artifacts);
}

main().catch((e) => { clearTimeout(waitTimer); console.error(e); setStatus("error", `Cannot show the asset: ${e.message || e}`); });
