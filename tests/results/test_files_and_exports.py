"""Issue 25: files that are only what they claim, and exports and records that stay what they
are whatever free text they carry. Every case here was run against the code before the fix
and failed there (written through a link, hung on a FIFO, read /dev/zero, embedded a file
from elsewhere, added a parameter line, wrote ill-formed XML, printed an escape sequence,
showed half a password, called a port an internal error)."""
from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import numpy as np
import pytest
from imubench.cli.main import main as imubench
from imubench.errors import ImubenchError
from imubench.recordings import RecordingError, read
from imubench.results.atomic import write_json_atomic, write_text_atomic
from imubench.results.report import build_report

VICTIM = "the user's own file\n"


def _victim(tmp_path: Path) -> Path:
    v = tmp_path / "elsewhere" / "victim.txt"
    v.parent.mkdir(exist_ok=True)
    v.write_text(VICTIM)
    return v


def _cli(args, cwd: Path, timeout=60) -> subprocess.CompletedProcess:
    """The command line in its own process, so that a hang (a FIFO opened) fails by the timeout."""
    return subprocess.run([sys.executable, "-m", "imubench", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout, stdin=subprocess.DEVNULL)


def _one_error_line(r, needle: str) -> str:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 1 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert needle in lines[0], lines[0]
    return lines[0]


# ------------------------------------------------------------------ outputs
def test_tree_digest_is_one_hash_of_the_names_and_bytes_in_path_order(tmp_path):
    """imubench.files.tree_digest, the determinism checks' one comparison: the files' relative
    paths and bytes, in path order; another name, byte or file changes it; nothing matched: None."""
    import hashlib
    from imubench.files import tree_digest
    (tmp_path / "a" / "slot-1").mkdir(parents=True)
    (tmp_path / "a" / "slot-1" / "capture-1.bin").write_bytes(b"\x01\x02")
    (tmp_path / "a" / "capture-1.bin").write_bytes(b"\x03")
    (tmp_path / "a" / "notes.txt").write_text("not hashed")
    digest, files = tree_digest(tmp_path / "a")
    want = hashlib.sha256(b"capture-1.bin\0\x03" + b"slot-1/capture-1.bin\0\x01\x02").hexdigest()
    assert digest == want and [f.name for f in files] == ["capture-1.bin", "capture-1.bin"]
    (tmp_path / "a" / "capture-1.bin").write_bytes(b"\x04")
    assert tree_digest(tmp_path / "a")[0] != want
    assert tree_digest(tmp_path / "a", "*.none") == (None, [])


@pytest.mark.parametrize("openat", [True, False], ids=["openat", "portable"])
def test_both_atomic_writers_replace_whole_with_the_usual_mode_or_leave_nothing(tmp_path, monkeypatch, openat):
    """imubench.files.atomic_output on its two paths (openat where the OS has dir_fd, the portable
    one elsewhere), which share their write body: the content replaces the file whole with mode
    0666 less the umask, binary or text with the newline asked for; an exception in the block
    leaves the old content and no temporary file."""
    from imubench import files as F
    if openat and not F._OPENAT:
        pytest.fail("this system has no openat (dir_fd): the openat path cannot be checked here")
    monkeypatch.setattr(F, "_OPENAT", openat)
    target = tmp_path / "out.txt"
    target.write_text("old\n")
    with F.atomic_output(target, newline="\r\n") as fh:
        fh.write("new\n")
    assert target.read_bytes() == b"new\r\n"
    assert (target.stat().st_mode & 0o777) == 0o666 & ~F._UMASK
    with F.atomic_output(tmp_path / "b.bin", binary=True) as fh:
        fh.write(b"\x00\xff")
    assert (tmp_path / "b.bin").read_bytes() == b"\x00\xff"
    with pytest.raises(RuntimeError, match="half way"):
        with F.atomic_output(target) as fh:
            fh.write("partial")
            raise RuntimeError("half way")
    assert target.read_text() == "new\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.bin", "out.txt"]     # no temporary left


