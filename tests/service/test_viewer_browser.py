"""The web viewer, end to end in a real headless browser (Debian's chromium driven by Playwright) against
the service run by uvicorn on a loopback port, plus plain checks that the page and its assets are served.

Two browser runs:
- a known room (tests/viewer_job_functions.py, no SLAM): with an API key, a parameter error shown as the
  API words it, the live map while the job runs, then walls and the pillar at the right map coordinates,
  the texture layer, the layer control, the cursor readout, the scale bar and a download;
- the real pipeline on a simulated CARMEN log dropped onto the page.

Chromium missing: skipped with the reason, but failed when CI=true. A failing browser test leaves a
screenshot in tests/artifacts/.
"""

from __future__ import annotations

import base64
import contextlib
import io
import os
import re
import shutil
import socket
import threading
import time
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path

import httpx
import numpy as np
import pytest
import uvicorn
import yaml
from fastapi.testclient import TestClient
from PIL import Image

from service.api.app import create_app
from service.api.routers.viewer import STATIC_DIR
from service.settings import Settings
from tests.service.viewer_job_functions import PILLAR_SIZE_M, PILLAR_XY_M, ROOM_X_M, ROOM_Y_M

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts"
ROOM_JOB = "tests.service.viewer_job_functions:synthetic_room"
API_KEY = "viewer-test-key"


# ---------------------------------------------------------------------------------------------- served


class _AssetLinks(HTMLParser):
    """Local files that index.html loads (stylesheets, scripts)."""

    def __init__(self) -> None:
        super().__init__()
        self.paths: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "link" and a.get("rel") == "stylesheet":
            self.paths.append(a["href"])
        if tag == "script" and a.get("src"):
            self.paths.append(a["src"])


def _module_imports(source: str) -> list[str]:
    return re.findall(r'^\s*import\s[^;]*?from\s+"(\.{1,2}/[^"]+)"', source, flags=re.MULTILINE)


def test_root_redirects_to_the_viewer_and_every_asset_is_served(tmp_path) -> None:
    client = TestClient(create_app(Settings(data_dir=tmp_path)))
    root = client.get("/", follow_redirects=False)
    assert root.status_code == 307 and root.headers["location"] == "/viewer/"
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert str(page.url).endswith("/viewer/")
    assert '<div id="map"' in page.text
    assert client.get("/viewer", follow_redirects=True).text == page.text

    parser = _AssetLinks()
    parser.feed(page.text)
    assert set(parser.paths) == {"vendor/leaflet/leaflet.css", "css/viewer.css", "js/main.js"}
    # Every ES module the page imports, followed through their relative imports, is served as JavaScript.
    pending, seen = ["js/main.js"], set()
    while pending:
        path = pending.pop()
        if path in seen:
            continue
        seen.add(path)
        response = client.get(f"/viewer/{path}")
        assert response.status_code == 200, path
        assert "javascript" in response.headers["content-type"], (path, response.headers["content-type"])
        base = path.rsplit("/", 1)[0]
        pending += [os.path.normpath(f"{base}/{target}") for target in _module_imports(response.text)]
    assert {"js/api.js", "js/mapview.js", "js/newrun.js", "js/jobs.js", "js/format.js",
            "vendor/leaflet/leaflet-src.esm.js"} <= seen
    for path in parser.paths:
        assert client.get(f"/viewer/{path}").status_code == 200, path
    # Leaflet's stylesheet finds its images beside it; Leaflet is the vendored 1.9.4.
    css = client.get("/viewer/vendor/leaflet/leaflet.css").text
    for image in set(re.findall(r"url\((images/[^)]+)\)", css)):
        response = client.get(f"/viewer/vendor/leaflet/{image}")
        assert response.status_code == 200 and response.headers["content-type"] == "image/png", image
    assert 'var version = "1.9.4"' in client.get("/viewer/vendor/leaflet/leaflet-src.esm.js").text
    assert client.get("/viewer/no-such-file.js").status_code == 404


def test_nothing_is_loaded_from_outside_the_package() -> None:
    """No CDN: the page's own HTML, CSS and JS reference no absolute http(s) URL."""
    own = [p for p in STATIC_DIR.rglob("*") if p.suffix in {".html", ".css", ".js"} and "vendor" not in p.parts]
    assert len(own) >= 7
    for path in own:
        assert not re.search(r"""(src|href|url|import|from)\s*[=(]?\s*["']?https?://""", path.read_text()), path


# ------------------------------------------------------------------------------------------- browser


def _require_browser():
    """Playwright's sync API, or skip (fail when CI=true) when it or chromium is missing."""
    reason = None
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        reason = "the Python package playwright is not installed (pip install -e '.[dev]')"
    if reason is None and not (CHROMIUM.exists() or shutil.which("chromium")):
        reason = "chromium is not installed (apt-get install chromium)"
    if reason:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(reason)
        pytest.skip(reason)
    return sync_playwright


