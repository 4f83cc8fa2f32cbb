"""Benchmark tables the docs state are the benchmarks' output: every `<!-- bench:NAME -->` block
in README.md and docs/*.md is bench/results/NAME.md byte for byte (a figure edited by hand in
either fails), every results file is shown somewhere, and bench/publish.py really rewrites the
blocks (bench/publish.py says how a bench publishes)."""
from __future__ import annotations

import re
import shutil
import sys

import pytest
from conftest import ROOT

sys.path.insert(0, str(ROOT / "bench"))
import publish as P  # noqa: E402

RESULTS = ROOT / "bench" / "results"


def _doc_blocks() -> list[tuple[str, str, str]]:
    """(document, name, content) of every block."""
    out = []
    for doc in P.doc_files():
        for name, contents in P.blocks(doc.read_text()).items():
            out += [(str(doc.relative_to(ROOT)), name, c) for c in contents]
    return out


def test_every_marker_opens_and_closes_a_whole_block():
    for doc in P.doc_files():
        text = doc.read_text()
        opens = re.findall(r"^<!-- bench:(\S+) -->$", text, re.M)
        closes = re.findall(r"^<!-- /bench:(\S+) -->$", text, re.M)
        whole = [n for n, cs in P.blocks(text).items() for _ in cs]
        assert sorted(opens) == sorted(closes) == sorted(whole), (
            f"{doc.relative_to(ROOT)}: bench markers unbalanced (open {opens}, close {closes})")
        stray = [ln for ln in text.splitlines() if re.match(r"\s*<!--\s*/?\s*bench", ln)
                 and not re.fullmatch(r"<!-- /?bench:\S+ -->", ln)]
        assert not stray, f"{doc.relative_to(ROOT)}: bench markers not in the form <!-- bench:NAME -->: {stray}"


def test_every_block_is_its_results_file_byte_for_byte():
    found = _doc_blocks()
    assert len({n for _, n, _ in found}) >= 10, "the benchmark tables lost their markers"
    for doc, name, content in found:
        f = RESULTS / f"{name}.md"
        assert f.exists(), f"{doc} has a bench:{name} block but bench/results/{name}.md does not exist"
        assert content == f.read_text(), (
            f"{doc}'s bench:{name} block differs from bench/results/{name}.md: a figure edited by hand? "
            f"Run the bench (it publishes), or copy the file into the block")


def test_every_results_file_is_shown_and_says_where_it_came_from():
    shown = {n for _, n, _ in _doc_blocks()}
    files = sorted(RESULTS.glob("*.md"))
    assert files
    for f in files:
        assert f.stem in shown, f"bench/results/{f.name} is in no <!-- bench:{f.stem} --> block of README.md or docs/"
        first, blank, *table = f.read_text().split("\n")
        bench = f.stem.split("-")[0]
        assert (ROOT / "bench" / f"{bench}.py").exists(), f"bench/results/{f.name}: no bench/{bench}.py"
        assert f"bench/{bench}.py" in first and re.search(r"\d{4}-\d\d-\d\d", first), (
            f"bench/results/{f.name}: the first line must give the date and the command")
        assert blank == "" and table[0].startswith("|") and re.match(r"^\|[-:| ]+\|$", table[1]), (
            f"bench/results/{f.name}: a header line, a blank line, then the table")


@pytest.fixture()
def tree(tmp_path):
    """A copy of the documents with their blocks, to publish into."""
    (tmp_path / "docs").mkdir()
    for doc in P.doc_files():
        dst = tmp_path / doc.relative_to(ROOT)
        shutil.copy(doc, dst)
    shutil.copytree(RESULTS, tmp_path / "bench" / "results")
    return tmp_path


def test_publish_rewrites_every_block_and_the_results_file(tree):
    table = "| case | time |\n|---|---|\n| 26 poses × 2000 samples (target < 50 ms) | 99 ms |\n"
    before_fw = (tree / "docs" / "firmware.md").read_text()
    out = P.publish("calib_solve", table, {"repeat": 7}, root=tree, command="python bench/calib_solve.py")
    assert out == tree / "bench" / "results" / "calib_solve.md"
    text = out.read_text()
    assert text.endswith("\n\n" + table) and text.startswith("Measured ")
    assert "`python bench/calib_solve.py`" in text and "repeat 7" in text and "CPUs" in text
    readme = (tree / "README.md").read_text()
    assert P.blocks(readme)["calib_solve"] == [text]
    assert "| 11 ms |" not in readme.split("<!-- /bench:calib_solve -->")[0].split("<!-- bench:calib_solve -->")[1]
    # the rest of the file is untouched
    orig = (ROOT / "README.md").read_text()
    assert readme.replace(text, "") == orig.replace(P.blocks(orig)["calib_solve"][0], "")
    assert (tree / "docs" / "firmware.md").read_text() == before_fw

    # a block in two documents gets the table in both
    P.publish("arm_cycles", "| a |\n|---|\n| 1 |\n", root=tree, command="python bench/arm_cycles.py")
    new = (tree / "bench" / "results" / "arm_cycles.md").read_text()
    assert P.blocks((tree / "README.md").read_text())["arm_cycles"] == [new]
    assert P.blocks((tree / "docs" / "firmware.md").read_text())["arm_cycles"] == [new]


def test_publish_refuses_what_it_cannot_do_and_writes_nothing(tree):
    readme = tree / "README.md"
    before = readme.read_text()
    assert P.publish("calib_solve", "| x |\n|---|\n", root=tree, enabled=False) is None
    assert readme.read_text() == before
    with pytest.raises(SystemExit, match=r"^bench/publish.py: error: not published: no <!-- bench:nosuch -->"):
        P.publish("nosuch", "| x |\n|---|\n", root=tree)
    assert not (tree / "bench" / "results" / "nosuch.md").exists()
    readme.write_text(before.replace("<!-- /bench:calib_solve -->\n", "", 1))
    saved = (tree / "bench" / "results" / "calib_solve.md").read_text()
    with pytest.raises(P.PublishError, match="1 open and 0 close"):
        P.write("calib_solve", "| x |\n|---|\n", root=tree)
    assert (tree / "bench" / "results" / "calib_solve.md").read_text() == saved
