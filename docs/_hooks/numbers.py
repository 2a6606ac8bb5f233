"""A MkDocs hook: a value and its spread (``4.930 ± 0.049``) never break over two lines. The
results tables print mean ± std in every cell; in a narrow column the browser would otherwise
break each at its spaces, into three lines."""

from __future__ import annotations

import re
from typing import Any

_SPREAD = re.compile(r"(\d) ± ([\d−-])")


def on_page_content(html: str, **kwargs: Any) -> str:
    return _SPREAD.sub("\\1\u00a0±\u00a0\\2", html)
