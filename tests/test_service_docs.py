"""``/docs`` works on an offline network: Swagger UI's page references only this server, which serves its files."""

import re

import httpx
import pytest

from service_support import ServerThread


@pytest.fixture(scope="module")
def client():
    with ServerThread(workers=1) as s:
        with httpx.Client(base_url=s.url) as c:
            yield c


def test_docs_page_references_only_this_server(client):
    page = client.get("/docs")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    urls = re.findall(r"""(?:src|href|url)\s*[:=]\s*['"]([^'"]+)['"]""", page.text)
    assert urls, page.text
    # every script, style sheet, icon and the schema: a path on this server, no scheme, no other host
    assert all(u.startswith("/") and not u.startswith("//") for u in urls), urls
    assert "http://" not in page.text and "https://" not in page.text
    assert {"/docs/swagger-ui-bundle.js", "/docs/swagger-ui.css", "/openapi.json"} <= set(urls)


def test_docs_assets_are_served_here(client):
    js = client.get("/docs/swagger-ui-bundle.js")
    assert js.status_code == 200 and "javascript" in js.headers["content-type"]
    assert len(js.content) > 100_000 and b"SwaggerUIBundle" in js.content  # the real bundle, not a stub
    css = client.get("/docs/swagger-ui.css")
    assert css.status_code == 200 and css.headers["content-type"].startswith("text/css") and b".swagger-ui" in css.content
    assert client.get("/docs/favicon-32x32.png").content[:4] == b"\x89PNG"
    # only the named files: not the package's other files, not a path out of it
    assert client.get("/docs/index.html").status_code == 404
    assert client.get("/docs/..%2F__init__.py").status_code == 404
    assert client.get("/redoc").status_code == 404
    assert client.get("/openapi.json").json()["info"]["title"]
