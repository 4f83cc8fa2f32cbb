"""Publish a benchmark's table: bench/results/NAME.md and the docs' `<!-- bench:NAME -->` blocks.

A benchmark builds its markdown table, prints it, and calls `publish(NAME, table, meta)` at
its end. That writes bench/results/NAME.md: one line saying when, where and how the table was
measured (UTC date, Python, CPUs, load average, the command that reproduces it, and whatever
the bench adds in `meta`), a blank line, then the table exactly as printed. Then, in README.md
and every docs/*.md, the text between

    <!-- bench:NAME -->
    <!-- /bench:NAME -->

is replaced by that file's content, so the figures the docs state are the bench's output and
nothing else (tests/repo/test_bench_tables.py fails when a block and its file differ).

`add_arguments(parser)` gives a bench `--no-publish`, for runs that must not touch the docs
(trials, loaded machines, other sizes); `publish(..., enabled=False)` then only says that the
table was not published. A bench that finds a block missing or unbalanced stops with a
one-line error before writing anything (`write()` raises PublishError instead).
"""
from __future__ import annotations

import argparse
import datetime as _dt
import os
import platform
import re
import shlex
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = "bench/results"
NAME_RE = re.compile(r"^[a-z0-9_]+(?:-[a-z0-9_]+)*$")


class PublishError(RuntimeError):
    """A block is missing, unbalanced or the name is not usable; nothing was written."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--no-publish", action="store_true",
                        help="print the tables only; leave bench/results, README.md and docs/ alone")


def block_re(name: str) -> re.Pattern[str]:
    """The block of NAME: the open marker's line, the content, the close marker's line."""
    n = re.escape(name)
    return re.compile(rf"^<!-- bench:{n} -->\n(.*?)^<!-- /bench:{n} -->$", re.M | re.S)


def blocks(text: str) -> dict[str, list[str]]:
    """Every block's content by name (a name may appear more than once in one file)."""
    out: dict[str, list[str]] = {}
    for m in re.finditer(r"^<!-- bench:([^ ]+) -->\n(.*?)^<!-- /bench:\1 -->$", text, re.M | re.S):
        out.setdefault(m.group(1), []).append(m.group(2))
    return out


def doc_files(root: Path = ROOT) -> list[Path]:
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


def header(meta: dict | None = None, command: str | None = None) -> str:
    """The result file's first line: when, where, how."""
    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    try:
        load = "load average " + " / ".join(f"{x:.1f}" for x in os.getloadavg())
    except OSError:
        load = "load average unknown"
    cmd = command or "python " + " ".join(shlex.quote(a) for a in
                                           [os.path.relpath(sys.argv[0], ROOT), *sys.argv[1:]])
    facts = [now, f"`{cmd}`", f"{os.cpu_count()} CPUs, {load}", f"Python {platform.python_version()}"]
    facts += [f"{k} {v}" for k, v in (meta or {}).items()]
    return "Measured " + ", ".join(facts) + "; written by the bench, not by hand."


def render(table: str, meta: dict | None = None, command: str | None = None) -> str:
    return header(meta, command) + "\n\n" + table.strip("\n") + "\n"


def replace_blocks(text: str, name: str, content: str) -> tuple[str, int]:
    """TEXT with every block of NAME holding CONTENT, and how many blocks there were."""
    opens = len(re.findall(rf"^<!-- bench:{re.escape(name)} -->$", text, re.M))
    closes = len(re.findall(rf"^<!-- /bench:{re.escape(name)} -->$", text, re.M))
    new, n = block_re(name).subn(lambda _m: f"<!-- bench:{name} -->\n{content}<!-- /bench:{name} -->", text)
    if opens != closes or opens != n:
        raise PublishError(f"bench:{name}: {opens} open and {closes} close markers, {n} whole blocks")
    return new, n


def publish(name: str, table: str, meta: dict | None = None, *, enabled: bool = True,
            command: str | None = None, root: Path = ROOT) -> Path | None:
    """Write bench/results/NAME.md and every `<!-- bench:NAME -->` block from TABLE.

    Returns the results file, or None when not enabled. When NAME is not a usable name or no
    document has a whole block of it, writes nothing and exits with a one-line error (the
    bench has printed its table already)."""
    try:
        return write(name, table, meta, enabled=enabled, command=command, root=root)
    except PublishError as e:
        raise SystemExit(f"bench/publish.py: error: not published: {e}") from None


def write(name: str, table: str, meta: dict | None = None, *, enabled: bool = True,
          command: str | None = None, root: Path = ROOT) -> Path | None:
    """publish() without the exit: raises PublishError, having written nothing."""
    if not NAME_RE.match(name):
        raise PublishError(f"bench name {name!r}: use lower-case letters, digits, _ and -")
    content = render(table, meta, command)
    if not enabled:
        print(f"(not published: {RESULTS}/{name}.md and the docs' bench:{name} blocks left as they are)")
        return None
    changed: dict[Path, str] = {}
    total = 0
    for doc in doc_files(root):
        if not doc.exists():
            continue
        text = doc.read_text()
        new, n = replace_blocks(text, name, content)
        total += n
        if new != text:
            changed[doc] = new
    if total == 0:
        raise PublishError(f"no <!-- bench:{name} --> block in README.md or docs/*.md: add one where "
                           f"the table belongs, or run with --no-publish")
    out = root / RESULTS / f"{name}.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(content)
    for doc, text in changed.items():
        doc.write_text(text)
    where = ", ".join(str(p.relative_to(root)) for p in changed) or "the docs already had it"
    print(f"published {out.relative_to(root)} ({total} block{'s' if total != 1 else ''}; rewrote: {where})")
    return out
