"""Every path and Python name the docs point a reader to exists: a moved module or a renamed
file breaks this test, not the reader's afternoon."""
from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md"), ROOT / "protocol" / "SPEC.md"])

NAME = re.compile(r"\bimubench(?:\.[A-Za-z_]\w*)+")
PATH = re.compile(r"`((?:docs|host|firmware|tools|bench|tests|protocol|\.ci)/[^`\s]*|\.importlinter|Makefile)`")


def _resolve(dotted: str) -> bool:
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def _names():
    for doc in DOCS:
        for m in NAME.finditer(doc.read_text()):
            name = m.group(0).rstrip(".")
            if name.split(".")[-1] in ("toml", "elf", "bin", "hex", "map", "md", "py"):
                continue           # a file name such as protocol/imubench.toml
            yield doc.name, name


def _paths():
    for doc in DOCS:
        for m in PATH.finditer(doc.read_text()):
            p = m.group(1).rstrip(".,:;")
            if any(c in p for c in "<>*{}|") or p.startswith("build/"):
                continue           # a pattern, not a path
            yield doc.name, p


@pytest.mark.parametrize("doc,name", sorted(set(_names())))
def test_python_names_in_docs_exist(doc, name):
    assert _resolve(name), f"{doc} names {name}, which does not exist"


@pytest.mark.parametrize("doc,path", sorted(set(_paths())))
def test_paths_in_docs_exist(doc, path):
    assert (ROOT / path).exists(), f"{doc} names {path}, which does not exist"


WORDS_NOBODY_CAN_LOOK_UP = ("seed paper", "spanish seed", "portuguese seed", "chinese seed", "thai seed",
                            "the brief", "the anchors", "anchors'")


@pytest.mark.parametrize("doc", DOCS, ids=[d.name for d in DOCS])
def test_docs_cite_works_not_our_private_names(doc):
    """A reader cannot look up 'the seed paper' or 'the brief': cite authors, title and year."""
    text = doc.read_text().lower()
    found = [w for w in WORDS_NOBODY_CAN_LOOK_UP if w in text]
    assert not found, f"{doc.name} says {found}"