@contextlib.contextmanager
def _serve(data_dir: Path, job_function: str | None = None, **settings) -> Iterator[str]:
    """The service on a free loopback port (uvicorn in a thread, workers in processes); yields its URL."""
    settings.setdefault("workers", 1)
    app = create_app(Settings(data_dir=data_dir, **settings), job_function=job_function)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the service did not start")
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    finally:
        server.should_exit = True
        thread.join(timeout=30)
        sock.close()


@contextlib.contextmanager
def _browser_page(name: str, http_credentials: dict[str, str] | None = None) -> Iterator:
    """A fresh page in headless chromium (answering a login prompt with ``http_credentials``); on failure
    its screenshot goes to tests/artifacts/<name>.png."""
    sync_playwright = _require_browser()
    with sync_playwright() as playwright:
        executable = str(CHROMIUM if CHROMIUM.exists() else shutil.which("chromium"))
        browser = playwright.chromium.launch(executable_path=executable, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 800}, accept_downloads=True,
                                http_credentials=http_credentials)
        page.set_default_timeout(30_000)
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        try:
            yield page
            assert not errors, f"JavaScript errors: {errors}"
        except BaseException:
            ARTIFACTS.mkdir(exist_ok=True)
            with contextlib.suppress(Exception):
                page.screenshot(path=str(ARTIFACTS / f"{name}.png"))
            raise
        finally:
            browser.close()


def _map_image(page) -> np.ndarray:
    """The map area as seen (RGB array)."""
    return np.asarray(Image.open(io.BytesIO(page.locator("#map").screenshot())).convert("RGB"))


def _screen_point(page, x_m: float, y_m: float) -> tuple[int, int]:
    """Map-frame (x, y) [m] -> pixel (column, row) in the map element."""
    point = page.evaluate("([x, y]) => { const p = window.lidarmap.jobMap.map.latLngToContainerPoint([y, x]);"
                          " return [p.x, p.y]; }", [x_m, y_m])
    return round(point[0]), round(point[1])


def _pixel(image: np.ndarray, point: tuple[int, int]) -> np.ndarray:
    column, row = point
    return image[row - 1:row + 2, column - 1:column + 2].reshape(-1, 3).mean(axis=0)


def _loaded_tiles(page, layer: str) -> int:
    return page.locator(f".tiles-{layer} img.leaflet-tile-loaded").count()


def _upload_file(page, path: Path) -> None:
    """Drop ``path`` onto the page's drop zone, as a person dragging the file would."""
    data = base64.b64encode(path.read_bytes()).decode()
    transfer = page.evaluate_handle(
        """([name, data]) => {
             const bytes = Uint8Array.from(atob(data), (c) => c.charCodeAt(0));
             const transfer = new DataTransfer();
             transfer.items.add(new File([bytes], name, { type: "application/octet-stream" }));
             return transfer;
           }""", [path.name, data])
    page.dispatch_event("#drop-zone", "drop", {"dataTransfer": transfer})


def _simulated_log(tmp_path: Path) -> Path:
    from slam_engine.simulation import simulate, write_simulated

    drive = simulate("office", seed=3, rig="carmen-robot", max_duration_s=12.0)
    return write_simulated(drive, "carmen", tmp_path / "simulated")