def test_a_link_at_the_temporary_name_is_not_written_through(tmp_path):
    victim = _victim(tmp_path)
    out = tmp_path / "s"
    out.mkdir()
    for name in ("report.html", "session.json"):
        (out / f"{name}.tmp").symlink_to(victim)
    write_text_atomic(out / "report.html", "<html></html>")
    write_json_atomic(out / "session.json", {"schema": 1})
    assert victim.read_text() == VICTIM
    assert (out / "report.html").read_text() == "<html></html>" and not (out / "report.html").is_symlink()
    assert json.loads((out / "session.json").read_text()) == {"schema": 1}
    # nothing but the two results and the two planted links: the temporary files are gone
    assert sorted(p.name for p in out.iterdir()) == ["report.html", "report.html.tmp", "session.json",
                                                     "session.json.tmp"]


def test_a_link_at_the_final_name_is_refused_in_one_line(tmp_path):
    victim = _victim(tmp_path)
    (tmp_path / "report.html").symlink_to(victim)
    with pytest.raises(ImubenchError, match="report.html is a symbolic link; imubench does not write through"):
        write_text_atomic(tmp_path / "report.html", "x")
    assert victim.read_text() == VICTIM and (tmp_path / "report.html").is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["elsewhere", "report.html"]     # no temporary left


def test_a_plot_is_not_drawn_through_a_link(tmp_path):
    from test_calibration import make_result

    from imubench.results.calibration import plot_pose_residuals
    victim = _victim(tmp_path)
    (tmp_path / "residuals.png").symlink_to(victim)
    with pytest.raises(ImubenchError, match="residuals.png is a symbolic link"):
        plot_pose_residuals(make_result(), tmp_path / "residuals.png")
    assert victim.read_text() == VICTIM


def test_decode_exports_are_not_written_through_links(tmp_path):
    victim = _victim(tmp_path)
    cap = _capture(tmp_path)
    for opt, name in (("--npz", "out.npz"), ("--csv", "out.csv")):
        (tmp_path / name).symlink_to(victim)
        r = _cli(["decode", cap, opt, name], tmp_path)
        _one_error_line(r, f"{name} is a symbolic link")
        assert victim.read_text() == VICTIM


def _capture(tmp_path: Path) -> Path:
    """A short raw capture: the shared protocol vectors' raw sample batch."""
    vec = json.loads((Path(__file__).resolve().parents[2] / "protocol" / "vectors" / "vectors.json").read_text())
    frames = [bytes.fromhex(v["frame_hex"]) for v in vec["vectors"] if v["name"] == "raw_batch_16"]
    assert frames, "the shared vectors hold a raw sample batch"
    p = tmp_path / "capture-1.bin"
    p.write_bytes(b"".join(frames))
    return p


def test_growing_outputs_refuse_links_and_fifos(tmp_path):
    from imubench.files import FileRefused, open_growing
    victim = _victim(tmp_path)
    (tmp_path / "capture-1.bin").symlink_to(victim)
    with pytest.raises(FileRefused, match="symbolic link"):
        open_growing(tmp_path / "capture-1.bin")
    os.mkfifo(tmp_path / "angles.csv")
    with pytest.raises(FileRefused, match="FIFO"):
        open_growing(tmp_path / "angles.csv", append=False, binary=False)
    with open_growing(tmp_path / "capture-2.bin") as fh:
        fh.write(b"ab")
    with pytest.raises(FileRefused, match="capture-2.bin exists already; a capture is never appended to"):
        open_growing(tmp_path / "capture-2.bin")                   # issue 36: never appended to
    assert (tmp_path / "capture-2.bin").read_bytes() == b"ab" and victim.read_text() == VICTIM


