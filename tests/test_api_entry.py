"""What a newcomer opens first: ``/`` and the interactive API docs, which must work offline."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from swagger_ui_bundle import swagger_ui_path

from harness.live import LiveServer
from service.config import Settings

ASSET_URLS = re.compile(r'(?:href|src)="([^"]*)"')


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    url = f"sqlite:///{tmp_path_factory.mktemp('entry') / 'narxwatch.db'}"
    with LiveServer(Settings(database_url=url)) as live:
        yield live


def test_the_root_leads_to_the_dashboard(server: LiveServer):
    response = httpx.get(f"{server.url}/")
    assert response.is_redirect and response.headers["location"] == "/dashboard"
    followed = httpx.get(f"{server.url}/", follow_redirects=True)
    assert followed.status_code == 200 and followed.url.path == "/dashboard/login"


def test_the_docs_load_swagger_ui_from_the_installed_package_only(server: LiveServer):
    page = httpx.get(f"{server.url}/docs")
    assert page.status_code == 200
    assert "http://" not in page.text and "https://" not in page.text, "nothing is fetched from elsewhere"
    assets = ASSET_URLS.findall(page.text)
    assert {Path(url).name for url in assets} == {
        "swagger-ui.css",
        "swagger-ui-bundle.js",
        "favicon-32x32.png",
    }
    for url in assets:
        assert url.startswith("/") and not url.startswith("//"), url
        answer = httpx.get(f"{server.url}{url}")
        assert answer.status_code == 200, url
        assert answer.content == (Path(swagger_ui_path) / Path(url).name).read_bytes()
    assert "url: '/openapi.json'" in page.text
    assert httpx.get(f"{server.url}/openapi.json").json()["info"]["title"] == "narxwatch"


def test_redoc_which_would_need_a_cdn_is_not_served(server: LiveServer):
    assert httpx.get(f"{server.url}/redoc").status_code == 404
