"""The snippet runner itself: what it extracts, how it merges fragments, and that a broken
block fails the run (a docs test that cannot fail would prove nothing)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import run_snippets as rs  # noqa: E402

RUNNER = Path(__file__).parent / "run_snippets.py"


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "page.md"
    p.write_text(text)
    return p


def test_extract_languages_lines_and_markers(tmp_path):
    page = write(tmp_path, "# t\n\n<!-- snippet: skip (needs a GPU) -->\n```sh\nexit 1\n```\n\n"
                 "<!-- snippet: run -->\n```yaml\nname: x\n```\n\n```text\nshown\n```\n")
    blocks = rs.extract(page)
    assert [(b.line, b.lang) for b in blocks] == [(4, "sh"), (9, "yaml"), (13, "text")]
    assert blocks[0].markers == {"skip": "(needs a GPU)"}
    assert blocks[1].markers == {"run": ""}
    assert blocks[0].text == "exit 1\n"


def test_untagged_block_and_skip_without_reason_are_refused(tmp_path):
    with pytest.raises(SystemExit, match=r"page.md:1: code block without a language"):
        rs.extract(write(tmp_path, "```\nls\n```\n"))
    with pytest.raises(SystemExit, match=r"needs a reason"):
        rs.extract(write(tmp_path, "<!-- snippet: skip -->\n```sh\nls\n```\n"))
    with pytest.raises(SystemExit, match=r"no such file"):
        rs.extract(write(tmp_path, "<!-- snippet: into pipelines/nope.yaml -->\n```yaml\n[]\n```\n"))


def test_merge_replaces_by_id_and_export_target():
    base = {"name": "p", "stages": [{"id": "a", "use": "x"}, {"id": "b", "use": "y"}],
            "export": [{"from": "a.o", "to": "out/a.csv"}]}
    frag = {"stages": [{"id": "b", "use": "z"}, {"id": "c", "use": "w"}],
            "export": [{"from": "c.o", "to": "out/a.csv"}, {"from": "b.o", "to": "out/b.vti"}]}
    m = rs.merge(base, frag, "here")
    assert [(s["id"], s["use"]) for s in m["stages"]] == [("a", "x"), ("b", "z"), ("c", "w")]
    assert [(e["from"], e["to"]) for e in m["export"]] == [("c.o", "out/a.csv"),
                                                           ("b.o", "out/b.vti")]
    assert base["stages"][1]["use"] == "y"  # the base pipeline is not modified
    assert len(rs.merge(base, [{"id": "d", "use": "v"}], "here")["stages"]) == 3


def test_split_values_keeps_brackets_together():
    assert rs.split_values("8um,4um") == ["8um", "4um"]
    assert rs.split_values("[1um,2um,3um],[4um,5um,6um],{a: 1, b: 2}") == [
        "[1um,2um,3um]", "[4um,5um,6um]", "{a: 1, b: 2}"]


def test_a_failing_block_fails_the_run(tmp_path):
    page = write(tmp_path, "```sh\ntest 2 -eq 2\n```\n\n```python\nassert 1 + 1 == 3\n```\n\n"
                 "<!-- snippet: skip (shown only) -->\n```sh\nexit 1\n```\n")
    env = dict(os.environ, PIPE="/bin/true")
    r = subprocess.run([sys.executable, str(RUNNER), "--scratch", str(tmp_path / "s"), str(page)],
                       capture_output=True, text=True, env=env)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "2 blocks run, 1 failed, 1 skipped" in r.stdout
    assert f"FAIL {page}:5 python" in r.stdout
    assert "AssertionError" in r.stdout