def test_outputs_follow_no_link_at_any_component_nor_a_hard_link(tmp_path):
    """issue 36 item 4: a planted `slot-1 -> ../victimdir` sent a whole session into another
    folder and replaced its files; a hard-linked capture-1.bin grew its victim from 24 B to
    913 KB (only the last component was checked, link counts never)."""
    from imubench.files import FileRefused, atomic_output, make_dir, open_growing, write_text
    victim = _victim(tmp_path)
    vdir = tmp_path / "victimdir"
    vdir.mkdir()
    (vdir / "session.json").write_text(VICTIM)
    out = tmp_path / "station"
    out.mkdir()
    (out / "slot-1").symlink_to("../victimdir")                      # a folder link in the output
    for write in (lambda: make_dir(out / "slot-1"), lambda: make_dir(out / "slot-1" / "deeper"),
                  lambda: write_text(out / "slot-1" / "session.json", "{}"),
                  lambda: open_growing(out / "slot-1" / "capture-1.bin")):
        with pytest.raises(FileRefused, match=r"station/slot-1 is a symbolic link \(to ../victimdir\); imubench writes "
                                              "only into real folders"):
            write()
    assert os.listdir(vdir) == ["session.json"] and (vdir / "session.json").read_text() == VICTIM
    # higher up the path too: the folder the session goes in is reached through a link
    (tmp_path / "via").symlink_to(out)
    with pytest.raises(FileRefused, match="via is a symbolic link"):
        make_dir(tmp_path / "via" / "slot-2")
    # a hard link at a capture's or a log's name: refused, the other file unchanged
    (out / "capture-1.bin").hardlink_to(victim)
    with pytest.raises(FileRefused, match="capture-1.bin exists already"):
        open_growing(out / "capture-1.bin")
    (out / "angles.csv").hardlink_to(victim)
    with pytest.raises(FileRefused, match="angles.csv has 3 links .a hard link to another file."):
        open_growing(out / "angles.csv", append=False, binary=False)
    assert victim.read_text() == VICTIM
    # a file on the way where a folder should be; a folder that does not exist for a file
    (out / "plain").write_text("x")
    with pytest.raises(FileRefused, match="plain is a regular file, not a folder"):
        make_dir(out / "plain" / "sub")
    with pytest.raises(FileRefused, match="nowhere does not exist"):
        write_text(out / "nowhere" / "x.json", "{}")
    # the system's own links at the top (root's, in /: /bin -> usr/bin here, /tmp and /var on
    # macOS) are no one else's to plant: followed
    from imubench.files import open_dir
    system = [n for n in os.listdir("/") if os.path.islink("/" + n) and os.path.isdir("/" + n)
              and os.lstat("/" + n).st_uid == 0]
    for n in system:
        fd = open_dir("/" + n, create=False)
        try:
            assert os.path.samestat(os.fstat(fd), os.stat("/" + n))
        finally:
            os.close(fd)
    # what is real is written as before; a relative path from the working folder too
    make_dir(out / "slot-3" / "a")
    write_text(out / "slot-3" / "a" / "s.json", "{}")
    with atomic_output(out / "slot-3" / "a" / "s.json") as fh:
        fh.write("[]")
    assert (out / "slot-3" / "a" / "s.json").read_text() == "[]"
    assert not [p for p in (out / "slot-3" / "a").iterdir() if p.name.endswith(".tmp")]
    cwd = os.getcwd()
    try:
        os.chdir(out)
        make_dir("rel/deep")
        with open_growing("rel/deep/capture-9.bin") as fh:
            fh.write(b"x")
    finally:
        os.chdir(cwd)
    assert (out / "rel" / "deep" / "capture-9.bin").read_bytes() == b"x"


# ------------------------------------------------------------------ inputs
HEADER = "t_s,ax,ay,az,gx,gy,gz\n"


def test_a_fifo_given_as_recording_or_session_is_refused_not_waited_on(tmp_path):
    os.mkfifo(tmp_path / "log.csv")
    r = _cli(["calibrate", "--from", "log.csv", "--accel-unit", "g", "--gyro-unit", "dps", "--dir", "o",
              "--db", tmp_path / "h.sqlite"], tmp_path)
    _one_error_line(r, "log.csv is a FIFO (named pipe); give a regular file")
    s = tmp_path / "sess"
    s.mkdir()
    os.mkfifo(s / "session.json")
    r = _cli(["calibrate", "--resume", s, "--port", "socket://127.0.0.1:1"], tmp_path)
    _one_error_line(r, "session.json is a FIFO (named pipe); give a regular file")