def test_known_room_through_the_page_with_an_api_key(tmp_path) -> None:
    log = _simulated_log(tmp_path)  # accepted by the upload check; the room job does not read it
    login = {"username": "viewer", "password": API_KEY}  # the browser's prompt for the page itself
    with _serve(tmp_path / "data", ROOM_JOB, api_keys=API_KEY) as url, _browser_page("viewer-room", login) as page:
        tile_urls: list[str] = []
        page.on("request", lambda request: tile_urls.append(request.url) if "/tiles/" in request.url else None)
        page.goto(url + "/")
        assert page.url == url + "/viewer/"

        # Without the key the list says what is missing.
        page.wait_for_selector("#list-error:not([hidden])")
        assert "API key is required" in page.inner_text("#list-error")
        page.fill("#api-key", API_KEY)
        page.click("#api-key-form button")
        page.wait_for_selector("#list-error", state="hidden")
        assert page.evaluate("localStorage.getItem('lidarmap.apiKey')") == API_KEY
        page.wait_for_function("document.querySelectorAll('#param-format option').length > 1")  # /v1/formats

        # A file in no known format: the service's 415 message, and no empty session left behind.
        junk = tmp_path / "notes.txt"
        junk.write_text("shopping list\nmilk\n")
        page.set_input_files("#log-file", str(junk))
        page.click("#upload-button")
        page.wait_for_selector("#run-error:not([hidden])", timeout=60_000)
        assert "format" in page.inner_text("#run-error").lower(), page.inner_text("#run-error")
        sessions = httpx.get(f"{url}/v1/sessions", headers={"X-API-Key": API_KEY}).json()
        assert sessions["count"] == 0

        # Error bodies in both shapes read as "field: message" lines.
        messages = page.evaluate("""async () => {
            const { describeError } = await import("/viewer/js/api.js");
            return [
              describeError(422, { detail: [{ loc: ["body", "particles"], msg: "Input should be >= 1" },
                                            { loc: ["query", "limit"], msg: "too big" }] }).message,
              describeError(404, { error: { code: "not_found", message: "no job 'x'", detail: { job_id: "x" } } })
                .message,
              describeError(500, "<html>boom</html>").message,
            ];
        }""")
        assert messages == ["particles: Input should be >= 1\nlimit: too big", "no job 'x'\njob_id: x",
                            "HTTP 500: <html>boom</html>"]

        # A parameter out of bounds: the upload goes through, the job is refused with the API's words.
        page.set_input_files("#log-file", str(log))
        page.fill("#param-particles", "5000")
        page.fill("#param-seed", "300")  # the room job: milliseconds per step
        page.click("#upload-button")
        page.wait_for_selector("#run-error:not([hidden])", timeout=60_000)
        message = page.inner_text("#run-error")
        assert "particles" in message and "1000" in message, message
        assert page.inner_text("#upload-button") == "Start the job"
        page.wait_for_selector(".session .session-name")

        # Fixed: 12 steps of 0.3 s; the live map shows while the job runs and is refreshed as it grows.
        page.fill("#param-particles", "12")
        page.click("#upload-button")
        page.wait_for_selector("#job-status.running", timeout=30_000)
        page.wait_for_function("() => { const w = parseFloat(document.getElementById('job-progress').style.width);"
                               " return w > 0 && w < 100; }")
        page.wait_for_selector(".tiles-occupancy img.leaflet-tile-loaded")
        # The stage the job is in, in its header and its row in the list.
        page.wait_for_function("document.getElementById('job-scans').textContent.startsWith('mapping scans · ')")
        assert "mapping scans · " in page.inner_text(".job.selected .job-meta")
        # Tiles of the live map carry the job's state and scan count (?v=running-<scans>), refreshed as it goes.
        live = {u.rsplit("v=", 1)[1] for u in tile_urls if "/tiles/occupancy/" in u and "v=running-" in u}
        assert live, tile_urls

        page.wait_for_selector("#job-status.succeeded", timeout=60_000)
        live = {u.rsplit("v=", 1)[1] for u in tile_urls if "/tiles/occupancy/" in u and "v=running-" in u}
        assert len(live) >= 2, f"the live map was refreshed only for {live}"
        page.wait_for_selector("path.trajectory-slam")
        page.wait_for_function("document.querySelectorAll('.tiles-texture img.leaflet-tile-loaded').length > 0")
        page.wait_for_function("document.querySelectorAll('.tiles-occupancy img.leaflet-tile-loaded').length > 0")
        page.wait_for_timeout(500)  # last tiles settle
        assert page.inner_text("#job-scans") == "12 / 12 scans"
        assert page.locator(".job .pill.succeeded").count() == 1

        # Both trajectories are SVG paths in the overlay pane, spanning most of the room on screen.
        slam_box = page.locator(".leaflet-overlay-pane svg path.trajectory-slam").bounding_box()
        dead_box = page.locator(".leaflet-overlay-pane svg path.trajectory-dead-reckoning").bounding_box()
        left, bottom = _screen_point(page, 1.5, 1.5)
        right, top = _screen_point(page, ROOM_X_M - 1.5, ROOM_Y_M - 1.5)
        map_box = page.locator("#map").bounding_box()
        assert abs(slam_box["x"] - map_box["x"] - left) < 6 and abs(slam_box["width"] - (right - left)) < 10
        assert abs(slam_box["y"] - map_box["y"] - top) < 6 and abs(slam_box["height"] - (bottom - top)) < 10
        assert dead_box["width"] > 0.8 * (right - left)

        # Occupancy alone (texture switched off in the layer control): the pillar is black where the map
        # frame says, the floor white-ish, outside the walls unknown grey.
        page.get_by_label("Ground texture").uncheck()
        page.wait_for_timeout(300)
        image = _map_image(page)
        pillar = _screen_point(page, PILLAR_XY_M[0] + PILLAR_SIZE_M / 2, PILLAR_XY_M[1] + PILLAR_SIZE_M / 2)
        floor = _screen_point(page, 5.0, 4.0)
        outside = _screen_point(page, -0.5, 4.0)
        wall = _screen_point(page, 0.0, 4.0)
        assert _pixel(image, pillar).max() < 60, _pixel(image, pillar)
        assert _pixel(image, wall).max() < 60, _pixel(image, wall)
        assert _pixel(image, floor).min() > 200, _pixel(image, floor)
        assert np.allclose(_pixel(image, outside), 205, atol=12), _pixel(image, outside)
        # North up, east right: a point just beside the pillar on each side is floor.
        for dx, dy in ((-0.8, 0.0), (0.8, 0.0), (0.0, -0.8)):
            beside = _screen_point(page, PILLAR_XY_M[0] + 0.5 + dx, PILLAR_XY_M[1] + 0.5 + dy)
            assert _pixel(image, beside).min() > 200, (dx, dy, _pixel(image, beside))

        # The texture on top: the floor at (4.5, 4.5) is in a green square, (5.5, 4.5) in a yellow one.
        page.get_by_label("Ground texture").check()
        page.wait_for_function("document.querySelectorAll('.tiles-texture img.leaflet-tile-loaded').length > 0")
        page.wait_for_timeout(300)
        image = _map_image(page)
        green = _pixel(image, _screen_point(page, 4.5, 4.5))
        yellow = _pixel(image, _screen_point(page, 5.5, 4.5))
        assert green[1] > 130 and green[0] < 70 and green[2] < 90, green
        assert yellow[0] > 200 and yellow[1] > 170 and yellow[2] < 80, yellow

        # Cursor readout in map metres.
        page.mouse.move(map_box["x"] + pillar[0], map_box["y"] + pillar[1])
        readout = page.inner_text(".cursor-position")
        x_m, y_m = (float(v) for v in re.findall(r"-?\d+\.\d+", readout))
        assert abs(x_m - 8.5) < 0.1 and abs(y_m - 5.5) < 0.1, readout

        # The scale bar's length matches its label in metres.
        scale = page.locator(".leaflet-control-scale-line")
        value, unit = re.fullmatch(r"(\d+) (m|km)", scale.inner_text()).groups()
        metres = float(value) * (1000 if unit == "km" else 1)
        pixels_per_metre = (_screen_point(page, 10.0, 4.0)[0] - _screen_point(page, 0.0, 4.0)[0]) / 10.0
        assert abs(scale.bounding_box()["width"] - metres * pixels_per_metre) < 4

        # Downloads (fetched with the key): every product link, and map.yaml reads back.
        labels = page.locator("#job-downloads a").all_inner_texts()
        for label in ("occupancy.png", "occupancy.tif (GeoTIFF)", "map.pgm", "map.yaml", "trajectory (TUM)",
                      "texture.png", "run record (JSON)"):
            assert label in labels, labels
        with page.expect_download() as download_info:
            page.click("#job-downloads a[data-product='map.yaml']")
        ros_map = yaml.safe_load(Path(download_info.value.path()).read_text())
        assert ros_map["resolution"] == pytest.approx(0.05)
        assert ros_map["image"] == "map.pgm"

        # Tiles of the final maps were requested for both layers.
        assert any("/tiles/texture/" in u and "v=succeeded-12" in u for u in tile_urls)
        assert any("/tiles/occupancy/" in u and "v=succeeded-12" in u for u in tile_urls)

        # The tile layout the page used: 280 x 200 cells of 0.05 m whose top-left corner is (-1, 9) m; one
        # tile pixel per cell at zoom 1, so zoom 0 has 0.1 m per pixel.
        job_id = page.evaluate("window.location.hash").removeprefix("#job=")
        scheme = httpx.get(f"{url}/v1/jobs/{job_id}/tiles/occupancy", headers={"X-API-Key": API_KEY}).json()
        assert (scheme["width_cells"], scheme["height_cells"], scheme["native_zoom"]) == (280, 200, 1)
        assert scheme["top_left_m"] == pytest.approx([-1.0, 9.0])
        assert scheme["leaflet_transformation"] == pytest.approx([10.0, 10.0, -10.0, 90.0])
        assert page.evaluate("window.lidarmap.jobMap.scheme") == scheme

        # Another job on the same session from its "Map again" button, cancelled from the job header.
        page.fill("#param-particles", "400")
        page.click(".session button:has-text('Map again')")
        page.wait_for_function(f"!window.location.hash.endsWith('{job_id}')")
        page.wait_for_selector("#job-status.running", timeout=30_000)
        page.click("#job-cancel")
        page.wait_for_selector("#job-status.cancelled", timeout=30_000)
        assert "cancelled" in page.inner_text("#job-error")
        assert page.locator(".job").count() == 2


