"""The mesh view (/viewer/{job}/mesh) in headless Chromium: a job's relightable asset
drawn with the vendored three.js (WebGL through SwiftShader: --disable-gpu).

The asset comes the real way: a mesh job with ``asset`` on the shared tiny trained job
(a 32³ grid, 1000 faces, 64² textures, 2 views: about two seconds).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from tests.api.support import list_all, wait_for
from tests.viewer.conftest import TrainedJob

CHROMIUM = os.environ.get("GLINT_CHROMIUM", "/usr/bin/chromium")

pytestmark = pytest.mark.skipif(
    not Path(CHROMIUM).is_file(),
    reason=f"{CHROMIUM} is missing: run scripts/browser.sh to install Debian's chromium",
)

ASSET = {"faces": 1000, "texture_size": 64, "views": 2}
BACKGROUND = (0x20, 0x21, 0x24)  # mesh.js's clear colour, sRGB

# The WebGL canvas read back through a 2D canvas (the renderer keeps its drawing
# buffer): how many pixels differ from the background colour, and the corner's colour.
CANVAS_PIXELS = """(bg) => {
  window.glintMeshView.render();
  const src = document.getElementById('view');
  const c = document.createElement('canvas');
  c.width = src.width; c.height = src.height;
  const g = c.getContext('2d');
  g.drawImage(src, 0, 0);
  const d = g.getImageData(0, 0, c.width, c.height).data;
  let object = 0, level = 0;
  for (let i = 0; i < d.length; i += 4) {
    const diff = Math.abs(d[i] - bg[0]) + Math.abs(d[i + 1] - bg[1]) + Math.abs(d[i + 2] - bg[2]);
    if (diff > 12) { object += 1; level += d[i] + d[i + 1] + d[i + 2]; }
  }
  return { object, level: level / Math.max(object, 1), total: d.length / 4,
           corner: [d[0], d[1], d[2]], w: c.width, h: c.height };
}"""


@pytest.fixture(scope="module")
def asset_job(trained_job: TrainedJob) -> str:
    """A succeeded mesh job of the shared trained job that also baked an asset."""
    with trained_job.server.client(trained_job.key) as c:
        r = c.post(f"/v1/jobs/{trained_job.job_id}/meshes", json={"resolution": 32, "asset": ASSET})
        assert r.status_code == 201, r.text
        job_id = r.json()["id"]

        def done() -> dict | None:
            j = c.get(f"/v1/jobs/{job_id}").json()
            return j if j["state"] in ("succeeded", "failed", "cancelled") else None

        job = wait_for(done, timeout=120, every=0.2)
        assert job["state"] == "succeeded", job["error"]
    return job_id


@pytest.fixture(scope="module")
def browser() -> Iterator:  # type: ignore[type-arg]
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(
            executable_path=CHROMIUM,
            headless=True,
            args=["--no-sandbox", "--disable-gpu", "--disable-background-networking"],
        )
        yield b
        b.close()


@pytest.fixture
def page(browser, trained_job: TrainedJob) -> Iterator:  # type: ignore[no-untyped-def, type-arg]
    """A fresh tab that records every request and page error; none may leave the
    server's origin (three.js is served with the page, not from a CDN)."""
    pg = browser.new_page(viewport={"width": 900, "height": 600})
    requests: list[str] = []
    errors: list[str] = []
    pg.on("request", lambda r: requests.append(r.url))
    pg.on("pageerror", lambda e: errors.append(str(e)))
    yield pg
    pg.close()
    origin = urlsplit(trained_job.server.url)
    foreign = [
        u
        for u in requests
        if not u.startswith(("data:", "blob:"))
        and (urlsplit(u).scheme, urlsplit(u).netloc) != (origin.scheme, origin.netloc)
    ]
    assert not foreign, f"requests to another origin: {foreign}"
    assert not any(u.startswith("blob:") and origin.netloc not in u for u in requests)
    assert not errors, f"page errors: {errors}"


def _open(page, trained_job: TrainedJob, job_id: str) -> str:  # type: ignore[no-untyped-def]
    page.goto(f"{trained_job.server.url}/viewer/{job_id}/mesh#key={trained_job.key}")
    page.wait_for_function(
        "window.glintMeshView && !['loading', 'waiting'].includes(window.glintMeshView.state)",
        timeout=60_000,
    )
    return page.locator("#mesh-status").get_attribute("data-state")


