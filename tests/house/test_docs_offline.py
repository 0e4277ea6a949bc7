"""/docs (Swagger UI) and /redoc work without internet: every asset comes from the app."""

from __future__ import annotations

import re
from html.parser import HTMLParser
from urllib.parse import urlparse

import pytest

pytestmark = pytest.mark.redis


class Links(HTMLParser):
    """The URLs of a page's src and href attributes."""

    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.urls += [v for k, v in attrs if k in ("src", "href") and v]


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_load_only_local_assets(api, page):
    answer = api.get(page)
    assert answer.status_code == 200 and answer.headers["content-type"].startswith("text/html")
    links = Links()
    links.feed(answer.text)
    urls = links.urls + re.findall(r"""(?:url|spec-url)\s*[:=]\s*['"]([^'"]+)['"]""", answer.text)
    assert any(u.endswith(".js") for u in urls) and "/openapi.json" in urls
    for url in urls:
        parsed = urlparse(url)
        assert not parsed.scheme and not parsed.netloc, url  # no CDN, no fonts host
        asset = api.get(url)
        assert asset.status_code == 200, url
        if url.endswith(".js"):  # the real bundle, not a stub
            assert len(asset.content) > 500_000 and "javascript" in asset.headers["content-type"]
    assert "http://" not in answer.text and "https://" not in answer.text
    if page == "/docs":
        assert '"validatorUrl": null' in answer.text  # Swagger UI's online validator: off
