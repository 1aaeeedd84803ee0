"""The dashboard (/app) in headless Chromium (Debian's), driven like a user would.

One flow from a dropped folder to a downloaded mesh, with the page reloaded in the middle
of the upload: the second selection of the same folder must send only the bytes the
server does not hold; then a second, long job is cancelled and deleted. Another test
makes a scene from the sidebar, drops a zip on it (an archive, one request) and deletes
the scene through the confirmation dialog; a third holds the page's SHA-256 to hashlib.
Every request the page makes must go to the server itself (no CDN, no font, no chart
library).
"""

from __future__ import annotations

import base64
import io
import json
import os
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.api.support import TINY_CONFIG, LiveServer, list_all, scene_files, wait_for

CHROMIUM = os.environ.get("GLINT_CHROMIUM", "/usr/bin/chromium")
# where to write the dashboard's screenshot for the docs (docs/dashboard.png), if anywhere
SCREENSHOT = os.environ.get("GLINT_DASHBOARD_SCREENSHOT")

pytestmark = pytest.mark.skipif(
    not Path(CHROMIUM).is_file(),
    reason=f"{CHROMIUM} is missing: run scripts/browser.sh to install Debian's chromium",
)

# 256-byte chunks: every file of the 24-px scene takes several PATCH requests; files above
# 1 KiB are hashed by the page's own incremental SHA-256 (the path big files take)
TUNING = {"chunkBytes": 256, "hashWholeMax": 1024}
PAUSE_AFTER = 14  # chunks sent before the page pauses and is reloaded

# how many colours the chart's canvas holds (a blank one: one or two)
CANVAS_COLOURS = """() => {
  const c = document.getElementById('chart');
  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  const seen = new Set();
  for (let i = 0; i < d.length; i += 4 * 13) seen.add((d[i] << 16) | (d[i + 1] << 8) | d[i + 2]);
  return seen.size;
}"""


class Recorder:
    """Every request the page makes; the PATCH chunks with their offsets and sizes."""

    def __init__(self) -> None:
        self.urls: list[str] = []
        self.chunks: list[tuple[str, int, int]] = []  # (upload id, Upload-Offset, bytes)

    def __call__(self, request) -> None:  # type: ignore[no-untyped-def]
        self.urls.append(request.url)
        if request.method == "PATCH" and "/uploads/" in request.url:
            body = request.post_data_buffer or b""
            offset = int(request.headers["upload-offset"])
            self.chunks.append((request.url.rsplit("/", 1)[-1], offset, len(body)))


@pytest.fixture(scope="module")
def owner(viewer_server: LiveServer) -> tuple[LiveServer, str]:
    return viewer_server, viewer_server.new_key("dashboard-owner")


@pytest.fixture(scope="module")
def page(owner: tuple[LiveServer, str]) -> Iterator:  # type: ignore[type-arg]
    from playwright.sync_api import sync_playwright

    srv, key = owner
    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=CHROMIUM,
            headless=True,
            args=["--no-sandbox", "--disable-gpu", "--disable-background-networking"],
        )
        pg = browser.new_page(viewport={"width": 1366, "height": 768}, accept_downloads=True)
        errors: list[str] = []
        pg.on("pageerror", lambda e: errors.append(str(e)))
        pg.recorder = Recorder()  # type: ignore[attr-defined]
        pg.on("request", pg.recorder)  # type: ignore[attr-defined]
        pg.goto(f"{srv.url}/app")
        # the key, pasted once (and kept: the reloads below do not ask again)
        pg.fill("#login-key", key)
        pg.press("#login-key", "Enter")
        pg.wait_for_function(
            "document.getElementById('who').textContent.startsWith('dashboard-owner')"
        )
        yield pg
        browser.close()
        assert not errors, f"page errors: {errors}"


def drop_folder(page, selector: str, folder: Path) -> None:  # type: ignore[no-untyped-def]
    """Drag a folder from disk onto an element, as a file manager does (DevTools protocol)."""
    box = page.locator(selector).bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    cdp = page.context.new_cdp_session(page)
    data = {"items": [], "files": [str(folder)], "dragOperationsMask": 1}
    for kind in ("dragEnter", "dragOver", "drop"):
        cdp.send("Input.dispatchDragEvent", {"type": kind, "x": x, "y": y, "data": data})
    cdp.detach()


def server_holds(srv: LiveServer, key: str, scene_id: str) -> tuple[dict[str, int], set[str]]:
    """(open upload id → offset, paths of complete files) as the API reports them."""
    with srv.client(key) as c:
        uploads = list_all(c, f"/v1/scenes/{scene_id}/uploads")
        files = list_all(c, f"/v1/scenes/{scene_id}/files")
    return {u["id"]: u["offset"] for u in uploads}, {f["path"] for f in files}


