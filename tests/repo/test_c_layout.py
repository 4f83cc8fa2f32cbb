"""The firmware's C sources keep their rooms small and their walls (issue 35): no function over
MAX_FUNCTION_LINES, no file over MAX_FILE_LINES outside generated code, no private header
(`*_priv.h`, "not an interface") included outside its family, no two modules that include each
other's headers, and the core never names a sensor part (the part interface, sensor.h).

Each rule is also run on a small tree broken on purpose, so a rule that cannot fail is seen here.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest
from conftest import ROOT

MAX_FUNCTION_LINES = 120
MAX_FILE_LINES = 600
INCLUDE = re.compile(r'^\s*#\s*include\s*"([^"]+)"', re.M)
# a definition's first line at column 0 (type and name), its body from a "{" line at column 0 to
# the next "}" line at column 0 (the tree's style: .clang-format-like, checked below)
SIGNATURE = re.compile(r"^[A-Za-z_][\w \t\*]*?\b(\w+)\s*\(")
# the parts of protocol/parts.toml and their drivers, as the core must not write them
PART_NAME = re.compile(r"adxl35\d|adxrs45\d|adxrs29\d", re.I)


def c_files(root: Path) -> list[Path]:
    return sorted(p for p in (root / "firmware").rglob("*.[ch]") if p.is_file())


def generated(p: Path) -> bool:
    return "GENERATED" in p.read_text(errors="replace").split("\n", 1)[0]


def long_functions(p: Path) -> list[str]:
    """'path:line name() N lines' for each function body longer than MAX_FUNCTION_LINES."""
    lines = p.read_text(errors="replace").splitlines()
    out, name, start = [], None, None
    for i, ln in enumerate(lines):
        if ln == "{" and i > 0:
            # the name: the nearest signature line above (a signature may wrap over lines)
            for j in range(i - 1, max(-1, i - 6), -1):
                m = SIGNATURE.match(lines[j])
                if m:
                    name, start = m.group(1), i
                    break
        elif ln.startswith("}") and start is not None:
            n = i - start + 1
            if n > MAX_FUNCTION_LINES:
                out.append(f"{p.relative_to(ROOT) if p.is_relative_to(ROOT) else p}:{start + 1} {name}() {n} lines")
            name, start = None, None
    return out


def long_files(root: Path) -> list[str]:
    return [f"{p.relative_to(root)}: {n} lines" for p in c_files(root) if not generated(p)
            for n in [len(p.read_text(errors="replace").splitlines())] if n > MAX_FILE_LINES]


def module_of(path: Path) -> str:
    """A file's module: its directory and stem without _priv (core_priv.h belongs to core.c)."""
    return str(path.parent / re.sub(r"_priv$", "", path.stem))


def includes(root: Path) -> dict[Path, list[Path]]:
    """Each C file's quoted includes that resolve to a file of firmware/ (same directory first,
    then anywhere in firmware/ by name, as the -I list does)."""
    by_name: dict[str, list[Path]] = {}
    for p in c_files(root):
        by_name.setdefault(p.name, []).append(p)
    out = {}
    for p in c_files(root):
        got = []
        for inc in INCLUDE.findall(p.read_text(errors="replace")):
            local = p.parent / inc
            got += [local] if local.is_file() else by_name.get(Path(inc).name, [])[:1]
        out[p] = got
    return out


def private_leaks(root: Path) -> list[str]:
    """A *_priv.h included by a file outside its family: the files of its directory whose name
    starts with its stem (core_priv.h: core*.c) or that its opening comment names as sharing it
    (sim_main_priv.h: "what sim_main.c ... and sim_loop.c ... share")."""
    bad = []
    for p, incs in includes(root).items():
        for h in incs:
            if not h.stem.endswith("_priv"):
                continue
            text = h.read_text(errors="replace")
            opening = text[: text.find("*/") + 2] if text.lstrip().startswith("/*") else ""
            named = set(re.findall(r"\b(\w+\.c)\b", opening))
            if p.parent != h.parent or not (p.stem.startswith(h.stem[: -len("_priv")]) or p.name in named):
                bad.append(f"{p.relative_to(root)} includes {h.relative_to(root)}")
    return bad


def mutual_includes(root: Path) -> list[str]:
    """Two modules (each with a .c file) whose files include each other's headers."""
    has_c = {module_of(p) for p in c_files(root) if p.suffix == ".c"}
    edges: dict[str, set[str]] = {}
    for p, incs in includes(root).items():
        a = module_of(p)
        for h in incs:
            b = module_of(h)
            if a != b and a in has_c and b in has_c:
                edges.setdefault(a, set()).add(b)
    pairs = sorted({tuple(sorted((a, b))) for a, bs in edges.items() for b in bs if a in edges.get(b, set())})
    return [f"{Path(a).relative_to(root)} <-> {Path(b).relative_to(root)}" for a, b in pairs]


