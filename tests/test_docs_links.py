"""The README stays a front door, and every relative link or image in the documentation
pages (README.md and the pages beside the code) points at a file that exists."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 200
PAGE_FOLDERS = ("dem", "pbm", "coupling", "workflows")

#: [text](target) and ![alt](target); the text may hold backticks and brackets of its own
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(([^()\s]+)(?:\s+\"[^\"]*\")?\)")
_FENCE = re.compile(r"^```.*?^```", flags=re.S | re.M)


def doc_pages(root: Path) -> list[Path]:
    """README.md and every Markdown page under the package folders."""
    pages = [root / "README.md"]
    for folder in PAGE_FOLDERS:
        pages += sorted((root / folder).rglob("*.md"))
    return pages


def relative_targets(text: str) -> list[str]:
    """The relative link and image targets of a Markdown text, fragments stripped; links to
    the web, mail and anchors within the page are left out, and so is fenced code."""
    targets = []
    for target in _LINK.findall(_FENCE.sub("", text)):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, flags=re.I) or target.startswith("#"):
            continue
        targets.append(target.split("#", 1)[0])
    return targets


def broken_links(page: Path, root: Path) -> list[str]:
    """The targets of `page` that resolve to no file or folder inside `root`."""
    broken = []
    for target in relative_targets(page.read_text(encoding="utf-8")):
        resolved = (root / target.lstrip("/")) if target.startswith("/") else (page.parent / target)
        resolved = resolved.resolve()
        if not resolved.exists() or root.resolve() not in (resolved, *resolved.parents):
            broken.append(target)
    return broken


def test_readme_is_a_front_door():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines, more than {README_MAX_LINES}"


@pytest.mark.parametrize("page", doc_pages(ROOT), ids=lambda page: str(page.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    assert broken_links(page, ROOT) == [], f"{page.relative_to(ROOT)} links to missing files"


def test_the_pages_link_to_each_other():
    # the README links every page it moved its findings to, so none is orphaned
    readme_targets = {
        (ROOT / target).resolve() for target in relative_targets((ROOT / "README.md").read_text(encoding="utf-8"))
    }
    pages = [page for page in doc_pages(ROOT)[1:] if page.stem.isupper()]
    orphans = [str(page.relative_to(ROOT)) for page in pages if page.resolve() not in readme_targets]
    assert orphans == []


def test_a_broken_link_or_image_is_found(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "figure.png").write_bytes(b"png")
    page = tmp_path / "docs" / "PAGE.md"
    page.write_text(
        "![ok](figure.png) ![gone](missing.png) [up](../README.md#intro) [web](https://example.org)\n"
        "[anchor](#here) [`code` text](figure.png#x)\n```\n[fenced](nowhere.md)\n```\n"
        "[outside](../../../etc/passwd)\n",
        encoding="utf-8",
    )
    assert broken_links(page, tmp_path) == ["missing.png", "../README.md", "../../../etc/passwd"]
    (tmp_path / "README.md").write_text("# x\n", encoding="utf-8")
    assert broken_links(page, tmp_path) == ["missing.png", "../../../etc/passwd"]