@pytest.mark.slow
def test_simulated_log_dropped_on_the_page_is_mapped(tmp_path) -> None:
    log = _simulated_log(tmp_path)
    with _serve(tmp_path / "data") as url, _browser_page("viewer-simulated") as page:
        tile_urls: list[str] = []
        page.on("request", lambda request: tile_urls.append(request.url) if "/tiles/" in request.url else None)
        page.goto(url + "/viewer/")
        _upload_file(page, log)
        assert page.inner_text("#drop-text").startswith("log.clf")
        page.fill("#param-particles", "8")
        page.click("#upload-button")
        page.wait_for_selector(".job", timeout=60_000)
        page.wait_for_selector("#job-status.succeeded", timeout=240_000)
        page.wait_for_selector(".tiles-occupancy img.leaflet-tile-loaded", timeout=30_000)
        page.wait_for_selector(".leaflet-overlay-pane svg path.trajectory-slam")
        page.wait_for_timeout(500)

        job_id = page.evaluate("window.location.hash").removeprefix("#job=")
        assert any(f"/v1/jobs/{job_id}/tiles/occupancy/" in u for u in tile_urls)
        tiles = page.locator(".tiles-occupancy img.leaflet-tile-loaded")
        assert tiles.count() >= 1
        assert all(w == 256 for w in page.eval_on_selector_all(
            ".tiles-occupancy img.leaflet-tile-loaded", "tiles => tiles.map((t) => t.naturalWidth)"))

        # Not blank: walls (dark) and free space (light) drawn around the trajectory, which the first view shows.
        gray = _map_image(page).astype(int).mean(axis=2)
        dark, light = int((gray < 80).sum()), int((gray > 235).sum())
        assert dark > 2000 and light > 20_000, (dark, light)

        # The trajectory starts at the map origin (first pose) and has one point per scan of the log.
        trajectory = page.evaluate("window.lidarmap.jobMap.layers.trajectory.getLatLngs()"
                                   ".map((p) => [p.lng, p.lat])")
        scans = page.evaluate(f"fetch('/v1/jobs/{job_id}').then((r) => r.json())")["scans_total"]
        assert len(trajectory) == scans >= 50
        assert np.allclose(trajectory[0], [0.0, 0.0], atol=1e-6)
        path_box = page.locator(".leaflet-overlay-pane svg path.trajectory-slam").bounding_box()
        assert path_box["width"] + path_box["height"] > 40


