"""The README is a short door and the docs a site whose every page is reachable: links in the
README resolve, every page under docs/ is in the site's navigation, the front door names no
machine and no run's wall time. (The commands of both are composed in tests/test_cli.py;
``mkdocs build --strict`` in .ci/run checks the site's own links.)"""

from __future__ import annotations

import re

import yaml
from helpers import REPO

README = REPO / "README.md"
DOCS = REPO / "docs"


def _nav_pages(node: object) -> list[str]:
    if isinstance(node, str):
        return [node]
    if isinstance(node, list):
        return [page for item in node for page in _nav_pages(item)]
    if isinstance(node, dict):
        return [page for value in node.values() for page in _nav_pages(value)]
    return []


def test_the_readme_is_a_short_door() -> None:
    text = README.read_text()
    assert len(text.splitlines()) <= 250
    # No lab notebook: machines, CPU features, run timings, commits.
    for pattern in (r"\bAMX\b", r"\bEPYC\b", r"this machine", r"\b\d+ min \d+ s\b", r"2 cores"):
        assert not re.search(pattern, text), pattern
    for heading in ("## Install", "## Citing", "## Layout", "## Documentation"):
        assert heading in text


def test_every_link_in_the_readme_resolves() -> None:
    links = re.findall(r"\]\(([^)\s]+)\)", README.read_text())
    local = [link for link in links if not re.match(r"[a-z]+://", link)]
    assert len(local) > 20
    missing = [link for link in local if not (REPO / link.split("#")[0]).exists()]
    assert missing == []


def test_every_docs_page_is_in_the_site_navigation() -> None:
    # mkdocs.yml has no Python tags (!!python/name) to resolve: plain YAML.
    config = yaml.safe_load((REPO / "mkdocs.yml").read_text())
    nav = set(_nav_pages(config["nav"]))
    pages = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")}
    assert pages - nav == set()
    assert nav - pages == set()
