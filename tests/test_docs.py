"""The contracts ship with the repository: docs/spec/ holds the spec pages the docstrings cite."""
import re

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
