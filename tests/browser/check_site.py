"""The built documentation site, looked at in a real browser: headless Chromium (Debian's
``chromium`` package) renders pages at 1400 × 900 px, as a reader's screen shows them, and this
script fails on what a reader would see broken. CI runs it after ``mkdocs build`` (pytest does
not collect this file: it needs a built site and a browser):

    python tests/browser/check_site.py .ci-site              # the pages below
    python tests/browser/check_site.py .ci-site --self-test  # and each fault, inflicted, is caught

On each page it fails on:

- an image that did not load (a missing or unreadable file);
- a Sphinx role shown as text (``:class:`X```, or a labelled ``:meth:`title <target>```, which
  Markdown renders as the role's name before a code span) instead of a link (this one on every
  page of the site, in its HTML);
- a list item shown as a paragraph that starts a line with ``- ``: a list broken by a block
  indented too little (also on every page, in its HTML);
- a name in code font in a table's first column broken over two lines (a config group cut
  mid-word);
- a table wider than the page's content that does not scroll inside its box with a visible cue
  (the edge shadows of ``docs/stylesheets/extra.css``);
- on the pages readers copy commands from, a code line cut off at the box's edge.

``--self-test`` then copies the site, breaks one thing at a time on a copy of the quick start
(an image's file removed, a raw role in the text, the stylesheet that draws the cue dropped with
a wide table added, a long command line, a name in a table's first column squeezed with the
stylesheet dropped) and checks that each fault, and only it, is reported; and that the scans of
the HTML find a labelled role and a broken list.
Exit status 0: every page is clean (and every fault was caught); 1 otherwise.
"""

from __future__ import annotations

import argparse
import html
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

WINDOW = "1400,900"
# (page, whether its code lines must fit their box): the home page, a guide, a results page,
# API pages and the pages whose commands readers copy.
PAGES = (
    ("index.html", True),
    ("get-started/quickstart/index.html", True),
    ("get-started/python/index.html", True),
    ("guides/evaluation/index.html", False),
    ("guides/configuration/index.html", False),
    ("guides/loss/index.html", False),
    ("results/fusion-weather/index.html", False),
    ("results/speed/index.html", False),
    ("reference/models/index.html", False),
    ("reference/runner/index.html", False),
)
BROWSERS = ("chromium", "chromium-browser", "google-chrome")
# Runs once the page and Material's scripts have loaded: what a reader would see broken, as JSON
# in an attribute of <html> that --dump-dom then shows.
_PROBE = """
<script>
window.addEventListener("load", () => setTimeout(() => {
  const found = [];
  const article = document.querySelector("article.md-content__inner") || document.body;
  const box = article.getBoundingClientRect();
  // Material's table wrapper reaches into the article's side margins: the column it may fill.
  const column = (article.parentElement || article).getBoundingClientRect();
  for (const img of document.querySelectorAll("article img")) {
    if (!(img.complete && img.naturalWidth > 0)) {
      found.push("image not loaded: " + img.getAttribute("src"));
    }
  }
  const role = article.innerText.match(
    /:(?:py:)?(?:class|func|data|meth|mod|attr|exc|obj|const):(?:`[^`]*`|[~.]?[A-Za-z_][\\w.]*)/);
  if (role) found.push("raw Sphinx role in the text: " + role[0]);
  for (const code of article.querySelectorAll("table td:first-child code")) {
    if (code.getClientRects().length > 1) {
      found.push("name broken over lines in a table's first column: " + code.innerText);
    }
  }
  article.querySelectorAll("table").forEach((table, i) => {
    const width = table.getBoundingClientRect().width;
    if (width <= box.width + 1) return;
    const head = (table.querySelector("th") || table).innerText.trim().slice(0, 30);
    const wrap = table.closest(".md-typeset__scrollwrap");
    const style = wrap && getComputedStyle(wrap);
    const scrolls = style && ["auto", "scroll"].includes(style.overflowX)
      && wrap.getBoundingClientRect().right <= column.right + 1;
    const cue = style && style.backgroundImage.includes("gradient");
    if (!scrolls || !cue) {
      const sizes = `${Math.round(width)} px wide in ${Math.round(box.width)} px of content`;
      found.push(`table ${i + 1} ("${head}") is ${sizes} `
        + (scrolls ? "and scrolls with no cue" : "and does not scroll in its box"));
    }
  });
  if (document.documentElement.dataset.codeMustFit === "yes") {
    for (const code of article.querySelectorAll("pre > code")) {
      if (code.scrollWidth > code.clientWidth + 1) {
        const lines = code.innerText.split("\\n");
        const line = lines.reduce((a, b) => (b.length > a.length ? b : a), "");
        found.push("code line cut off at the box's edge: " + line.trim().slice(0, 60));
      }
    }
  }
  document.documentElement.setAttribute("data-site-check", JSON.stringify(found));
}, 300));
</script>
"""
_RESULT = re.compile(r'data-site-check="([^"]*)"')
# A role as text: with its backquotes, or (a labelled role, :meth:`title <target>`) its name
# right before the code span Markdown made of the rest.
_ROLE = re.compile(r":(?:py:)?(?:class|func|data|meth|mod|attr|exc|obj|const):`[^`]*`")
_ROLE_BEFORE_CODE = re.compile(r":(?:py:)?(?:class|func|data|meth|mod|attr|exc|obj|const):<code>")
_TAG = re.compile(r"<script.*?</script>|<style.*?</style>|<[^>]+>", re.S)
_PARAGRAPH = re.compile(r"<p>(.*?)</p>", re.S)
# A line of a paragraph that starts like a list item: "- ", "* ", "+ ".
_LIST_LINE = re.compile(r"(?:^|\n)[ \t]*[-*+] \S")


