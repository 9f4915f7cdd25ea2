"""The documentation: docs/spec/ holds the contracts the docstrings cite; the README is for users (at most 300
lines, every file it names present, its table generated from docs/*.json); no issue numbers, branch names or
rounds of the team's work in the prose, the code or the tests."""
import importlib.util
import json
import re
from pathlib import Path

import pytest

from conftest import ROOT, SHARED

COPY = ROOT / "docs" / "spec"
ORIGINAL = SHARED.parent / "spec"


def test_every_cited_spec_page_is_in_docs_spec():
    cited = {m for p in (ROOT / "dfxcorr").rglob("*.py") for m in re.findall(r"spec/([\w-]+\.md)", p.read_text())}
    assert cited, "no docstring cites a spec page: the pattern is stale"
    missing = sorted(name for name in cited if not (COPY / name).is_file())
    assert not missing, missing


def test_docs_spec_is_a_copy_of_the_shared_spec():
    if not ORIGINAL.is_dir():
        pytest.skip(f"{ORIGINAL} is absent")
    originals = sorted(p.name for p in ORIGINAL.glob("*.md"))
    assert sorted(p.name for p in COPY.glob("*.md")) == originals
    for name in originals:
        assert (COPY / name).read_bytes() == (ORIGINAL / name).read_bytes(), name


# --- The README is for users; the measurements and the history live elsewhere --------------------------------------

README = ROOT / "README.md"
#: Issue numbers, branch names and rounds of the team's work: none in what users and reviewers read.
HISTORY = re.compile(r"\bissues? #?\d+\b|\bh-[a-z]+\b|\bround (?:one|two|three|four|five)\b", re.IGNORECASE)
#: Code whose comments, docstrings and help texts are held to that: every module of the package.
CODE = (sorted((ROOT / "dfxcorr").rglob("*.py")) + sorted((ROOT / "scripts").glob("*.py"))
        + sorted((ROOT / "scripts").glob("*.sh")))
PROSE = [README, ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md")),
         *sorted((ROOT / "configs").glob("*.yaml"))]
#: Tests, but this file: its own examples name what the pattern must catch.
TESTS = sorted(p for p in (ROOT / "tests").rglob("*.py") if p.name != Path(__file__).name)


def _docs_pages():
    """scripts/docs_pages.py as a module (a script, not a package)."""
    spec = importlib.util.spec_from_file_location("docs_pages", ROOT / "scripts" / "docs_pages.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_readme_is_at_most_300_lines():
    assert len(README.read_text().splitlines()) <= 300


@pytest.mark.parametrize("path", PROSE + CODE + TESTS,
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_no_issue_numbers_branch_names_or_rounds(path):
    found = [(n, m.group()) for n, line in enumerate(path.read_text().splitlines(), 1)
             for m in HISTORY.finditer(line)]
    assert not found, found


def test_the_history_pattern_catches_what_it_is_for():
    for text in ("Issue 20's targets", "as in issue 9", "branch h-speed", "merge of h-diag", "round three"):
        assert HISTORY.search(text), text
    for text in ("a high-resolution scan", "the issue of a scatter field", "round 0", "pixel-wise"):
        assert not HISTORY.search(text), text


def test_every_file_the_readme_names_exists():
    text = README.read_text()
    paths = set(re.findall(r"\b((?:scripts|dfxcorr|tests|configs|docs)/[\w./-]*\w\.(?:py|sh|md|yaml|json|png))\b",
                           text))
    scripts = set(re.findall(r"`([\w-]+\.(?:py|sh))\b", text))
    assert scripts, "no script named in the README's table: the pattern is stale"
    missing = sorted(p for p in paths if not (ROOT / p).is_file())
    missing += sorted(s for s in scripts if not (ROOT / "scripts" / s).is_file())
    assert not missing, missing


def test_measurement_pages_are_in_step_with_the_json():
    """docs/measurements.md and the README's table are what scripts/docs_pages.py writes from docs/*.json."""
    pages = _docs_pages()
    docs = ROOT / "docs"
    assert (docs / pages.PAGE).read_text() == pages.measurements(docs), "run scripts/docs_pages.py"
    assert pages.with_readme_table(README.read_text(), docs) == README.read_text(), "run scripts/docs_pages.py"


def test_readme_table_numbers_come_from_the_json(tmp_path):
    """A number changed in the JSON changes the README's table: nothing in it is typed by hand."""
    pages = _docs_pages()
    for p in (ROOT / "docs").glob("*.json"):
        (tmp_path / p.name).write_text(p.read_text())
    bench = json.loads((tmp_path / "benchmark.json").read_text())
    bench["clinical"]["cases"]["full"]["seconds"] = 12345.6
    (tmp_path / "benchmark.json").write_text(json.dumps(bench))
    assert "12345.6 s" in pages.readme_table(tmp_path) and "12345.6 s" not in pages.readme_table(ROOT / "docs")
