"""Every firmware C file passes cppcheck (warning, style, performance, portability), and
the layout rule holds: portable code never touches a register."""
import re
import subprocess

from conftest import ROOT


def test_cppcheck_clean():
    r = subprocess.run(["make", "-s", "-C", str(ROOT), "lint"], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_portable_code_touches_no_register():
    """firmware/core and firmware/drivers reach hardware only through board.h / spi_bus.h /
    flash_if.h: no absolute addresses cast to pointers, no volatile register access, no
    vendor or CMSIS headers."""
    bad = []
    pattern = re.compile(r"\(\s*volatile\b|\*\s*\(\s*\w+\s*\*\s*\)\s*0x[0-9a-fA-F]+|#include\s*[<\"](stm32|core_cm|cmsis)",
                         re.IGNORECASE)
    for d in ("firmware/core", "firmware/drivers"):
        for f in sorted((ROOT / d).glob("*.[ch]")):
            for i, line in enumerate(f.read_text().splitlines(), 1):
                if pattern.search(line):
                    bad.append(f"{f.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not bad, "\n".join(bad)