def test_a_device_or_a_directory_is_not_a_recording(tmp_path):
    (tmp_path / "zero.csv").symlink_to("/dev/zero")
    with pytest.raises(RecordingError, match="zero.csv is a character device; give a regular file"):
        read(tmp_path / "zero.csv", accel_unit="g", gyro_unit="dps")
    (tmp_path / "d.csv").mkdir()
    with pytest.raises(RecordingError, match="d.csv is a directory"):
        read(tmp_path / "d.csv", accel_unit="g", gyro_unit="dps")


def test_a_line_without_end_is_refused_at_the_limit(tmp_path):
    from imubench.files import MAX_LINE_CHARS
    p = tmp_path / "long.csv"
    with open(p, "w") as fh:
        fh.write(HEADER + "0,0,0,1,0,0,0\n")
        fh.write("1" * (MAX_LINE_CHARS + 10))
    with pytest.raises(RecordingError, match=f"line 3 is longer than the limit of {MAX_LINE_CHARS} characters"):
        read(p, accel_unit="g", gyro_unit="dps")
    p.write_text("1" * (MAX_LINE_CHARS + 10))                  # the header itself
    with pytest.raises(RecordingError, match="line 1 is longer than the limit"):
        read(p, accel_unit="g", gyro_unit="dps")


def test_a_small_npz_that_claims_gigabytes_is_refused_from_its_header(tmp_path):
    hdr = io.BytesIO()
    np.lib.format.write_array_header_1_0(hdr, {"descr": "<f8", "fortran_order": False, "shape": (201326592, 3)})
    p = tmp_path / "huge.npz"
    with zipfile.ZipFile(p, "w", zipfile.ZIP_DEFLATED) as z:
        for name in ("accel_mps2", "rate_rad_s"):
            z.writestr(name + ".npy", hdr.getvalue() + b"\0" * (1 << 20))
    assert p.stat().st_size < 100_000
    with pytest.raises(RecordingError, match=r"declares 4608 MiB \(shape \(201326592, 3\)\), more than the limit"):
        read(p)


def test_a_csv_is_read_in_chunks_as_before(tmp_path, monkeypatch):
    """The chunked reader (a few lines per chunk here) gives what one read gives."""
    from imubench.recordings import readers
    monkeypatch.setattr(readers, "CHUNK_LINES", 7)
    rng = np.random.default_rng(3)
    a = rng.normal(0, 0.01, (50, 3)) + [0, 0, 1]
    g = rng.normal(0, 0.1, (50, 3))
    p = tmp_path / "r.csv"
    with open(p, "w") as fh:
        fh.write("# a comment line\n" + HEADER)
        for i in range(50):
            fh.write(",".join(f"{v:.9g}" for v in (i / 100, *a[i], *g[i])) + ("\n" if i % 9 else "\n\n"))
    rec = read(p, accel_unit="g", gyro_unit="dps")
    assert len(rec) == 50 and rec.fs_hz == pytest.approx(100)
    assert np.allclose(rec.accel, a, atol=1e-8) and np.allclose(rec.gyro, g, atol=1e-8)


# ------------------------------------------------------------------ the report's JSON
def _bare_session(d: Path) -> None:
    d.mkdir()
    (d / "session.json").write_text(json.dumps({
        "schema": 1, "started": "2026-01-01T00:00:00+00:00", "poses": [], "complete": False,
        "config": {"method": "six", "rate_hz": 500, "hold_s": 1, "rest_s": 1, "settle_s": 1, "note": "",
                   "write": False, "tolerances": {}}}))


SECRET = "PRIVATE-PATH-FROM-ELSEWHERE"


def test_the_report_embeds_no_json_linked_from_outside(tmp_path):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "closure.json").write_text(json.dumps({"schema": 1, "path": SECRET, "after": {"distance_m": 0.1}}))
    (outside / "thermal.json").write_text(json.dumps({"schema": 1, "status": "done", "error": SECRET}))
    sd = tmp_path / "s"
    _bare_session(sd)
    (sd / "closure").mkdir()
    (sd / "closure" / "closure.json").symlink_to(outside / "closure.json")
    (sd / "thermal.json").symlink_to(outside / "thermal.json")
    doc = build_report(sd, tmp_path / "r.html", thermal_json=sd / "thermal.json").read_text()
    assert SECRET not in doc
    assert doc.count("data not embedded") == 2 and "is outside" in doc
    # the same files, where they are, are read
    (sd / "closure" / "closure.json").unlink()
    (sd / "closure" / "closure.json").write_text((outside / "closure.json").read_text())
    assert SECRET in build_report(sd, tmp_path / "r2.html").read_text()