def test_upload_reload_resume_train_and_download_the_mesh(  # type: ignore[no-untyped-def]
    page, owner: tuple[LiveServer, str], tmp_path: Path
) -> None:
    from core.scene.synthetic import write_synthetic_scene

    srv, key = owner
    rec: Recorder = page.recorder
    folder = write_synthetic_scene(
        tmp_path / "glossy sphere", "sphere", "glossy", n_train=6, n_test=2, size=24
    )
    files = scene_files(folder)
    total = sum(len(data) for _, data in files)

    # the folder dropped on the overview (a real drop: Chromium reads the folder from disk)
    # makes a scene named after it; the page pauses after PAUSE_AFTER chunks
    page.evaluate("location.hash = '#/'")
    page.locator("#dropzone").wait_for()
    pausing = {**TUNING, "pauseAfterChunks": PAUSE_AFTER}
    page.evaluate(f"window.__glintUploadTuning = {json.dumps(pausing)}")
    drop_folder(page, "#dropzone", folder)
    page.locator("#upload-panel[data-state='paused']").wait_for(timeout=20_000)
    assert page.inner_text("#main h1") == "glossy sphere"
    scene_id = page.evaluate("location.hash.split('/')[2]")
    assert scene_id.startswith("scn_")
    assert page.locator("#upload-panel li").count() == len(files)
    before = list(rec.chunks)
    partial, complete = server_holds(srv, key, scene_id)
    held = sum(partial.values()) + sum(len(d) for p, d in files if p in complete)
    assert len(before) >= PAUSE_AFTER and 0 < held < total
    assert held == sum(n for _, _, n in before), "the server holds other bytes than were sent"
    assert complete and any(off > 0 for off in partial.values())

    page.reload()
    resume = page.locator("#resume")
    resume.wait_for(timeout=10_000)
    assert "Unfinished upload" in resume.inner_text()
    assert f"{len(complete)} of {len(files)} files are on the server" in resume.inner_text()

    # the same folder again, chosen with the folder input this time: complete files are
    # skipped, partial ones go on from the server's offset
    page.evaluate(f"window.__glintUploadTuning = {json.dumps(TUNING)}")
    page.set_input_files("#pick-folder", folder)
    page.locator("#upload-panel[data-state='done']").wait_for(timeout=20_000)
    after = rec.chunks[len(before) :]
    assert after, "nothing was sent after the reload"
    assert sum(n for _, _, n in rec.chunks) == total, "some bytes were sent twice (or never)"
    for upload_id, offset, _ in after:  # a resumed upload starts where the server stood
        if upload_id in partial:
            assert offset >= partial[upload_id]
    assert page.locator("#upload-panel li[data-state='present']").count() == len(complete)
    with srv.client(key) as c:
        got = {f["path"]: f["size"] for f in list_all(c, f"/v1/scenes/{scene_id}/files")}
    assert got == {p: len(d) for p, d in files}

    # commit, then train with a tiny config from the form
    page.click("#commit")
    page.wait_for_function("document.getElementById('scene-state').textContent === 'ready'")
    page.fill("#train-iterations", "20")
    page.click("#train-form summary")
    config = {k: v for k, v in TINY_CONFIG.items() if k != "iterations"}
    page.fill("#train-config", json.dumps(config))
    page.click("#train-start")
    page.wait_for_function("location.hash.startsWith('#/jobs/job_')")
    job_id = page.evaluate("location.hash.split('/')[2]")
    page.locator("#job-state[data-state='succeeded']").wait_for(timeout=120_000)

    # the chart, the stages, the artifacts, the preview, the viewer link
    page.wait_for_function("window.glintDashboard.chart && window.glintDashboard.chart.psnr >= 2")
    colours = page.evaluate(CANVAS_COLOURS)
    assert colours > 8, "the chart canvas is blank"
    assert page.locator("#job-stages li.done").count() == page.locator("#job-stages li").count()
    glb = page.locator("#artifacts tr[data-name='mesh.glb']")
    glb.wait_for(timeout=10_000)
    with srv.client(key) as c:
        arts = {a["name"]: a["size"] for a in list_all(c, f"/v1/jobs/{job_id}/artifacts")}
    assert page.locator("#artifacts tbody tr").count() == len(arts)
    page.wait_for_function(
        "document.getElementById('mesh-preview').complete && "
        "document.getElementById('mesh-preview').naturalWidth > 0"
    )
    href = page.get_attribute("#open-viewer", "href")
    assert href == f"/viewer/{job_id}#key={key}"

    # another mesh from the checkpoint, at another grid: listed, followed, downloadable
    page.select_option("#mesh-res", "64")
    page.click("#mesh-start")
    mesh = page.locator("#meshes li[data-state='succeeded']")
    mesh.wait_for(timeout=60_000)
    assert mesh.inner_text().startswith("64³ base")
    assert mesh.locator("button[data-download='mesh.glb']").count() == 1

    if SCREENSHOT:
        page.screenshot(path=SCREENSHOT)

    # the mesh, downloaded through fetch with the key in the header
    with page.expect_download(timeout=30_000) as dl:
        glb.locator("button[data-download='mesh.glb']").click()
    path = dl.value.path()
    assert path is not None
    data = Path(path).read_bytes()
    assert data[:4] == b"glTF" and len(data) == arts["mesh.glb"]
    run_dir = srv.settings.store_root / "jobs" / job_id / "run"
    assert data == (run_dir / "mesh.glb").read_bytes()
    assert dl.value.suggested_filename == f"{job_id}_mesh.glb"

    # a long job on the same scene, cancelled from its page, then deleted (asks first)
    page.click(f"#main a[href='#/scenes/{scene_id}']")
    page.locator("#train-form").wait_for()
    page.fill("#train-iterations", "100000")
    page.click("#train-form summary")
    page.fill("#train-config", json.dumps(config))
    page.click("#train-start")
    other_job = f"location.hash.startsWith('#/jobs/') && !location.hash.includes('{job_id}')"
    page.wait_for_function(other_job)
    long_id = page.evaluate("location.hash.split('/')[2]")
    page.locator("#job-cancel").click()
    page.locator("#job-state[data-state='cancelled']").wait_for(timeout=30_000)
    page.click("#job-delete")
    page.click("#confirm-ok")
    page.wait_for_function(f"location.hash === '#/scenes/{scene_id}'")
    with srv.client(key) as c:
        assert c.get(f"/v1/jobs/{long_id}").status_code == 404
        assert c.get(f"/v1/jobs/{job_id}").json()["state"] == "succeeded"

    # nothing but the server (and the page's own blob: URLs) was asked for anything
    foreign = [u for u in rec.urls if not u.startswith((srv.url + "/", "blob:", "data:"))]
    assert not foreign, foreign


