"""/docs (Swagger UI) and /redoc (ReDoc) render with the network off: a real headless chromium whose every
request to a host other than the service's loopback address is refused (and recorded), against the service
run by uvicorn. Their scripts and styles are the package's own (service/api/docs_assets), pinned.

Chromium missing: skipped with the reason, but failed when CI=true.
"""

from __future__ import annotations

from pathlib import Path
from urllib.parse import urlsplit

from fastapi.testclient import TestClient

from service.api.app import create_app
from service.api.routers.api_docs import ASSETS_DIR, REDOC_VERSION, SWAGGER_UI_VERSION
from service.settings import Settings
from tests.service.test_viewer_browser import _browser_page, _serve

LOOPBACK = {"127.0.0.1", "localhost"}


def offline(page) -> list[str]:
    """Refuse every request that leaves this machine; returns the list the refused URLs go into."""
    refused: list[str] = []

    def route(route) -> None:
        if urlsplit(route.request.url).hostname in LOOPBACK or route.request.url.startswith("data:"):
            route.continue_()
        else:
            refused.append(route.request.url)
            route.abort("internetdisconnected")

    page.route("**/*", route)
    return refused


def test_docs_pages_reference_only_the_packaged_assets(tmp_path: Path) -> None:
    client = TestClient(create_app(Settings(data_dir=tmp_path)))
    for page_url in ("/docs", "/redoc"):
        page = client.get(page_url)
        assert page.status_code == 200
        assert "http://" not in page.text and "https://" not in page.text, page_url  # no CDN, no web font
        assert "default-src 'self'" in page.headers["content-security-policy"]  # nor from the scripts
    assets = {"/static/docs/swagger-ui/swagger-ui-bundle.js": f'PACKAGE_VERSION:"{SWAGGER_UI_VERSION}"',
              "/static/docs/redoc/redoc.standalone.js": f'"{REDOC_VERSION}"'}
    for url, version in assets.items():  # the pinned versions are the ones served
        response = client.get(url)
        assert response.status_code == 200 and "javascript" in response.headers["content-type"]
        assert version in response.text, url
    assert client.get("/static/docs/swagger-ui/swagger-ui.css").status_code == 200
    for licence in ("swagger-ui/LICENSE", "redoc/LICENSE"):
        assert (ASSETS_DIR / licence).stat().st_size > 500
    provenance = (ASSETS_DIR / "PROVENANCE.md").read_text()
    assert f"Swagger UI {SWAGGER_UI_VERSION}" in provenance and f"ReDoc {REDOC_VERSION}" in provenance


def test_swagger_ui_renders_the_operations_offline(tmp_path: Path) -> None:
    with _serve(tmp_path / "data") as url, _browser_page("api-docs-offline") as page:
        refused = offline(page)
        page.goto(f"{url}/docs")
        page.wait_for_selector(".opblock", timeout=30_000)
        paths = [p.strip() for p in page.locator(".opblock-summary-path").all_inner_texts()]
        assert "/v1/jobs/{job_id}" in [p.replace("\u200b", "") for p in paths]
        assert len(paths) >= 20
        assert page.locator(".info .title").inner_text().startswith("lidarmap")
        page.goto(f"{url}/redoc")
        page.wait_for_selector("h1", timeout=30_000)
        page.get_by_text("Queue a mapping run", exact=False).first.wait_for(timeout=30_000)
        assert refused == []