def test_a_localisation_and_an_extension_are_shown_on_their_saved_map(tmp_path) -> None:
    """The simulated office mapped, and a drive there days later (a desk moved, a pillar gone, a door
    closed, a partition put up) localised in its map (the page shows the drive's scans over the saved map,
    and what changed) and used to extend it (the saved map's drive and the new drive in two colours, the
    changes as a layer with its key)."""
    from slam_engine.formats import write_log
    from slam_engine.simulation import simulate

    halves = (simulate("office", seed=0, cameras=False).log, simulate("office-changed", seed=1, cameras=False).log)
    with _serve(tmp_path / "data") as url, httpx.Client(base_url=url, timeout=60) as api:
        sid = api.post("/v1/sessions", json={"name": "office"}).json()["id"]
        logs = []
        for index, half in enumerate(halves):
            path = write_log(half, "carmen", tmp_path / f"half{index}")
            with path.open("rb") as f:
                logs.append(api.post(f"/v1/sessions/{sid}/logs", files={"file": (path.name, f)}).json()["id"])

        def finished(job: dict) -> dict:
            for _ in range(2400):
                state = api.get(f"/v1/jobs/{job['id']}").json()
                if state["status"] not in ("queued", "running"):
                    return state
                time.sleep(0.1)
            raise AssertionError(f"job {job['id']} did not finish")

        mapped = finished(api.post(f"/v1/sessions/{sid}/jobs", json={"log_id": logs[0], "particles": 10}).json())
        assert mapped["status"] == "succeeded", mapped
        start_from = {"log_id": logs[1], "map_job_id": mapped["id"], "particles": 10}
        localised = finished(api.post(f"/v1/sessions/{sid}/jobs", json={**start_from, "mode": "localize"}).json())
        extended = finished(api.post(f"/v1/sessions/{sid}/jobs", json={**start_from, "mode": "extend"}).json())
        assert localised["status"] == extended["status"] == "succeeded", (localised, extended)

        with _browser_page("viewer-localisation") as page:
            page.goto(f"{url}/viewer/#job={localised['id']}")
            image = page.wait_for_selector("img.product-image[data-product='localization.png']", state="visible",
                                           timeout=60_000)
            assert page.evaluate("(img) => img.naturalWidth", image) > 50
            assert page.locator("#job-downloads a[data-product='localization.png']").count() == 1
            picture = np.asarray(Image.open(io.BytesIO(image.screenshot())).convert("RGB")).astype(int)
            red = (picture[..., 0] > 180) & (picture[..., 1] < 90) & (picture[..., 2] < 90)
            assert red.sum() > 50  # the drive's matched end points over the saved map
            # below it, what changed: the saved map with the added cells red and the removed blue
            changes = page.locator("img.product-image[data-product='changes.png']")
            assert changes.is_visible() and page.evaluate("(img) => img.naturalWidth", changes.element_handle()) > 50
            picture = np.asarray(Image.open(io.BytesIO(changes.screenshot())).convert("RGB")).astype(int)
            blue = (picture[..., 2] > 150) & (picture[..., 0] < 80)
            assert blue.sum() > 5 and ((picture[..., 0] > 180) & (picture[..., 1] < 90)).sum() > 5
            # the summary says how much of the drive matched the map, and how long it took
            page.wait_for_selector("#job-summary:not([hidden])")
            placed = page.locator("#job-summary [data-figure='localisation'] .summary-text").inner_text()
            run = api.get(f"/v1/jobs/{localised['id']}/run.json").json()["localization"]
            assert re.fullmatch(rf"{run['scans_tracked']} of {run['scans']} scans matched the map "
                                r"\(mean confidence [\d.]+\) in [\d.]+ s", placed), placed

        with _browser_page("viewer-extension") as page:
            page.goto(f"{url}/viewer/#job={extended['id']}")
            page.wait_for_selector(".tiles-occupancy img.leaflet-tile-loaded", timeout=60_000)
            page.wait_for_selector(".leaflet-overlay-pane svg path.trajectory-saved")
            saved = page.evaluate("window.lidarmap.jobMap.layers.savedDrives.getLatLngs().length")
            new = page.evaluate("window.lidarmap.jobMap.layers.trajectory.getLatLngs().length")
            assert saved == len(halves[0].scans) and new == len(halves[1].scans)
            # the saved map's drives have their own line in the key and their own box in the layer control
            assert page.locator(".map-key .key-saved-drives").inner_text() == "Saved map's drives"
            assert page.get_by_label("Saved map's drives").is_checked()
            page.get_by_label("Saved map's drives").uncheck()
            assert page.locator(".leaflet-overlay-pane svg path.trajectory-saved").count() == 0
            page.get_by_label("Saved map's drives").check()
            assert page.locator("#job-downloads a[data-product='drives.png']").count() == 1
            # what changed since the saved map: polygons in their layer, counted in the key
            page.wait_for_selector(".leaflet-overlay-pane svg path.change-removed")
            features = api.get(f"/v1/jobs/{extended['id']}/changes.geojson").json()["features"]
            removed = sum(f["properties"]["kind"] == "removed" for f in features)
            assert page.locator("path.change-removed").count() == removed == 2
            assert page.locator("path.change-added").count() == len(features) - removed >= 3
            assert page.locator(".map-key .key-changes-removed").inner_text() == "removed since (2)"
            page.get_by_label("Changes since the saved map").uncheck()
            assert page.locator("path.change-added").count() == 0
            page.get_by_label("Changes since the saved map").check()
            assert page.locator("#job-downloads a[data-product='changes.geojson']").count() == 1
            assert page.locator("#job-downloads a[data-product='map_bundle.npz']").count() == 1
            ARTIFACTS.mkdir(exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "viewer-extension.png"))