def core_names_a_part(root: Path) -> list[str]:
    bad = []
    for p in sorted((root / "firmware" / "core").glob("*.[ch]")):
        if generated(p):
            continue
        for i, ln in enumerate(p.read_text(errors="replace").splitlines(), 1):
            if PART_NAME.search(ln):
                bad.append(f"{p.relative_to(root)}:{i}: {ln.strip()}")
    return bad


def test_no_c_function_is_longer_than_the_limit():
    bad = [f for p in c_files(ROOT) if not generated(p) for f in long_functions(p)]
    assert not bad, f"C functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(bad)


def test_the_function_scan_sees_every_function():
    """The scan relies on the tree's style ({ and } of a body at column 0): every file's
    column-0 braces pair up, and it finds the functions we know."""
    for p in c_files(ROOT):
        lines = p.read_text(errors="replace").splitlines()
        opens, closes = sum(ln == "{" for ln in lines), sum(ln == "}" for ln in lines)
        assert opens == closes, f"{p.relative_to(ROOT)}: {opens} bodies open at column 0, {closes} close there"
    names = {m for p in c_files(ROOT) for m in re.findall(r"\n(?:static )?\w[\w \*]*?\b(\w+)\(", p.read_text())}
    assert {"ib_core_tick", "ibc_sample_finish", "ib_adxl355_init", "main"} <= names


def test_no_c_file_outside_generated_code_is_longer_than_the_limit():
    bad = long_files(ROOT)
    assert not bad, f"C files over {MAX_FILE_LINES} lines:\n" + "\n".join(bad)


def test_no_private_header_leaves_its_family():
    bad = private_leaks(ROOT)
    assert not bad, "private headers included outside their family:\n" + "\n".join(bad)


def test_no_two_c_modules_include_each_other():
    bad = mutual_includes(ROOT)
    assert not bad, "modules that include each other's headers:\n" + "\n".join(bad)


def test_the_core_names_no_part():
    bad = core_names_a_part(ROOT)
    assert not bad, "the core names a sensor part (use the ops of sensor.h):\n" + "\n".join(bad)


# ---- each rule fails on a tree broken on purpose ----

@pytest.fixture
def tree(tmp_path):
    fw = tmp_path / "firmware"
    (fw / "core").mkdir(parents=True)
    (fw / "boards").mkdir()
    return tmp_path


def test_a_long_function_is_named(tree):
    f = tree / "firmware" / "core" / "big.c"
    body = "\n".join(f"    x += {i};" for i in range(MAX_FUNCTION_LINES))
    f.write_text(f"static int small(void)\n{{\n    return 0;\n}}\n\nint too_big(int x)\n{{\n{body}\n    return x;\n}}\n")
    assert long_functions(f) == [f"{f}:7 too_big() {MAX_FUNCTION_LINES + 3} lines"]


def test_a_long_file_a_leak_a_circle_and_a_part_name_are_named(tree):
    fw = tree / "firmware"
    (fw / "core" / "long.c").write_text("int x;\n" * (MAX_FILE_LINES + 1))
    (fw / "core" / "long_gen.c").write_text("/* GENERATED by a tool */\n" + "int y;\n" * (MAX_FILE_LINES + 1))
    (fw / "core" / "core_priv.h").write_text("")
    (fw / "core" / "core.c").write_text('#include "core_priv.h"\nstatic int adxl355_reads;\n')
    (fw / "boards" / "board.c").write_text('#include "core_priv.h"\n#include "flash.h"\n#include "loop_priv.h"\n')
    (fw / "boards" / "loop_priv.h").write_text("/* loop_priv.h - what loop.c and main.c share. */\n")
    (fw / "boards" / "main.c").write_text('#include "loop_priv.h"\n')
    (fw / "boards" / "board.h").write_text("")
    (fw / "boards" / "flash.c").write_text('#include "board.h"\n')
    (fw / "boards" / "flash.h").write_text("")
    assert long_files(tree) == [f"firmware/core/long.c: {MAX_FILE_LINES + 1} lines"]
    assert private_leaks(tree) == ["firmware/boards/board.c includes firmware/core/core_priv.h",
                                   "firmware/boards/board.c includes firmware/boards/loop_priv.h"]
    assert mutual_includes(tree) == ["firmware/boards/board <-> firmware/boards/flash"]
    assert core_names_a_part(tree) == ["firmware/core/core.c:2: static int adxl355_reads;"]
