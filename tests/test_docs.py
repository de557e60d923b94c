"""Citations point into this repository's docs/ (issue 28, item 6).

Whoever clones robotd has only the repository, so every document a docstring, comment, config
file or page cites must be in it:

- no citation of the design notes that used to live outside the repository (the three names are
  built below, so that this file does not cite them itself);
- every ``docs/….md`` path that is cited exists, and so does every relative ``.md`` link between
  the pages of docs/;
- a cited section exists in the cited page: ``docs/math.md §6.3`` (a numbered heading "6.3 …"),
  ``docs/slam.md "Weights and pose estimate"`` (a heading that starts with the quoted words) and
  ``docs/math.md#62-2d-odometry-increment-model`` (a GitHub heading anchor);
- a bare ``§6.3`` in a Python or TOML file (one that follows no page name, thesis or paper) means
  the section of docs/math.md, as that page's introduction says: the section exists, and the file
  names docs/math.md somewhere, so a reader knows which page.
"""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"

# directories that are not the project's text: VCS, virtual environments, caches, build output
SKIP_DIR_NAMES = {"__pycache__", "node_modules", "build", "dist"}
TEXT_SUFFIXES = {".py", ".md", ".toml", ".json5", ".json", ".yaml", ".yml", ".service", ".rules", ".txt", ".cfg", ".sh"}
TEXT_NAMES = {"Makefile"}

# the three design notes that lived beside the repository, never in it
OUTSIDE_NOTES = tuple(stem + ".md" for stem in ("algo" + "rithms", "de" + "sign", "inter" + "faces"))
OUTSIDE_NOTE_RE = re.compile(
    r"(?P<prefix>[\w./-]*?)\b(?P<name>" + "|".join(re.escape(n) for n in OUTSIDE_NOTES) + r")\b"
)

# a citation of a page of docs/: the path, then an optional #anchor, § numbers or a quoted heading
SECTION_NUMBER = r"§\s?\d+(?:\.\d+)*"
DOC_CITE_RE = re.compile(
    r"(?<![\w/.-])docs/(?P<path>[\w/-]+\.md)"
    r"(?:#(?P<anchor>[\w-]+))?"
    r"(?P<sections>\s*" + SECTION_NUMBER + r"(?:\s*(?:–|-|,|/|and)\s*" + SECTION_NUMBER + r")*)?"
    r"(?:\s+\"(?P<heading>[^\"\n]+)\")?"
)
NUMBER_RE = re.compile(r"§\s?(\d+(?:\.\d+)*)")
# a relative link between pages of docs/: [text](page.md) or [text](page.md#anchor)
MD_LINK_RE = re.compile(r"\]\((?P<path>[\w./-]+\.md)(?:#(?P<anchor>[\w-]+))?\)")
# a § right after a page name, the thesis or a paper is theirs; so is one that continues such a list
QUALIFIER_RE = re.compile(r"(?:\.md(?:#[\w-]+)?|[Tt]hesis|Bay|et al\.(?: \(?\d{4}\)?)?|ch\.)\s*$")
LIST_SEPARATOR_RE = re.compile(r"^\s*(?:–|-|,|/|and|or)\s*$")


def _text_files() -> list[Path]:
    out: list[Path] = []
    for path in sorted(REPO.rglob("*")):
        rel = path.relative_to(REPO)
        if any(part.startswith(".") or part in SKIP_DIR_NAMES or part.endswith(".egg-info") for part in rel.parts[:-1]):
            continue
        if not path.is_file() or not (path.suffix in TEXT_SUFFIXES or path.name in TEXT_NAMES):
            continue
        out.append(path)
    return out