def test_a_finished_map_is_fitted_keyed_and_summarised(tmp_path) -> None:
    """The known room: while it runs no empty dead-reckoning layer is offered; opened when finished, the
    map fills the pane around the trajectory, drawn thin and half transparent, with a colour key, a
    summary of the run record and every download (occupancy_trajectory.png included). A screenshot of
    the finished page is left in tests/artifacts/viewer-finished-map.png."""
    log = _simulated_log(tmp_path)  # accepted by the upload check; the room job does not read it
    with _serve(tmp_path / "data", ROOM_JOB) as url, httpx.Client(base_url=url, timeout=60) as api:
        sid = api.post("/v1/sessions", json={"name": "room"}).json()["id"]
        with log.open("rb") as f:
            assert api.post(f"/v1/sessions/{sid}/logs", files={"file": (log.name, f)}).status_code == 201
        job_id = api.post(f"/v1/sessions/{sid}/jobs", json={"particles": 12, "seed": 400}).json()["id"]

        with _browser_page("viewer-running-room") as page:
            page.goto(f"{url}/viewer/#job={job_id}")
            page.wait_for_selector("#job-status.running", timeout=30_000)
            page.wait_for_selector(".tiles-occupancy img.leaflet-tile-loaded", timeout=30_000)
            assert api.get(f"/v1/jobs/{job_id}").json()["status"] == "running"
            assert page.get_by_label("Dead reckoning").count() == 0  # nothing to show yet: not offered
            assert page.locator(".map-key .key-dead-reckoning").count() == 0
            page.wait_for_selector("#job-status.succeeded", timeout=60_000)
            page.wait_for_selector("path.trajectory-dead-reckoning", timeout=30_000)
            assert page.get_by_label("Dead reckoning").is_checked()  # offered once it has poses
            assert page.locator(".map-key .key-dead-reckoning").count() == 1

        with _browser_page("viewer-finished-map") as page:
            page.goto(f"{url}/viewer/#job={job_id}")
            page.wait_for_selector(".tiles-occupancy img.leaflet-tile-loaded", timeout=30_000)
            page.wait_for_selector(".leaflet-overlay-pane svg path.trajectory-slam")
            page.wait_for_selector("#job-summary:not([hidden])")
            page.wait_for_timeout(500)  # last tiles settle
            trajectory = page.locator(".leaflet-overlay-pane svg path.trajectory-slam")
            path, settled = trajectory.bounding_box(), None
            for _ in range(20):  # a zoom still animating (once in CI: 652 px wide, 621 after) settles first
                page.wait_for_timeout(100)
                settled = trajectory.bounding_box()
                if settled == path:
                    break
                path = settled

            # fitted: the trajectory and a 2 m margin fill the pane's limiting side (at whole zooms with
            # a 25 % margin the room's trajectory filled under half of the pane)
            pane = page.locator("#map").bounding_box()
            south, west, north, east = page.evaluate(
                "(() => { const b = window.lidarmap.jobMap.layers.trajectory.getBounds();"
                " return [b.getSouth(), b.getWest(), b.getNorth(), b.getEast()]; })()")
            width_m, height_m = east - west, north - south
            pixels_per_m = min(pane["width"] / (width_m + 4.0), pane["height"] / (height_m + 4.0))
            assert path["width"] == pytest.approx(width_m * pixels_per_m, abs=4), (path, pane, width_m)
            assert path["height"] == pytest.approx(height_m * pixels_per_m, abs=4), (path, pane, height_m)
            assert max(path["width"] / pane["width"], path["height"] / pane["height"]) > 0.6

            # thin, half transparent lines
            style = page.eval_on_selector(".leaflet-overlay-pane svg path.trajectory-slam",
                                          "p => [p.getAttribute('stroke-width'), p.getAttribute('stroke-opacity')]")
            assert [float(v) for v in style] == [1.5, 0.6]

            # the colour key: the map's three greys and both lines
            key = page.locator(".map-key").inner_text().splitlines()
            assert key == ["occupied", "free", "unknown", "Trajectory (SLAM)", "Dead reckoning"], key

            # the run record's summary
            figures = {row.get_attribute("data-figure"): row.locator(".summary-text").inner_text()
                       for row in page.locator("#job-summary .summary-row").all()}
            assert figures["accuracy"].startswith("not known"), figures
            assert re.fullmatch(r"\d+ s for 12 scans(, [\d.]+ scans/s)?", figures["time"]), figures
            assert figures["warnings"] == "none", figures

            labels = page.locator("#job-downloads a").all_inner_texts()
            assert "occupancy + trajectories.png" in labels, labels
            with page.expect_download() as download_info:
                page.click("#job-downloads a[data-product='occupancy_trajectory.png']")
            assert Image.open(download_info.value.path()).size == (280, 200)
            ARTIFACTS.mkdir(exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "viewer-finished-map.png"))