# ------------------------------------------------------------------ exports and records
NASTY = "board\nARMING_CHECK,0\r\n\x1b[2J\x1b]0;owned\x07\x00\x0c\u202e"


def test_a_file_name_adds_no_ardupilot_parameter_line():
    from imubench.results.paramfiles import ardupilot_text
    text = ardupilot_text(np.eye(3), np.zeros(3), np.zeros(3), comment=f"imubench from {NASTY}.csv")
    params = [ln.split(",")[0] for ln in text.splitlines() if ln and not ln.startswith("#")]
    assert params == [f"INS_{k}_{ax}" for k in ("ACCOFFS", "ACCSCAL", "GYROFFS") for ax in "XYZ"]
    assert "ARMING_CHECK" in text.splitlines()[0] and "\x1b" not in text and "\r" not in text


def test_imucal_json_and_our_param_file_carry_free_text_as_json():
    from imubench.results.paramfiles import imucal_dict
    d = imucal_dict(np.eye(3), np.zeros(3), np.eye(3), np.zeros(3), "g", "deg/s", comment=NASTY)
    assert json.loads(json.dumps(d))["comment"] == NASTY           # JSON escapes it: one string, nothing added


def _run(**kw) -> dict:
    r = {"run_id": 1, "slot": 0, "port": "socket://127.0.0.1:1", "mcu_uid": "0123456789AB0123456789AB",
         "board": "f103", "passed": False, "written": False, "verified": False, "failed_stage": "health",
         "failure": "link lost\x00\x01\x1b[31m <&> \ufffe", "started": "2026-01-01T00:00:00+00:00",
         "finished": None, "started_utc": "2026-01-01T00:00:00+00:00", "finished_utc": None,
         "method": "multi", "gyro_method": None, "fw_version": "1.0.0", "fw_build": "abc\x08",
         "measurements": [], "session_id": "S\x0b1", "station_id": "line\x1f1", "operator": "A\x00B",
         "fixture": None, "host_version": "x"}
    r.update(kw)
    return r


def test_junit_stays_well_formed_whatever_the_text():
    from imubench.results.export import junit_xml
    doc = junit_xml([_run()])
    root = ET.fromstring(doc)                                             # well-formed XML 1.0
    err = root.find(".//error")
    assert err is not None and err.text == "link lost[31m <&> " and err.get("type") == "health"
    assert root.find(".//testsuite").get("hostname") == "line1"


def test_no_escape_sequence_reaches_the_terminal(tmp_path, capsys):
    code = imubench(["calibrate", "--from", str(tmp_path / f"{NASTY}.csv"), "--accel-unit", "g",
                     "--gyro-unit", "dps", "--dir", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code != 0 and err.count("\n") == 1 and err.endswith("\n")
    for c in ("\x1b", "\x07", "\x00", "\r", "\x0c", "\u202e"):
        assert c not in err, repr(c)
    assert "\\x1b[2J" in err and "\\u202e" in err                    # shown, escaped


def test_printed_commands_are_quoted(tmp_path, capsys):
    out = tmp_path / "closure run; rm -rf ~"
    out.mkdir()
    (out / "capture.bin").write_bytes(b"x")
    assert imubench(["closure", "--out", str(out), "--port", "socket://127.0.0.1:1"]) == 1
    err = capsys.readouterr().err
    assert f"imubench closure --analyse '{out}' recomputes it" in err, err


@pytest.mark.parametrize("url,needle", [
    ("postgresql://imubench:s3cr@t@127.0.0.1:1/db", "has more than one '@' before its host; write an '@'"),
    ("postgresql://imubench:s3cr3t@127.0.0.1:abc/db", "has a port that is not a number ('abc')"),
])
def test_database_urls_get_their_own_line_and_hide_the_password(url, needle, capsys):
    assert imubench(["history", "--db", url]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err and "internal error" not in err, err
    assert "s3cr" not in err and "t@" not in err and "postgresql://***@127.0.0.1" in err