def test_drop_a_zip_to_make_a_scene_then_delete_it(page, owner: tuple[LiveServer, str]) -> None:  # type: ignore[no-untyped-def]
    """A scene made from the sidebar takes a dropped zip (one request); deleting asks first."""
    srv, key = owner
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("cap/images/a.txt", b"not really a photo")
        z.writestr("cap/images/b.txt", b"nor is this")
    # a new scene from the sidebar, by keyboard
    page.fill("#new-scene-name", "zip drop")
    page.press("#new-scene-name", "Enter")
    page.wait_for_function("location.hash.startsWith('#/scenes/scn_')")
    page.locator("#dropzone").wait_for()
    dt = page.evaluate_handle(
        """(b64) => { const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
        const dt = new DataTransfer();
        dt.items.add(new File([bytes], 'capture.zip', { type: 'application/zip' }));
        return dt; }""",
        base64.b64encode(buf.getvalue()).decode(),
    )
    page.dispatch_event("#dropzone", "drop", {"dataTransfer": dt})
    page.locator("#upload-panel[data-state='done']").wait_for(timeout=20_000)
    assert "uploaded and unpacked (2 files)" in page.inner_text("#upload-summary")
    scene_id = page.evaluate("location.hash.split('/')[2]")
    with srv.client(key) as c:
        scene = c.get(f"/v1/scenes/{scene_id}").json()
    assert scene["name"] == "zip drop" and scene["file_count"] == 2

    # a failed commit names the file and the field; the scene stays open
    page.click("#commit")
    page.locator("#commit-error").wait_for()
    assert "Commit failed" in page.inner_text("#commit-error")

    page.click("#scene-delete")
    page.locator("#confirm[open]").wait_for()
    page.keyboard.press("Escape")  # keep it
    page.locator("#confirm:not([open])").wait_for(state="attached")
    with srv.client(key) as c:
        assert c.get(f"/v1/scenes/{scene_id}").status_code == 200
    page.click("#scene-delete")
    page.click("#confirm-ok")
    page.wait_for_function("location.hash === '#/'")
    with srv.client(key) as c:
        wait_for(lambda: c.get(f"/v1/scenes/{scene_id}").status_code == 404, timeout=10)


def test_the_page_hashes_large_files_in_slices_like_hashlib(page) -> None:  # type: ignore[no-untyped-def]
    """Files above the whole-file limit are hashed in 4 MiB slices by the page's own
    SHA-256: across slice boundaries and the padding cases it must agree with hashlib."""
    import hashlib

    sizes = [0, 55, 56, 64, 119, 4 * 1024 * 1024 + 17, 9 * 1024 * 1024 + 3]
    got = page.evaluate(
        """async (sizes) => {
        const { hashFile } = await import('/app/static/sha256.js');
        const out = [];
        for (const n of sizes) {
          const b = new Uint8Array(n);
          for (let i = 0; i < n; i++) b[i] = (i * 31 + (i >> 11)) & 255;
          out.push(await hashFile(new Blob([b]), { wholeMax: 0 }));
        }
        return out;
        }""",
        sizes,
    )
    want = [
        hashlib.sha256(bytes((i * 31 + (i >> 11)) & 255 for i in range(n))).hexdigest()
        for n in sizes
    ]
    assert got == want