@pytest.mark.slow
def test_loop_closures_are_drawn_and_counted(tmp_path) -> None:
    """The simulated office loop mapped by the real pipeline: each accepted loop closure is a line between
    its two key frames' places, counted in the colour key and the summary."""
    from slam_engine.formats import write_log
    from slam_engine.simulation import simulate

    log = write_log(simulate("office", seed=0, cameras=False).log, "carmen", tmp_path / "office")
    with _serve(tmp_path / "data") as url, httpx.Client(base_url=url, timeout=60) as api:
        sid = api.post("/v1/sessions", json={"name": "office loop"}).json()["id"]
        with log.open("rb") as f:
            assert api.post(f"/v1/sessions/{sid}/logs", files={"file": (log.name, f)}).status_code == 201
        job_id = api.post(f"/v1/sessions/{sid}/jobs", json={"particles": 10}).json()["id"]
        for _ in range(2400):
            job = api.get(f"/v1/jobs/{job_id}").json()
            if job["status"] not in ("queued", "running"):
                break
            time.sleep(0.1)
        assert job["status"] == "succeeded", job
        closing = api.get(f"/v1/jobs/{job_id}/run").json()["loop_closing"]
        accepted = [c for c in closing["closures"] if c["accepted"]]
        assert len(accepted) >= 5

        with _browser_page("viewer-closures") as page:
            page.goto(f"{url}/viewer/#job={job_id}")
            page.wait_for_selector(".leaflet-overlay-pane svg path.loop-closure")
            assert page.locator(".leaflet-overlay-pane svg path.loop-closure").count() == len(accepted)
            ends = page.evaluate("window.lidarmap.jobMap.layers.closures.getLayers()"
                                 ".map((line) => line.getLatLngs().map((p) => [p.lng, p.lat]))")
            assert sorted(map(sorted, ends)) == sorted(sorted([c["anchor_xy_m"], c["node_xy_m"]]) for c in accepted)
            assert page.get_by_label("Loop closures").is_checked()
            assert f"Loop closures ({len(accepted)})" in page.locator(".map-key").inner_text()
            page.wait_for_selector("#job-summary:not([hidden])")
            summary = page.locator("#job-summary [data-figure='loop-closures'] .summary-text").inner_text()
            assert summary == f"{len(accepted)} accepted of {closing['candidates_matched']} candidates matched"
            ARTIFACTS.mkdir(exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "viewer-closures.png"))