@cache
def _read(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        return ""


def _heading_lines(text: str) -> list[str]:
    lines, fenced = [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        elif not fenced and re.match(r"#{1,6}\s", line):
            lines.append(line.lstrip("#").strip())
    return lines


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    s = heading.strip().lower()
    s = re.sub(r"[^\w\- ]", "", s)
    return s.replace(" ", "-")


@cache
def _page(path: Path) -> tuple[frozenset[str], frozenset[str], tuple[str, ...]]:
    """(section numbers, anchors, heading texts in lower case without backticks) of a page."""
    headings = _heading_lines(_read(path))
    numbers = set()
    for h in headings:
        m = re.match(r"(\d+(?:\.\d+)*)\.?\s", h)
        if m:
            numbers.add(m.group(1))
    anchors = {_slug(h) for h in headings}
    texts = tuple(h.replace("`", "").lower() for h in headings)
    return frozenset(numbers), frozenset(anchors), texts


def _where(path: Path, text: str, pos: int) -> str:
    return f"{path.relative_to(REPO)}:{text.count(chr(10), 0, pos) + 1}"


def _is_url(text: str, start: int) -> bool:
    line_start = text.rfind("\n", 0, start) + 1
    token = re.split(r"[\s(<\"'`]", text[line_start:start])[-1]
    return "://" in token or token.startswith(("www.", "github.com"))


def _bare_sections(line: str) -> list[str]:
    """The section numbers of the bare § citations of one line (docs/math.md's)."""
    out, qualified, end = [], False, 0
    for m in NUMBER_RE.finditer(line):
        qualified = bool(QUALIFIER_RE.search(line[: m.start()])) or (
            qualified and bool(LIST_SEPARATOR_RE.match(line[end : m.start()]))
        )
        end = m.end()
        if not qualified:
            out.append(m.group(1))
    return out


def _check_section_refs(page: Path, anchor: str | None, sections: str | None, heading: str | None) -> list[str]:
    numbers, anchors, texts = _page(page)
    problems = []
    if anchor and anchor not in anchors:
        problems.append(f"#{anchor}: no such heading anchor")
    for number in NUMBER_RE.findall(sections or ""):
        if number not in numbers:
            problems.append(f"§{number}: no heading numbered {number}")
    if heading:
        want = heading.replace("`", "").lower()
        if not any(t.startswith(want) for t in texts):
            problems.append(f'"{heading}": no heading starting with these words')
    return problems


FILES = _text_files()


def test_the_walk_sees_the_sources_and_the_docs() -> None:
    names = {p.relative_to(REPO).as_posix() for p in FILES}
    assert {"robotd/pipeline/step.py", "docs/math.md", "docs/interfaces.md", "README.md"} <= names


def test_no_citation_of_notes_outside_the_repository() -> None:
    bad = []
    for path in FILES:
        text = _read(path)
        for m in OUTSIDE_NOTE_RE.finditer(text):
            if _is_url(text, m.start()):
                continue  # an upstream project's page, not a citation of ours
            prefix, name = m.group("prefix"), m.group("name")
            if prefix.startswith("docs/"):
                target = REPO / prefix / name
            elif path.is_relative_to(DOCS) and prefix in ("", "./"):
                target = path.parent / name
            else:
                target = None
            if target is None or not target.is_file():
                bad.append(f"{_where(path, text, m.start())}: {prefix}{name}")
        for m in re.finditer(r"shared/" + "docs", text):
            bad.append(f"{_where(path, text, m.start())}: {m.group()}")
    assert not bad, "citations of documents that are not in the repository's docs/:\n" + "\n".join(bad)


def test_cited_docs_pages_and_sections_exist() -> None:
    bad = []
    for path in FILES:
        text = _read(path)
        for m in DOC_CITE_RE.finditer(text):
            page = DOCS / m.group("path")
            where = f"{_where(path, text, m.start())}: docs/{m.group('path')}"
            if not page.is_file():
                bad.append(f"{where}: no such file")
                continue
            bad += [
                f"{where} {p}"
                for p in _check_section_refs(page, m.group("anchor"), m.group("sections"), m.group("heading"))
            ]
    assert not bad, "citations of docs/ that do not resolve:\n" + "\n".join(bad)


def test_links_between_docs_pages_resolve() -> None:
    bad = []
    for path in FILES:
        if path.suffix != ".md":
            continue
        text = _read(path)
        for m in MD_LINK_RE.finditer(text):
            if _is_url(text, m.start("path")):
                continue
            page = (path.parent / m.group("path")).resolve()
            where = f"{_where(path, text, m.start())}: {m.group('path')}"
            if not page.is_file():
                bad.append(f"{where}: no such file")
            elif m.group("anchor") and m.group("anchor") not in _page(page)[1]:
                bad.append(f"{where}: no heading anchor #{m.group('anchor')}")
    assert not bad, "links between docs pages that do not resolve:\n" + "\n".join(bad)


@pytest.mark.parametrize("suffix", [".py", ".toml"])
def test_bare_section_numbers_name_their_page_and_exist(suffix: str) -> None:
    numbers = _page(DOCS / "math.md")[0]
    unnamed, missing = [], []
    for path in FILES:
        if path.suffix != suffix or path == Path(__file__).resolve():
            continue  # (this file's own examples of bad citations are not citations)
        text = _read(path)
        for line_no, line in enumerate(text.splitlines(), 1):
            for number in _bare_sections(line):
                where = f"{path.relative_to(REPO)}:{line_no}: {line.strip()}"
                if "docs/math.md" not in text:
                    unnamed.append(where)
                if number not in numbers:
                    missing.append(f"{where} (§{number})")
    assert not unnamed, "a bare § number in a file that never names docs/math.md (cite it once):\n" + "\n".join(unnamed)
    assert not missing, "a bare § number that is no section of docs/math.md:\n" + "\n".join(missing)


def test_the_checks_catch_what_they_are_for() -> None:
    # the patterns themselves: a broken citation must not slip through a regex that never matches
    text = 'see docs/math.md §6.3 and docs/slam.md "Weights and pose estimate"; docs/math.md#1-conventions-and-frames'
    found = [
        (m.group("path"), m.group("anchor"), m.group("sections"), m.group("heading"))
        for m in DOC_CITE_RE.finditer(text)
    ]
    assert found == [
        ("math.md", None, " §6.3", None),
        ("slam.md", None, None, "Weights and pose estimate"),
        ("math.md", "1-conventions-and-frames", None, None),
    ]
    assert _check_section_refs(DOCS / "math.md", None, " §6.3–§6.99", None) == ["§6.99: no heading numbered 6.99"]
    assert _check_section_refs(DOCS / "slam.md", None, None, "No such heading")
    assert _check_section_refs(DOCS / "math.md", "no-such-anchor", None, None)
    assert [m.group("name") for m in OUTSIDE_NOTE_RE.finditer("(" + OUTSIDE_NOTES[0] + " §2.1)")] == [OUTSIDE_NOTES[0]]
    assert _is_url("see https://github.com/ros2/rmw_zenoh/blob/rolling/docs/x.md", 50)
    line = "thesis §3.1.2 and §3.2.1; docs/math.md §2, §3 (§5.1) and §6; Thrun et al. 2005 §10.3.3, Bay et al. §3.1"
    assert _bare_sections(line) == ["5.1", "6"]