def browser() -> str:
    """The path of a Chromium to run, or exit naming the package to install."""
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    sys.exit("check_site: no Chromium found; install Debian's package: apt-get install chromium")


def look(page: Path, code_must_fit: bool, chromium: str) -> list[str]:
    """What is broken on ``page`` (a built HTML file) as Chromium renders it. The page is
    probed through a copy beside it (the same relative links), removed afterwards."""
    text = page.read_text(encoding="utf-8")
    flag = ' data-code-must-fit="yes"' if code_must_fit else ""
    text = re.sub(r"<html([^>]*)>", lambda m: f"<html{m.group(1)}{flag}>", text, count=1)
    probe = page.with_name(f".probe-{os.getpid()}-{page.name}")
    probe.write_text(text.replace("</body>", _PROBE + "</body>", 1), encoding="utf-8")
    command = [
        chromium,
        "--headless",
        "--no-sandbox",  # CI runs as root, where Chromium's sandbox refuses to start
        "--disable-gpu",
        "--hide-scrollbars",
        f"--window-size={WINDOW}",
        "--virtual-time-budget=15000",
        "--dump-dom",
        probe.as_uri(),
    ]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    finally:
        probe.unlink(missing_ok=True)
    match = _RESULT.search(done.stdout)
    if match is None:
        return [f"the page did not render (Chromium exit {done.returncode}: {done.stderr[-300:]})"]
    return json.loads(html.unescape(match.group(1)))


def raw_roles(site: Path) -> list[str]:
    """Every page of ``site`` whose text (tags stripped) shows a Sphinx role, with the first."""
    found = []
    for page in sorted(site.rglob("*.html")):
        source = page.read_text(encoding="utf-8")
        text = html.unescape(_TAG.sub(" ", source))
        role = _ROLE.search(text) or _ROLE_BEFORE_CODE.search(source)
        if role:
            found.append(f"{page.relative_to(site)}: raw Sphinx role in the text: {role[0]}")
    return found


def broken_lists(site: Path) -> list[str]:
    """Every page of ``site`` with a paragraph holding a line that starts like a list item
    (``- ``): a list that a block indented too little (a fenced block inside a list item needs
    the item's four spaces) ended, leaving the next item as text."""
    found = []
    for page in sorted(site.rglob("*.html")):
        for paragraph in _PARAGRAPH.finditer(page.read_text(encoding="utf-8")):
            if _LIST_LINE.search(paragraph.group(1)):
                text = html.unescape(_TAG.sub("", paragraph.group(1)))[:60]
                found.append(f"{page.relative_to(site)}: a list item shown as text: {text!r}")
                break
    return found


def check(site: Path, chromium: str) -> int:
    """Each of :data:`PAGES` of ``site`` in the browser, and every page's text for raw roles;
    prints what is broken. Returns how many faults."""
    static = raw_roles(site) + broken_lists(site)
    for fault in static:
        print(fault)
    faults = len(static)
    for name, code_must_fit in PAGES:
        page = site / name
        if not page.is_file():
            print(f"{name}: not in the site")
            faults += 1
            continue
        found = look(page, code_must_fit, chromium)
        for fault in found:
            print(f"{name}: {fault}")
        faults += len(found)
        if not found:
            print(f"{name}: ok")
    return faults


