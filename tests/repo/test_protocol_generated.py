"""The C header and the Python layouts are generated from protocol/imubench.toml; a stale
generated file (someone edited the definition without regenerating, or edited a generated
file by hand) fails here."""
import subprocess
import sys

from conftest import ROOT


def test_generated_files_are_fresh():
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "gen_protocol.py"), "--check"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_generated_c_compiles_warning_free(tmp_path):
    r = subprocess.run(["gcc", "-std=c11", "-Wall", "-Wextra", "-Werror", "-Wshadow", "-pedantic",
                        f"-I{ROOT / 'firmware' / 'core'}", "-c", str(ROOT / "firmware" / "core" / "protocol_gen.c"),
                        "-o", str(tmp_path / "p.o")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