def test_the_mesh_view_draws_the_asset_lit_by_its_environment(  # type: ignore[no-untyped-def]
    page, trained_job: TrainedJob, asset_job: str, tmp_path: Path
) -> None:
    state = _open(page, trained_job, asset_job)
    status = page.locator("#mesh-status")
    assert state == "loaded", status.inner_text()
    assert "#key" not in page.url  # the key left the address bar at once
    # the counts are read from the loaded glTF; asset.json says what was written
    with trained_job.server.client(trained_job.key) as c:
        info = c.get(f"/v1/jobs/{asset_job}/artifacts/asset.json").json()
    assert int(status.get_attribute("data-vertices")) == info["mesh"]["vertices"] > 0
    assert int(status.get_attribute("data-faces")) == info["mesh"]["faces"] > 0
    assert f"{info['mesh']['faces']:,} faces" in status.inner_text()
    assert page.evaluate("window.glintMeshView.hasEnv") is True
    assert "asset_env.hdr" in page.locator("#env-note").inner_text()

    plain = page.evaluate(CANVAS_PIXELS, list(BACKGROUND))
    assert plain["w"] > 100 and plain["h"] > 100
    assert plain["corner"] == list(BACKGROUND)
    # the object covers part of the view and is lit (its pixels are not the background)
    assert 0.02 < plain["object"] / plain["total"] < 0.95, plain

    page.fill("#exposure", "1")  # one stop up: the object's pixels brighten
    assert page.locator("#exposure-value").inner_text() == "+1.0 EV"
    bright = page.evaluate(CANVAS_PIXELS, list(BACKGROUND))
    assert bright["level"] > plain["level"] + 5, (plain, bright)

    page.check("#env-bg")  # the environment behind the object: the corner changes
    lit = page.evaluate(CANVAS_PIXELS, list(BACKGROUND))
    assert lit["corner"] != list(BACKGROUND), lit
    files = page.locator("#asset-files a")
    assert "asset.glb" in files.all_inner_texts()
    shot = tmp_path / "mesh_view.png"
    page.screenshot(path=str(shot))
    print(f"mesh view screenshot: {shot}")


def test_a_job_without_an_asset_says_so_and_how_to_make_one(  # type: ignore[no-untyped-def]
    page, trained_job: TrainedJob, asset_job: str
) -> None:
    with trained_job.server.client(trained_job.key) as c:
        names = {a["name"] for a in list_all(c, f"/v1/jobs/{trained_job.job_id}/artifacts")}
    assert "asset.glb" not in names  # the shared job trained without outputs.asset
    assert _open(page, trained_job, trained_job.job_id) == "missing"
    assert "no relightable asset" in page.locator("#mesh-status").inner_text()
    missing = page.locator("#missing")
    text = missing.inner_text()
    assert f"POST /v1/jobs/{trained_job.job_id}/meshes" in text and '{"asset": {}}' in text
    # the training job's mesh jobs with an asset are offered
    assert missing.locator(f"a[data-job='{asset_job}']").count() == 1
    assert page.locator("#make-asset").is_visible()


def test_three_js_is_served_with_the_page_as_javascript(trained_job: TrainedJob) -> None:
    with trained_job.server.client(None) as c:
        html = c.get(f"/viewer/{trained_job.job_id}/mesh")
        assert html.status_code == 200 and 'type="importmap"' in html.text
        csp = html.headers.get("content-security-policy")
        assert csp is None or "blob:" in csp  # GLTFLoader reads embedded textures by blob URL
        for path in (
            "vendor/three/three.module.js",
            "vendor/three/three.core.js",
            "vendor/three/addons/loaders/GLTFLoader.js",
            "vendor/three/addons/loaders/HDRLoader.js",
            "vendor/three/addons/controls/OrbitControls.js",
            "vendor/three/addons/utils/BufferGeometryUtils.js",
            "vendor/three/addons/utils/SkeletonUtils.js",
            "mesh.js",
        ):
            r = c.get(f"/viewer/static/{path}")
            assert r.status_code == 200, path
            assert "javascript" in r.headers["content-type"], (path, r.headers["content-type"])
