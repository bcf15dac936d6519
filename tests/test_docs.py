"""Every ```python block of README.md and docs/*.md runs as pasted, each in a fresh namespace.

A block that cannot end by itself (a server that runs until Ctrl-C) is fenced ```python no-run."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FENCE = re.compile(r"^```python([^\n]*)\n(.*?)^```", re.S | re.M)


def _blocks():
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = path.read_text()
        for match in FENCE.finditer(text):
            if "no-run" in match.group(1):
                continue
            line = text.count("\n", 0, match.start()) + 1
            yield pytest.param(match.group(2), id=f"{path.relative_to(ROOT)}:{line}")


def test_there_are_blocks_to_run():
    assert len(list(_blocks())) >= 8


@pytest.mark.parametrize("code", list(_blocks()))
def test_block_runs(code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # anything a block writes lands in a scratch folder
    exec(compile(code, "<doc block>", "exec"), {"__name__": "__doc_block__"})
