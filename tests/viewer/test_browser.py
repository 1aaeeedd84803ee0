"""The viewer page in headless Chromium (Debian's, never a downloaded one)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.viewer.conftest import TrainedJob

CHROMIUM = os.environ.get("GLINT_CHROMIUM", "/usr/bin/chromium")

pytestmark = pytest.mark.skipif(
    not Path(CHROMIUM).is_file(),
    reason=f"{CHROMIUM} is missing: run scripts/browser.sh to install Debian's chromium",
)

# A digest of the canvas pixels: equal digests = the same picture.
CANVAS_SUM = """() => {
  const c = document.getElementById('view');
  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  let h = 0;
  for (let i = 0; i < d.length; i += 7) h = (h * 31 + d[i]) >>> 0;
  return [h, c.width, c.height];
}"""


@pytest.fixture(scope="module")
def page(trained_job: TrainedJob) -> Iterator:  # type: ignore[type-arg]
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=CHROMIUM,
            headless=True,
            args=["--no-sandbox", "--disable-gpu", "--disable-background-networking"],
        )
        pg = browser.new_page(viewport={"width": 1100, "height": 640})
        errors: list[str] = []
        pg.on("pageerror", lambda e: errors.append(str(e)))
        pg.goto(f"{trained_job.server.url}/viewer/{trained_job.job_id}#key={trained_job.key}")
        yield pg
        browser.close()
        assert not errors, f"page errors: {errors}"


def wait_still_frame(page, after_seq: int = 0, channel: str | None = None) -> dict:  # type: ignore[no-untyped-def]
    """Wait for a full-resolution frame answering a camera newer than ``after_seq``."""
    cond = f"(h => h && h.full && h.seq > {after_seq}" + (
        f" && h.channel === '{channel}')" if channel else ")"
    )
    page.wait_for_function(
        f"{cond}(window.glintViewer && window.glintViewer.lastHeader)", timeout=60_000
    )
    return page.evaluate("window.glintViewer.lastHeader")


def test_view_orbit_channel_and_screenshot(page, trained_job: TrainedJob, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    page.wait_for_function("window.glintViewer && window.glintViewer.frames > 0", timeout=60_000)
    first = wait_still_frame(page)
    page.wait_for_function("window.glintViewer.cameras.length > 0", timeout=30_000)
    assert page.locator("#job-state").inner_text() == "succeeded"
    assert page.locator("#job-iter").inner_text() == "12 / 12"
    assert "dB" in page.locator("#job-psnr").inner_text()
    assert page.locator("#st-device").inner_text() in ("cpu · cpu", "cpu · reference")
    # settle on the view the page chose (it jumps to the first training camera)
    page.wait_for_timeout(400)
    before_head = wait_still_frame(page, 0)
    before = page.evaluate(CANVAS_SUM)
    assert before[1] > 100 and before[2] > 100

    box = page.locator("#stage").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 160, y + 30, steps=8)
    page.mouse.up()
    orbited_head = wait_still_frame(page, before_head["seq"])
    orbited = page.evaluate(CANVAS_SUM)
    assert orbited != before, "the frame did not change after orbiting"

    page.click("button[data-channel='normal']")
    normal_head = wait_still_frame(page, orbited_head["seq"], channel="normal")
    normal = page.evaluate(CANVAS_SUM)
    assert normal != orbited, "the normal channel looks like the final one"
    assert normal_head["channel"] == "normal"

    # the env map panorama and the readouts are there
    page.wait_for_function(
        "document.getElementById('envmap').complete && !document.getElementById('envmap').hidden",
        timeout=30_000,
    )
    assert page.evaluate("document.getElementById('envmap').naturalWidth") > 0
    assert "ms" in page.locator("#hud-ms").inner_text()
    assert "×" in page.locator("#hud-res").inner_text()

    page.click("button[data-channel='final']")
    wait_still_frame(page, normal_head["seq"], channel="final")
    shot = tmp_path / "viewer.png"
    page.screenshot(path=str(shot))
    assert shot.stat().st_size > 10_000
    print(f"viewer screenshot: {shot}")
    assert first["render_ms"] > 0


def test_reset_returns_to_the_home_view(page) -> None:  # type: ignore[no-untyped-def]
    head = wait_still_frame(page)
    home_eye = page.evaluate("window.glintViewer.home.target")
    page.keyboard.press("d")  # not in the stage focus rules: any key press reaches window
    page.click("#reset")
    wait_still_frame(page, head["seq"])
    assert page.evaluate("window.glintViewer.target") == home_eye


def test_mesh_panel_lists_extracts_and_downloads(page, trained_job: TrainedJob) -> None:  # type: ignore[no-untyped-def]
    """The training job's own mesh is listed; a re-extraction started from the panel
    runs to the end and its files download (through fetch, the key in a header)."""
    own = page.locator(f"#meshes li[data-job='{trained_job.job_id}']")
    own.wait_for(timeout=30_000)
    assert "from training" in own.inner_text()
    page.select_option("#mesh-res", "64")
    page.select_option("#mesh-color", "radiance")
    page.click("#mesh-start")
    others = f"#meshes li[data-state='succeeded']:not([data-job='{trained_job.job_id}'])"
    done = page.locator(others).filter(has_text="64³ radiance")  # not another test's mesh job
    done.first.wait_for(timeout=90_000)
    assert "64³ radiance" in done.first.inner_text()
    with page.expect_download(timeout=30_000) as dl:
        done.first.locator("a[data-file='mesh.glb']").click()
    path = dl.value.path()
    assert path is not None and Path(path).read_bytes()[:4] == b"glTF"
    assert dl.value.suggested_filename.endswith("_mesh.glb")
    assert page.locator("#mesh-note").inner_text() == ""
