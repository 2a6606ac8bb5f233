"""A Griffe extension for the API reference: the package's docstrings cross-reference with
Sphinx roles (``:class:`~fusion_depth.data.Sample```, ``:func:`predict_depth```), which
``help()`` and editors show as they are and Markdown would print as literal text. Here each
role becomes an optional autorefs link: a link where the target is on a reference page, its name
in code font where it is not (``torch.Tensor``, a private helper).

Names resolve as Sphinx resolves them in the docstring's scope: absolute (``fusion_depth.x``),
relative to the package (``.cli``), or through the object's and its parents' members and
imports; an alias goes to the object it names, which is where the reference renders it.
"""

from __future__ import annotations

import html
import re
from typing import Any

import griffe

# :class:`Name`, :func:`~pkg.mod.f`, :py:meth:`Class.method`, and with a title of its own,
# :meth:`title <pkg.mod.Class.method>` (the title shown, the target linked).
ROLE = re.compile(
    r":(?:py:)?(?:class|func|data|meth|mod|attr|exc|obj|const):"
    r"`(?:([^`<>]*?)\s*<(~?)([^`<>]+)>|(~?)([^`<>]+))`"
)


def _package_of(obj: griffe.Object) -> griffe.Object:
    module = obj if obj.is_module else obj.module
    return module if module.is_init_module else module.parent


def _path(obj: griffe.Object, target: str) -> str | None:
    """The full path ``target`` names in ``obj``'s docstring, or None."""
    if target.startswith("."):
        level = len(target) - len(target.lstrip("."))
        base = _package_of(obj)
        for _ in range(level - 1):
            base = base.parent
        return f"{base.path}.{target.lstrip('.')}" if base is not None else None
    head, _, rest = target.partition(".")
    try:
        found = obj.resolve(head)
    except Exception:  # noqa: BLE001 - Griffe raises several kinds for an unknown name
        return target
    return f"{found}.{rest}" if rest else found


def _canonical(package: griffe.Module, path: str) -> str:
    """``path`` with aliases followed to the object they name (where the reference renders
    it); ``path`` itself outside the package or when Griffe cannot follow it."""
    head, _, inner = path.partition(".")
    if head != package.name or not inner:
        return path
    try:
        found = package[inner]
        return found.final_target.path if found.is_alias else found.path
    except Exception:  # noqa: BLE001 - a member Griffe does not know, or a broken alias
        return path


class SphinxRoles(griffe.Extension):
    """Rewrites the Sphinx roles of every docstring in the package as autorefs links."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        for obj in _walk(pkg):
            docstring = obj.docstring
            if docstring is None or ":" not in docstring.value:
                continue

            def link(match: re.Match, obj: griffe.Object = obj) -> str:
                label, labelled = match.group(1), match.group(3)
                short, target = (
                    (match.group(2), labelled) if labelled else (match.group(4), match.group(5))
                )
                target = target.strip()
                title = target.rsplit(".", 1)[-1] if short else target.lstrip(".")
                if labelled and label.strip():
                    title = label.strip()
                path = _path(obj, target)
                if path is None:
                    return f"<code>{html.escape(title)}</code>"
                identifier = html.escape(_canonical(pkg, path), quote=True)
                return (
                    f'<autoref identifier="{identifier}" optional>'
                    f"<code>{html.escape(title)}</code></autoref>"
                )

            docstring.value = ROLE.sub(link, docstring.value)


def _walk(obj: griffe.Object):
    """``obj`` and every object defined below it (aliases skipped: their target is walked)."""
    yield obj
    for member in obj.members.values():
        if not member.is_alias:
            yield from _walk(member)
