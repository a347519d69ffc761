"""Every Python block of README.md and docs/*.md runs, in order, as a reader would run it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def python_blocks(text: str) -> list[str]:
    """The code of every fenced ```python block of a Markdown text, in order."""
    return BLOCK.findall(text)


def test_blocks_are_found():
    text = "intro\n```python\nx = 1\n```\n```bash\nls\n```\n```python\ny = x\n```\n"
    assert python_blocks(text) == ["x = 1\n", "y = x\n"]
    assert python_blocks((ROOT / "README.md").read_text()), "the README shows no Python"


def test_links_to_docs_exist():
    for document in DOCUMENTS:
        for target in re.findall(r"\]\(([^)#:]+)\)", document.read_text()):
            assert (document.parent / target).exists(), f"{document.name} links to missing {target}"


@pytest.mark.parametrize("document", DOCUMENTS, ids=[d.name for d in DOCUMENTS])
def test_python_blocks_run(document, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # snippets that write files write them here
    namespace: dict = {"__name__": "__main__"}
    for number, code in enumerate(python_blocks(document.read_text()), 1):
        try:
            exec(compile(code, f"{document.name}, Python block {number}", "exec"), namespace)
        except Exception as e:
            raise AssertionError(f"{document.name}, Python block {number} raised "
                                 f"{type(e).__name__}: {e}\n{code}") from e
