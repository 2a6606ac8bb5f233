"""A MkDocs hook: the built site leaves out two things Material copies that no reader loads.

- The JavaScript source maps (``*.js.map``, ~1 MB), which only a browser's developer tools
  request, to show Material's own TypeScript.
- Search's stemmers for other languages (``assets/javascripts/lunr/``, ~1 MB), when the search
  plugin indexes English only: Material's search worker loads a language's file only for the
  languages configured.

The site stays within CI's 8 MiB budget (``.ci/run``) with room for pictures."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any


def _search_languages(config: Any) -> list[str]:
    search = config["plugins"].get("search") or config["plugins"].get("material/search")
    languages = (search.config.get("lang") if search is not None else None) or ["en"]
    return [languages] if isinstance(languages, str) else list(languages)


def on_post_build(config: Any, **kwargs: Any) -> None:
    scripts = Path(config["site_dir"]) / "assets" / "javascripts"
    for source_map in scripts.rglob("*.js.map"):
        source_map.unlink()
    if _search_languages(config) == ["en"]:
        shutil.rmtree(scripts / "lunr", ignore_errors=True)
