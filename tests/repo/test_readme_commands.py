"""Every `imubench` command line of README.md, run verbatim from an empty folder (issue 32).

The commands are read from the text itself (fenced and indented code blocks, and inline code
spans; `~/imubench-env/bin/` and a trailing comment or description column are dropped):

* a line with a placeholder (`[...]`, `a|b`, `...`, an upper-case word such as FILE, URL, DIR)
  is a synopsis, not a command: it cannot be typed as it stands, so it is not run;
* every other line is run as written, with nothing but what the text shows, from an empty
  temporary folder with its own history database (IMUBENCH_DB), and must end as RUN says;
* a command not run is in EXCLUDED with the reason, and every entry there must still be in
  the README (a stale exclusion fails), so a command added to the README is run by default.

The README's `calibrate --from FILE --accel-unit U --gyro-unit U ...` is a synopsis (FILE is the
reader's); tests/procedures/test_from_file.py (test_readme_first_command_without_dir_...) runs
the newcomer's form of it, without --dir, on a synthetic file from an empty folder.

docs/: the commands there that use a file the repository ships are run the same way (none do
today: their files are the reader's own, e.g. log.csv; the scan is checked to find commands).
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"

# a synopsis: an option list, alternatives, an ellipsis, or a placeholder word in capitals
PLACEHOLDER = re.compile(r"\[|\||\.\.\.|…|(?<![\w-])[A-Z][A-Z_]*\d*(?!\w)")

EXCLUDED = {
    "imubench calibrate --sim --target f103":
        "the F103 firmware under the ARM emulator: minutes of CPU (tests/repo/test_wheel.py runs the images)",
    "imubench calibrate --sim --target f4": "the F4 firmware under the ARM emulator: as --target f103",
    "imubench sim --target f103": "the ARM emulator: needs the built images; tests/cli/test_cli_errors.py runs it",
    "imubench sim --target f103 --boot0 --pty": "the ROM bootloader on a pty for stm32flash, served until Ctrl-C "
                                                "(tests/cli/test_cli_errors.py)",
    "imubench qemu": "needs qemu-system-arm, which this test does not install",
    "imubench station --open": "serves the station page until Ctrl-C and opens a browser (tests/station/)",
    "imubench calibrate --station-file station.toml": "the text shows no station.toml; its ports are real boards "
                                                      "(tests/procedures/test_fixture.py reads station files)",
    "imubench calibrate --sim --sim-boards 4": "time: about 60 s on two shared cores (tests/station/test_station.py "
                                               "runs virtual boards on one plate)",
    "imubench calibrate --sim --sim-boards 16 --ui web": "serves the station page until Ctrl-C (tests/station/)",
    "imubench calibrate --sim --sim-seed 7 --method multi --gyro turntable --closure":
        "time: about 30 s beside the session below (tests/procedures/test_closure.py runs the closure)",
    "imubench thermal --sim --temps 5,25,45 --write": "time: 45 s by the README's own account "
                                                      "(tests/procedures/test_warmup.py, tests/results/test_report.py)",
}

# what each command that runs must do: (exit code, a text its stdout holds; for "server": the
# line it prints when it listens, then Ctrl-C must stop it with exit 0)
RUN = {
    "imubench --version": (0, "imubench"),
    "imubench --help": (0, "calibrate"),
    "imubench demo": (0, "calibration PASSED"),
    "imubench calibrate --sim": (0, "calibration PASSED"),
    "imubench attitude --sim --steps": (0, "RMS static error"),
    "imubench info": (0, "firmware"),                   # --port defaults to $IMUBENCH_PORT (README says so)
    # an example serial number: on a fresh machine no history holds it, which is said in one line
    "imubench history B559FCF4": (1, "imubench history: error: no "),
    "imubench sim": ("server", "virtual device"),
    "imubench sim --thermal-lag": ("server", "virtual device"),
    "imubench fake": ("server", "fake device"),
}


def command_lines(text: str) -> list[str]:
    """The `imubench ...` lines of a Markdown text, in order, without repeats."""
    out = []
    fence = False
    for ln in text.splitlines():
        if ln.strip().startswith("```"):
            fence = not fence
            continue
        if fence or ln.startswith("    "):
            m = re.match(r"\s*(?:\$ )?(?:~/imubench-env/bin/)?(imubench(?:\s.*)?)$", ln)
            if m:
                out.append(re.split(r"\s{2,}|\s#", m.group(1))[0].strip())
    out += [m.group(1).strip() for m in re.finditer(r"`(?:~/imubench-env/bin/)?(imubench\s[^`\n]*)`", text)]
    return list(dict.fromkeys(out))


def concrete(lines) -> list[str]:
    return [c for c in lines if not PLACEHOLDER.search(c)]


README_COMMANDS = concrete(command_lines(README.read_text(encoding="utf-8")))


def test_every_readme_command_is_run_or_excluded_with_a_reason():
    assert len(README_COMMANDS) >= 10, README_COMMANDS          # the scan finds the README's commands
    unknown = [c for c in README_COMMANDS if c not in RUN and c not in EXCLUDED]
    assert not unknown, f"README commands neither run nor excluded with a reason: {unknown}"
    stale = [c for c in [*RUN, *EXCLUDED] if c not in README_COMMANDS]
    assert not stale, f"no longer in the README: {stale}"
    assert all(len(why) > 20 for why in EXCLUDED.values())


def test_the_scan_tells_a_synopsis_from_a_command():
    text = ("```\nimubench calibrate --from FILE --accel-unit U\nimubench demo            # a session\n"
            "imubench flash --board f103|f4\n~/imubench-env/bin/imubench --version   # versions\nimubench calibrate --port URL1 --port URL2\n```\n"
            "and `imubench history B559FCF4` or `imubench calibrate ...`")
    assert concrete(command_lines(text)) == ["imubench demo", "imubench --version", "imubench history B559FCF4"]


@pytest.fixture(scope="module")
def virtual_port():
    """A virtual device for the commands that talk to one through $IMUBENCH_PORT."""
    from imubench.device.sim import VirtualBench
    with VirtualBench(speed=20.0, seed=1) as vb:
        yield vb.port_url


def _env(tmp_path: Path, port: str) -> dict:
    # nothing of this process's IMUBENCH_* settings, except how a subprocess reaches the lockstep
    # virtual device's clock (imubench.device.clock.ENV): a user's `imubench info` against a
    # virtual bench started by the same session finds it there
    from imubench.device.clock import ENV
    env = {k: v for k, v in os.environ.items() if not k.startswith("IMUBENCH_") or k == ENV}
    env.update(IMUBENCH_DB=str(tmp_path / "history.sqlite"), IMUBENCH_PORT=port)
    return env


def _argv(command: str) -> list[str]:
    return [sys.executable, "-m", "imubench", *command.split()[1:]]


@pytest.mark.timeout(300)
def test_readme_commands_run_verbatim_from_an_empty_folder(tmp_path, virtual_port):
    ran = []
    for command in README_COMMANDS:
        if command in EXCLUDED:
            continue
        assert command in RUN, f"{command!r}: neither run nor excluded (test_every_readme_command_...)"
        code, needle = RUN[command]
        work = tmp_path / f"run{len(ran)}"
        work.mkdir()
        t0 = time.monotonic()
        if code == "server":
            p = subprocess.Popen(_argv(command), cwd=work, env=_env(tmp_path, virtual_port), text=True,
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL)
            first = p.stdout.readline()
            p.send_signal(signal.SIGINT)
            out, err = p.communicate(timeout=30)
            assert needle in first and p.returncode == 0 and "Traceback" not in out + err, (command, first, out, err)
        else:
            r = subprocess.run(_argv(command), cwd=work, env=_env(tmp_path, virtual_port), capture_output=True,
                               text=True, timeout=180, stdin=subprocess.DEVNULL)
            text = r.stdout if code == 0 else r.stderr
            assert r.returncode == code and needle in text, (command, r.returncode, r.stdout[-2000:], r.stderr)
            assert "Traceback" not in r.stdout + r.stderr and "internal error" not in r.stderr, (command, r.stderr)
            if code:
                assert len(r.stderr.strip().splitlines()) == 1, (command, r.stderr)
        ran.append((command, round(time.monotonic() - t0, 1)))
    assert [c for c, _ in ran] == [c for c in README_COMMANDS if c not in EXCLUDED], ran


def test_docs_commands_on_files_the_repository_ships(tmp_path):
    """docs/: a command naming a file the repository ships is run with that file copied to the
    same relative path of an empty folder (none today; the scan must still find the docs'
    commands, so that this is a finding and not a broken scan)."""
    found, with_files = 0, []
    for doc in sorted((ROOT / "docs").glob("*.md")):
        for c in concrete(command_lines(doc.read_text(encoding="utf-8"))):
            found += 1
            shipped = [a for a in c.split()[1:] if not a.startswith("-") and "/" in a and (ROOT / a).is_file()]
            if shipped:
                with_files.append((doc.name, c, shipped))
    assert found >= 20
    for _, c, files in with_files:
        work = tmp_path / f"doc{len(list(tmp_path.iterdir()))}"
        for f in files:
            (work / f).parent.mkdir(parents=True, exist_ok=True)
            (work / f).write_bytes((ROOT / f).read_bytes())
        r = subprocess.run(_argv(c), cwd=work, env=_env(tmp_path, ""), capture_output=True, text=True, timeout=180,
                           stdin=subprocess.DEVNULL)
        assert r.returncode == 0 and "Traceback" not in r.stdout + r.stderr, (c, r.stdout[-2000:], r.stderr)