def test_a_live_localisation_shows_the_robot_moving_in_the_saved_map(tmp_path) -> None:
    """The simulated office mapped, then driven again and streamed into a live localisation: while it runs
    the page shows the saved map's tiles, the path of the scans found in it growing, the robot's marker
    and its state in the key."""
    from service.storage.stream_log import calibration_from_log, messages_of_log
    from slam_engine.formats import load_log, write_log
    from slam_engine.simulation import simulate

    before = write_log(simulate("office", seed=0, cameras=False).log, "carmen", tmp_path / "before")
    later = load_log(write_log(simulate("office", seed=1, cameras=False).log, "carmen", tmp_path / "later"))
    messages = messages_of_log(later)
    chunks = [messages[i:i + 40] for i in range(0, len(messages), 40)]
    with _serve(tmp_path / "data", workers=2) as url, httpx.Client(base_url=url, timeout=60) as api:
        sid = api.post("/v1/sessions", json={"name": "office", "calibration": calibration_from_log(later)}).json()["id"]
        with before.open("rb") as f:
            api.post(f"/v1/sessions/{sid}/logs", files={"file": (before.name, f)})
        mapped = api.post(f"/v1/sessions/{sid}/jobs", json={"particles": 10}).json()
        for _ in range(2400):
            if api.get(f"/v1/jobs/{mapped['id']}").json()["status"] not in ("queued", "running"):
                break
            time.sleep(0.1)
        live = api.post(f"/v1/sessions/{sid}/jobs", json={"live": True, "mode": "localize",
                                                          "map_job_id": mapped["id"]}).json()
        with _browser_page("viewer-live-localisation") as page:
            page.goto(f"{url}/viewer/#job={live['id']}")
            page.wait_for_selector(".tiles-occupancy img.leaflet-tile-loaded", timeout=60_000)
            tiles = page.evaluate("window.lidarmap.jobMap.layers.occupancy._url")
            assert tiles.startswith(f"/v1/jobs/{mapped['id']}/tiles/occupancy/")  # the saved map's
            # the drive sent chunk by chunk until the page has drawn 50 found scans (a placement found in the
            # background lands with the scans after it, however slow the machine), then the rest of it
            count = "window.lidarmap.jobMap.layers.trajectory.getLatLngs().length"
            seq = 0
            while seq < len(chunks) - 10 and not (page.evaluate(f"!!window.lidarmap.jobMap.layers.trajectory "
                                                                f"&& {count} > 50")):
                api.post(f"/v1/sessions/{sid}/chunks", json={"seq": seq, "messages": chunks[seq]})
                seq += 1
                page.wait_for_timeout(300)
            page.wait_for_function(f"{count} > 50", timeout=60_000)
            seen = page.evaluate(count)
            assert page.locator(".map-key .key-live").inner_text().startswith("robot: found (confidence ")
            for later, chunk in enumerate(chunks[seq:], start=seq):
                api.post(f"/v1/sessions/{sid}/chunks", json={"seq": later, "messages": chunk})
            page.wait_for_function(f"{count} > {seen + 20}", timeout=60_000)  # the robot moves on as the stream goes on
            marker = page.evaluate("(() => { const p = window.lidarmap.jobMap.layers.pose.getLatLng(); "
                                   "return [p.lat, p.lng]; })()")
            poses = api.get(f"/v1/jobs/{live['id']}/poses").json()["poses"]
            placed = [p["pose"] for p in poses if p["pose"] is not None]
            assert min(abs(marker[0] - p[1]) + abs(marker[1] - p[0]) for p in placed) < 1e-6  # a reported pose
            ARTIFACTS.mkdir(exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "viewer-live-localisation.png"))
        api.post(f"/v1/sessions/{sid}/chunks/finish", json={})
