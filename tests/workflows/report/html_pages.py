"""A report page read with the standard library's HTML parser: its images, links, ids and
tables in document order, and what a reader would find broken in it."""

from __future__ import annotations

from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit


class Page(HTMLParser):
    """Every ``<img>`` (src, alt), ``<a href>``, element id (with its place in the
    document, counted in start tags), heading and table (its rows' cell texts, by the
    table's id) of one page."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.images: list[tuple[str, str | None]] = []
        self.links: list[str] = []
        self.ids: dict[str, int] = {}
        self.tables: dict[str, list[list[str]]] = {}
        self.headings: list[str] = []
        self.tags = 0
        self._table: str | None = None
        self._cell: list[str] | None = None
        self._heading: list[str] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags += 1
        a = dict(attrs)
        if a.get("id"):
            self.ids[a["id"]] = self.tags
        if tag == "img":
            self.images.append((a.get("src") or "", a.get("alt")))
        elif tag == "a" and "href" in a:
            self.links.append(a["href"] or "")
        elif tag == "table":
            self._table = a.get("id") or f"table-{self.tags}"
            self.tables[self._table] = []
        elif tag == "tr" and self._table is not None:
            self.tables[self._table].append([])
        elif tag in ("td", "th") and self._table is not None:
            self._cell = []
        elif tag in ("h1", "h2", "h3"):
            self._heading = []

    def handle_endtag(self, tag: str) -> None:
        if tag in ("td", "th") and self._cell is not None and self._table is not None:
            self.tables[self._table][-1].append(" ".join("".join(self._cell).split()))
            self._cell = None
        elif tag == "table":
            self._table = None
        elif tag in ("h1", "h2", "h3") and self._heading is not None:
            self.headings.append(" ".join("".join(self._heading).split()))
            self._heading = None

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)
        if self._heading is not None:
            self._heading.append(data)


def read_page(path: Path) -> Page:
    page = Page()
    page.feed(Path(path).read_text(encoding="utf-8"))
    page.close()
    return page


def broken(path: Path) -> list[str]:
    """What is broken in the page at ``path``: an image without a file beside it or without
    alt text, a relative link to no file, a fragment link to no id. Links with a scheme
    (https:, mailto:) are not followed."""
    page = read_page(path)
    here = Path(path).parent
    problems = []
    for src, alt in page.images:
        if not (alt or "").strip():
            problems.append(f"image {src!r} has no alt text")
        if not src or not (here / unquote(src)).is_file():
            problems.append(f"image {src!r} is not a file beside the page")
    for href in page.links:
        parts = urlsplit(href)
        if parts.scheme or parts.netloc:
            continue
        if parts.path and not (here / unquote(parts.path)).exists():
            problems.append(f"link {href!r} leads to no file")
        if not parts.path and parts.fragment and parts.fragment not in page.ids:
            problems.append(f"link {href!r} leads to no element")
    return problems