def _quickstart_faults(page: Path) -> dict[str, tuple[str, str]]:
    """Faults to inflict on the quick start: name → (what to change the page's text with, what
    the report must say)."""
    text = page.read_text(encoding="utf-8")
    image = re.search(r'<img[^>]* src="([^"]+)"', text)
    assert image, f"{page}: the quick start shows no picture to break"
    wide = "<table><tr>" + "".join(f"<th>column {i}</th>" for i in range(30)) + "</tr></table>"
    long_line = "python -m fusion_depth.train " + " ".join(f"key{i}=value{i}" for i in range(30))
    # A group name in a first column that the text of the second squeezes (as the
    # configuration guide's table did before its stylesheet kept such names whole).
    words = " ".join(["a long description that takes the width"] * 12)
    squeezed = (
        '<div class="md-typeset__table"><table><tr><th>group</th><th>notes</th></tr>'
        f"<tr><td><code>hydra/launcher_of_the_cluster</code></td><td>{words}</td></tr>"
        "</table></div>"
    )
    return {
        "missing image": (
            text.replace(image.group(1), "no-such-picture.png"),
            "image not loaded: no-such-picture.png",
        ),
        "raw role": (
            text.replace("</h1>", "</h1><p>See :class:`DepthModel` for more.</p>", 1),
            "raw Sphinx role in the text: :class:`DepthModel`",
        ),
        "table without cue": (
            re.sub(r'<link[^>]*href="[^"]*extra\.css"[^>]*>', "", text).replace(
                "</h1>", "</h1>" + wide, 1
            ),
            "and scrolls with no cue",
        ),
        "cut code": (
            text.replace("<pre>", f"<pre><code>{long_line}</code></pre><pre>", 1),
            "code line cut off at the box's edge",
        ),
        "broken name": (
            re.sub(r'<link[^>]*href="[^"]*extra\.css"[^>]*>', "", text).replace(
                "</h1>", "</h1>" + squeezed, 1
            ),
            "name broken over lines in a table's first column",
        ),
    }


def self_test(site: Path, chromium: str) -> int:
    """Inflict each fault on a copy of the quick start; returns how many went unreported (or
    were reported wrongly)."""
    missed = 0
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "site"
        shutil.copytree(site, copy)
        page = copy / "get-started/quickstart/index.html"
        for name, (text, expected) in _quickstart_faults(page).items():
            broken = page.with_name("broken.html")
            broken.write_text(text, encoding="utf-8")
            found = look(broken, True, chromium)
            caught = len(found) == 1 and expected in found[0]
            print(f"self-test, {name}: {'caught' if caught else 'MISSED'} ({found})")
            missed += not caught
        # The scans of the HTML: a labelled role as Markdown renders it, and a broken list.
        scans = {
            "labelled role": (
                "<p>returns (:meth:<code>RunRecord.to_json &lt;x.RunRecord.to_json&gt;</code>)</p>",
                raw_roles,
            ),
            "broken list": (
                "<p>(the others);\n- <strong>the second item</strong></p>",
                broken_lists,
            ),
        }
        for name, (paragraph, scan) in scans.items():
            page.write_text(
                page.read_text(encoding="utf-8").replace("</h1>", "</h1>" + paragraph, 1),
                encoding="utf-8",
            )
            found = [f for f in scan(copy) if f.startswith("get-started/quickstart/")]
            caught = len(found) == 1
            print(f"self-test, {name}: {'caught' if caught else 'MISSED'} ({found})")
            missed += not caught
    return missed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("site", type=Path, help="the built site (mkdocs build --site-dir ...)")
    parser.add_argument(
        "--self-test", action="store_true", help="also check that each fault is caught"
    )
    args = parser.parse_args(argv)
    chromium = browser()
    site = args.site.resolve()  # Chromium opens file:// URIs, which must be absolute
    faults = check(site, chromium)
    if args.self_test:
        faults += self_test(site, chromium)
    print(f"check_site: {'ok' if faults == 0 else f'{faults} problem(s)'}")
    return 0 if faults == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
