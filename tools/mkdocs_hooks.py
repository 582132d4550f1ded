"""Hooks of the documentation site (``mkdocs.yml``: ``hooks``).

The changelog lives once, in ``CHANGELOG.md`` at the root of the repository, where its links are
written from the root (``docs/performance.md#studies``). ``docs/changelog.md`` is only a pointer to
it; when the site is built this hook puts the changelog in that page instead, with each link
rewritten to work from the site: ``docs/X`` to ``X``, ``scenes/README.md`` to the scene format page,
``README.md`` and ``docs/`` to the home page, and a link to any other file of the repository (code,
tests) to its bare text, since the site has no such page. A link to a page or anchor that does not
exist stays broken, and the strict build fails on it.
"""
from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
CHANGELOG = REPO / "CHANGELOG.md"
CHANGELOG_PAGE = "changelog.md"
#: repository paths that have a page of their own on the site (besides docs/*)
PAGES = {"README.md": "index.md", "docs/": "index.md", "docs": "index.md", "scenes/README.md": "scenes.md"}

_LINK = re.compile(r"\[([^\]\n]*)\]\(([^)\s]+)\)")
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")


def site_link(text: str, url: str) -> str:
    """The markdown of a link from the repository's root, as a link from the site's top folder."""
    if _SCHEME.match(url) or url.startswith("#"):
        return f"[{text}]({url})"
    path, _, anchor = url.partition("#")
    path = path.removeprefix("./")
    if path in PAGES:
        target, anchor = PAGES[path], ""  # the README's sections are not the home page's
    elif path.startswith("docs/"):
        target = path.removeprefix("docs/")
    else:
        return text  # a file of the repository the site has no page for: the text alone
    return f"[{text}]({target}{'#' + anchor if anchor else ''})"


def rewrite_links(markdown: str) -> str:
    """Every link of ``markdown`` (written from the repository's root) as :func:`site_link` gives it."""
    return _LINK.sub(lambda m: site_link(m.group(1), m.group(2)), markdown)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if page.file.src_uri == CHANGELOG_PAGE:
        return rewrite_links(CHANGELOG.read_text(encoding="utf-8"))
    return markdown
