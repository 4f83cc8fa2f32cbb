"""Figures the docs state come from the build: README's and docs/firmware.md's footprint tables
against `arm-none-eabi-size` of the images `make firmware` builds. A change that moves an
image by more than 1 % (the build id alone moves it by a few bytes) must update the tables."""
from __future__ import annotations

import re
import shutil
import subprocess

import pytest
from conftest import ROOT, make

TOLERANCE = 0.01


@pytest.fixture(scope="module")
def sizes() -> dict[str, tuple[int, int]]:
    """(flash = text + data, RAM = data + bss) in bytes per image, from the build."""
    images = ("f103", "f4", "qemu-f1", "qemu-f4")
    make(*(f"arm-{i}" for i in images))
    size = shutil.which("arm-none-eabi-size")
    assert size, "arm-none-eabi-size is missing: `make firmware` installs the toolchain (SYSTEM_PKGS)"
    out = subprocess.run([size, *(str(ROOT / "build" / "arm" / i / "imubench.elf") for i in images)],
                         capture_output=True, text=True, check=True).stdout.splitlines()[1:]
    got = {}
    for line in out:
        text, data, bss, *_ = line.split()
        got[line.split("/")[-2]] = (int(text) + int(data), int(data) + int(bss))
    return got


def _num(text: str) -> int:
    return int(re.sub(r"[ ,\u202f]", "", text))


def _close(doc: int, built: int) -> bool:
    return abs(doc - built) <= TOLERANCE * built


def test_the_readme_footprints_are_the_builds(sizes):
    readme = (ROOT / "README.md").read_text()
    rows = re.findall(r"^\| (f103|f4) \| ([\d ,]+) B \| ([\d ,]+) B \|", readme, re.M)
    assert {r[0] for r in rows} == {"f103", "f4"}, "README's footprint table is gone or changed its form"
    for image, flash, ram in rows:
        assert _close(_num(flash), sizes[image][0]) and _close(_num(ram), sizes[image][1]), (
            f"README says {image}: {flash} B flash, {ram} B RAM; the build gives {sizes[image][0]} B, "
            f"{sizes[image][1]} B: update the table")


def test_the_firmware_doc_footprints_are_the_builds(sizes):
    doc = (ROOT / "docs" / "firmware.md").read_text()
    rows = re.findall(r"^\| (f103|f4|qemu-f1|qemu-f4) \| (\d+) \| (\d+) \| (\d+) \|", doc, re.M)
    assert {r[0] for r in rows} == set(sizes), "docs/firmware.md's footprint table is gone or changed its form"
    for image, text, data, bss in rows:
        flash, ram = int(text) + int(data), int(data) + int(bss)
        assert _close(flash, sizes[image][0]) and _close(ram, sizes[image][1]), (
            f"docs/firmware.md says {image}: {flash} B flash, {ram} B RAM; the build gives "
            f"{sizes[image][0]} B, {sizes[image][1]} B: update the table")
