"""Reading what a command a test started prints, after the test has read some of its lines.

A test that reads a Popen's stdout with readline() and then calls communicate() loses output:
readline() reads ahead into the text wrapper's buffer, and communicate() reads the pipe's file
descriptor underneath it, so whatever the wrapper had already taken in is never returned (the
station overview test missed a line printed right after the page's address that way). finish()
reads the rest through the same wrappers instead."""
from __future__ import annotations

import re
import subprocess
import threading
import time


def finish(proc: subprocess.Popen, timeout: float) -> tuple[str, str]:
    """The rest of proc's stdout and its stderr (text mode), read to the end through the file
    objects the test read from, once proc has exited (killed after timeout seconds)."""
    got: dict[str, str] = {}
    readers = [threading.Thread(target=lambda name=name: got.__setitem__(name, getattr(proc, name).read()),
                                daemon=True) for name in ("stdout", "stderr")]
    for t in readers:
        t.start()
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    for t in readers:
        t.join(timeout=30)
    return got.get("stdout", ""), got.get("stderr", "")


def wait_for_line(proc: subprocess.Popen, pattern: str, lines: list[str], timeout_s: float = 60.0) -> re.Match:
    """Read proc's stdout line by line into `lines` until one matches pattern (its match);
    fails with what was printed when the output ends or timeout_s passes first."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        line = proc.stdout.readline()
        assert line, "".join(lines) + proc.stderr.read()
        lines.append(line)
        m = re.search(pattern, line)
        if m:
            return m
    raise AssertionError(f"no line matching {pattern!r} within {timeout_s:g} s:\n" + "".join(lines))
