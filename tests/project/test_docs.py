"""The docs hold together (issue 53): every relative link and ``#anchor`` of ``docs/*.md`` and
README.md resolves (the file exists; the anchor is a heading of that file as GitHub slugs it),
so does every ``docs/<page>.md#<anchor>`` written in the code, the configs, the notebooks and
the tests, and no page of docs/ is over :data:`MAX_PAGE_LINES` lines except the benchmark record.
Two tests feed the checker a page with a dead link and a dead anchor to show it can fail."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from markdown_it import MarkdownIt

from helpers.paths import ROOT

DOCS = ROOT / "docs"

#: A page of docs/ longer than this is split by what users do (issue 53).
MAX_PAGE_LINES = 600
#: The one page allowed longer: the record of measured figures, which only grows.
LONG_PAGES = {"benchmarks.md"}

#: ``docs/<page>.md`` or ``docs/<page>.md#<anchor>`` as plain text in code, configs and notebooks.
DOC_REFERENCE = re.compile(r"docs/([\w.-]+\.md)(?:#([\w-]+))?")
#: Where plain-text references to a doc page are looked for, and the files read there.
REFERENCE_ROOTS = ("src", "conf", "tests", "benchmarks", "notebooks")
REFERENCE_SUFFIXES = {".py", ".yaml", ".yml", ".toml", ".ipynb", ".md", ".txt", ".cfg"}

_MD = MarkdownIt("commonmark")


def slug(heading: str) -> str:
    """GitHub's anchor of a heading's text: lowercase, every character that is not a letter, a
    digit, a space, ``-`` or ``_`` dropped, each space turned into ``-``.

    Written by hand: the well-kept implementation (mdit-py-plugins' anchors plugin) is not
    installed here, and the rule is these two lines (GitHub's html-pipeline TocFilter)."""
    text = heading.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _inline_text(token) -> str:
    """The text a heading shows (code spans and link texts kept, markup dropped)."""
    return "".join(
        child.content for child in token.children or [] if child.type in ("text", "code_inline")
    )


def anchors(text: str) -> set[str]:
    """Every anchor of a Markdown page: its headings' slugs, a repeated slug numbered as GitHub
    numbers it (``-1``, ``-2``), plus explicit ``<a id=...>`` / ``<a name=...>`` targets."""
    found: set[str] = set()
    seen: dict[str, int] = {}
    tokens = _MD.parse(text)
    for i, token in enumerate(tokens):
        if token.type == "heading_open":
            base = slug(_inline_text(tokens[i + 1]))
            count = seen.get(base, 0)
            seen[base] = count + 1
            found.add(base if count == 0 else f"{base}-{count}")
    found.update(re.findall(r"<a\s+(?:id|name)=\"([^\"]+)\"", text))
    return found


def links(text: str) -> list[str]:
    """Every link and image target of a Markdown page (code blocks and code spans skipped)."""
    out = []
    for token in _MD.parse(text):
        for child in token.children or []:
            if child.type == "link_open":
                out.append(child.attrGet("href"))
            elif child.type == "image":
                out.append(child.attrGet("src"))
    return out


def dead_links(page: Path) -> list[str]:
    """``page: target (why)`` for each relative link or anchor of ``page`` that does not resolve."""
    text = page.read_text(encoding="utf-8")
    dead = []
    for target in links(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto:: not ours to check
            continue
        path_part, _, anchor = target.partition("#")
        dest = (page.parent / path_part).resolve() if path_part else page
        if not dest.exists():
            dead.append(f"{page.name}: {target} (no file {path_part})")
            continue
        if (
            anchor
            and dest.suffix == ".md"
            and anchor not in anchors(dest.read_text(encoding="utf-8"))
        ):
            dead.append(f"{page.name}: {target} (no heading #{anchor} in {dest.name})")
    return dead


def dead_references(path: Path, docs: Path = DOCS) -> list[str]:
    """``file: docs/page.md#anchor (why)`` for each plain-text doc reference that does not resolve."""
    dead = []
    name = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
    for match in DOC_REFERENCE.finditer(path.read_text(encoding="utf-8", errors="replace")):
        page, anchor = match.group(1), match.group(2)
        dest = docs / page
        if not dest.is_file():
            dead.append(f"{name}: {match.group(0)} (no file)")
        elif anchor and anchor not in anchors(dest.read_text(encoding="utf-8")):
            dead.append(f"{name}: {match.group(0)} (no heading #{anchor})")
    return dead


#: A repository path written in a page (``tests/resireg/deploy/test_export.py``,
#: ``src/resireg/method/lite.py``, ``conf/map.yaml``): a file that must exist. Placeholders
#: (``conf/encoder/<name>.yaml``), globs and an upstream repository's files (``src/model.py``
#: of OTAS) do not match.
REPO_PATH = re.compile(
    r"(?<![\w/.<-])((?:src/(?:resireg|resireg_train|hydra_plugins)|tests|benchmarks|conf|notebooks)"
    r"/[\w./-]*\w\.(?:py|yaml|md|ipynb|json|txt))"
)


def missing_files(page: Path, root: Path = ROOT) -> list[str]:
    """``page: path`` for each repository path the page names that is no file under ``root``
    (a test or module moved since the page was written)."""
    name = page.relative_to(root) if page.is_relative_to(root) else page
    text = page.read_text(encoding="utf-8")
    return [f"{name}: {m}" for m in sorted(set(REPO_PATH.findall(text)))
            if not (root / m).is_file()]  # fmt: skip


def _pages() -> list[Path]:
    return [*sorted(DOCS.glob("*.md")), ROOT / "README.md"]


@pytest.mark.parametrize("page", _pages(), ids=lambda p: p.name)
def test_every_link_and_anchor_of_the_docs_resolves(page: Path) -> None:
    assert dead_links(page) == []


@pytest.mark.parametrize("page", _pages(), ids=lambda p: p.name)
def test_every_file_a_page_names_exists(page: Path) -> None:
    assert missing_files(page) == []


def test_a_page_naming_a_moved_test_is_found(tmp_path: Path) -> None:
    (tmp_path / "tests" / "resireg" / "deploy").mkdir(parents=True)
    (tmp_path / "tests" / "resireg" / "deploy" / "test_export.py").write_text("")
    page = tmp_path / "page.md"
    page.write_text("Tested (`tests/resireg/deploy/test_export.py`, `tests/test_export.py::t`);\n"
                    "a recipe: `conf/encoder/<name>.yaml`.\n")  # fmt: skip
    assert missing_files(page, tmp_path) == ["page.md: tests/test_export.py"]


def test_every_doc_reference_in_code_and_configs_resolves() -> None:
    dead = []
    for root in REFERENCE_ROOTS:
        for path in sorted((ROOT / root).rglob("*")):
            if (
                path.is_file()
                and path.suffix in REFERENCE_SUFFIXES
                and "__pycache__" not in path.parts
            ):
                if path == Path(__file__).resolve():  # this file's examples of dead references
                    continue
                dead += dead_references(path)
    assert dead == []


def test_no_page_of_docs_is_over_the_limit() -> None:
    long = {
        page.name: n
        for page in DOCS.glob("*.md")
        if (n := len(page.read_text(encoding="utf-8").splitlines())) > MAX_PAGE_LINES
        and page.name not in LONG_PAGES
    }
    assert long == {}


def test_slug_follows_githubs_rule() -> None:
    # anchors the docs linked before the split (written against GitHub's rendering); the last
    # one: GitHub keeps underscores (they are word characters)
    assert slug("Dense encoders (`resireg.models.DenseEncoder`)") == (
        "dense-encoders-resiregmodelsdenseencoder"
    )
    assert slug(
        "Deployment: ONNX and TensorRT, the Hugging Face Hub, one image (`resireg.deploy`)"
    ) == ("deployment-onnx-and-tensorrt-the-hugging-face-hub-one-image-resiregdeploy")
    assert (
        slug("resireg-map on live topics (source=ros2)") == "resireg-map-on-live-topics-sourceros2"
    )
    assert slug("Your robot's recordings (`resireg-map`)") == "your-robots-recordings-resireg-map"
    assert slug("resireg_train's run_record") == "resireg_trains-run_record"


def test_anchors_number_repeated_headings_and_skip_code() -> None:
    text = "# A\n\n## Setup\n\n```bash\n# not a heading\n```\n\n## Setup\n"
    assert anchors(text) == {"a", "setup", "setup-1"}


def test_a_dead_link_and_a_dead_anchor_are_found(tmp_path: Path) -> None:
    (tmp_path / "other.md").write_text("# Other\n\n## Real heading\n", encoding="utf-8")
    page = tmp_path / "page.md"
    page.write_text(
        "# Page\n\n## Here\n\n"
        "[fine](other.md#real-heading), [fine too](#here), [web](https://example.org/x#y)\n"
        "[gone](missing.md), [no anchor](other.md#not-a-heading), [no local](#nowhere)\n"
        "`[in code](missing2.md)`\n",
        encoding="utf-8",
    )
    assert dead_links(page) == [
        "page.md: missing.md (no file missing.md)",
        "page.md: other.md#not-a-heading (no heading #not-a-heading in other.md)",
        "page.md: #nowhere (no heading #nowhere in page.md)",
    ]


def test_a_dead_reference_in_code_is_found(tmp_path: Path) -> None:
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "guide.md").write_text("# Guide\n\n## Resume\n", encoding="utf-8")
    module = tmp_path / "mod.py"
    module.write_text(
        '"""See docs/guide.md#resume, docs/guide.md#gone and docs/nothing.md."""\n',
        encoding="utf-8",
    )
    assert dead_references(module, docs) == [
        f"{module}: docs/guide.md#gone (no heading #gone)",
        f"{module}: docs/nothing.md (no file)",
    ]
