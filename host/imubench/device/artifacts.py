"""Where the compiled parts of imubench are: the one place that finds them.

    sim_binary()            the virtual device (firmware core + drivers + sensor models for Linux)
    models_library()        libimumodels.so, the same models for the ARM emulator (ctypes)
    arm_image(image, ext)   an STM32 image: f103, f4, qemu-f1, qemu-f4; ext elf|bin|hex|map
    build_info()            package version, source revision, the images' versions and SHA-256

Two places, looked at in this order:

  installed   a platform wheel (or a wheel built from the sdist) carries them all in
              imubench/_data/ (bin/, lib/, firmware/<image>/, firmware/manifest.json,
              build_info.json), compiled when the wheel was built (setup.py). Nothing is
              compiled at run time: no make, compiler or checkout is needed.
  checkout    running from the source tree (an editable install, `make test`): build/host/ and
              build/arm/<image>/ of the checkout, brought up to date with `make` first (`build=True`),
              as before.

Anything else (a pure-Python install of the package without its data) is an ArtifactError that
says how to get a complete one.
"""
from __future__ import annotations

import hashlib
import json
import re
import shutil
import subprocess
from functools import lru_cache
from pathlib import Path

from imubench.errors import ImubenchError

__all__ = ["ArtifactError", "DATA", "IMAGES", "arm_image", "build_info", "checkout_root", "installed",
           "models_library", "sim_binary"]

PACKAGE = Path(__file__).resolve().parents[1]          # .../imubench
DATA = PACKAGE / "_data"                                # package data of a wheel
BUILD_INFO = "build_info.json"
MANIFEST = "firmware/manifest.json"

# the STM32 images: name -> what it is (firmware/arm.mk)
IMAGES = {
    "f103": "STM32F103 hardware",
    "f4": "STM32F405/407 hardware",
    "qemu-f1": "the F1 board code for qemu-system-arm -M stm32vldiscovery",
    "qemu-f4": "the F4 board code for qemu-system-arm -M netduinoplus2",
}
IMAGE_EXTS = ("elf", "bin", "hex", "map")


class ArtifactError(ImubenchError, RuntimeError):
    """A compiled part (virtual device, models library, firmware image) is missing or cannot be built."""


def installed() -> bool:
    """True when this package carries its compiled parts (installed from a platform wheel)."""
    return (DATA / BUILD_INFO).is_file()


def checkout_root() -> Path | None:
    """The source checkout this package runs from (host/imubench -> repo root), or None."""
    root = PACKAGE.parents[1]
    if (root / "Makefile").is_file() and (root / "firmware").is_dir() and (root / "host" / "imubench") == PACKAGE:
        return root
    return None


def not_found() -> ArtifactError:
    return ArtifactError(f"this imubench ({PACKAGE}) has neither its compiled parts (a platform wheel's "
                         "imubench/_data) nor a source checkout around it: install the wheel "
                         "(pip install imubench-*.whl, README.md, Install) or run from the checkout")


def _make(root: Path, *targets: str) -> None:
    if shutil.which("make") is None:
        raise ArtifactError("`make` not found: install make and a C compiler (gcc) to build the virtual "
                            f"device in the checkout {root}")
    r = subprocess.run(["make", "-s", "-C", str(root), *targets], capture_output=True, text=True)
    if r.returncode != 0:
        raise ArtifactError(f"building in {root} failed (make -s {' '.join(targets)}, exit {r.returncode}):\n"
                            f"{r.stdout}{r.stderr}".rstrip())


_BUILT: set[tuple[str, ...]] = set()


def _checkout_build(targets: tuple[str, ...], build: bool) -> Path:
    root = checkout_root()
    if root is None:
        raise not_found()
    if build and targets not in _BUILT:
        _make(root, *targets)
        _BUILT.add(targets)
    return root


def _packaged(rel: str) -> Path:
    p = DATA / rel
    if not p.is_file():
        raise ArtifactError(f"{p} is missing from this installed imubench: reinstall the wheel "
                            "(pip install --force-reinstall imubench-*.whl)")
    return p


def sim_binary(build: bool = True) -> Path:
    """The virtual device's executable (imubench-sim)."""
    if installed():
        return _packaged("bin/imubench-sim")
    root = _checkout_build(("sim",), build)
    p = root / "build" / "host" / "imubench-sim"
    if not p.is_file():
        raise ArtifactError(f"{p} is missing: build it with `make sim` in {root}")
    return p


def models_library(build: bool = True) -> Path:
    """libimumodels.so: the sensor models, physics, control channel and serial endpoint that the
    ARM emulator loads through ctypes."""
    if installed():
        return _packaged("lib/libimumodels.so")
    root = _checkout_build(("sim",), build)
    p = root / "build" / "host" / "libimumodels.so"
    if not p.is_file():
        raise ArtifactError(f"{p} is missing: build it with `make sim` in {root}")
    return p


def arm_image(image: str, ext: str = "elf", build: bool = True) -> Path:
    """One STM32 image file (`image` one of IMAGES, `ext` one of elf, bin, hex, map). In the
    checkout with build=True its image is brought up to date first (`make arm-<image>`); the
    path is returned even when the file does not exist (the caller says so in its words)."""
    if image not in IMAGES:
        raise ValueError(f"unknown image {image!r}: one of {', '.join(IMAGES)}")
    if ext not in IMAGE_EXTS:
        raise ValueError(f"unknown image file type {ext!r}: one of {', '.join(IMAGE_EXTS)}")
    if installed():
        return DATA / "firmware" / image / f"imubench.{ext}"
    root = _checkout_build((f"arm-{image}",), build)
    return root / "build" / "arm" / image / f"imubench.{ext}"


def image_dir(image: str) -> Path:
    """Where the image's files are (without building anything)."""
    return arm_image(image, "elf", build=False).parent


# ------------------------------------------------------------------ versions

FW_VERSION_RE = re.compile(r"#define\s+FW_VERSION_(MAJOR|MINOR|PATCH)\s+(\d+)u?")


def firmware_version(core_c: Path) -> str:
    """The firmware version the sources define (firmware/core/core.c FW_VERSION_*)."""
    parts = dict(FW_VERSION_RE.findall(core_c.read_text()))
    return ".".join(parts[k] for k in ("MAJOR", "MINOR", "PATCH"))


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 16), b""):
            h.update(chunk)
    return h.hexdigest()


def git_revision(root: Path) -> str | None:
    """`git describe --always --dirty` of a checkout (None without git or outside one)."""
    try:
        r = subprocess.run(["git", "-C", str(root), "describe", "--always", "--dirty"], capture_output=True,
                           text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() or None if r.returncode == 0 else None


def image_manifest(firmware_dir: Path, version: str, build_id: str, protocol_version: int) -> dict:
    """The manifest of built images: per image and file its size and SHA-256 (what setup.py writes
    into the wheel and `imubench --version` shows)."""
    images = {}
    for image in IMAGES:
        d = firmware_dir / image
        if not (d / "imubench.elf").is_file():
            continue
        images[image] = {"board": IMAGES[image], "fw_version": version, "fw_build": build_id,
                         "files": {f"imubench.{e}": {"size": (d / f"imubench.{e}").stat().st_size,
                                                     "sha256": sha256(d / f"imubench.{e}")}
                                   for e in IMAGE_EXTS if (d / f"imubench.{e}").is_file()}}
    return {"fw_version": version, "fw_build": build_id, "protocol_version": protocol_version,
            "images": images}


@lru_cache(maxsize=1)
def build_info() -> dict:
    """Package version, source revision, where the compiled parts come from and the images'
    versions: from the wheel's build_info.json and manifest, or computed from the checkout."""
    from imubench import __version__
    from imubench.wire.protocol_gen import PROTOCOL_VERSION
    if installed():
        info = json.loads((DATA / BUILD_INFO).read_text())
        manifest = json.loads((DATA / MANIFEST).read_text()) if (DATA / MANIFEST).is_file() else {"images": {}}
        return {"version": __version__, "revision": info.get("revision") or "unknown", "source": "wheel",
                "location": str(DATA), "protocol_version": PROTOCOL_VERSION, "images": manifest["images"]}
    root = checkout_root()
    if root is None:
        return {"version": __version__, "revision": "unknown", "source": "none", "location": str(PACKAGE),
                "protocol_version": PROTOCOL_VERSION, "images": {}}
    revision = git_revision(root) or "unknown"
    try:
        fw = firmware_version(root / "firmware" / "core" / "core.c")
    except (OSError, KeyError):
        fw = "unknown"
    built = root / "build" / "arm"
    try:
        build_id = (built / "build_id.txt").read_text().strip()
    except OSError:
        build_id = "unknown"
    man = image_manifest(built, fw, build_id, PROTOCOL_VERSION)
    return {"version": __version__, "revision": revision, "source": "checkout", "location": str(root),
            "protocol_version": PROTOCOL_VERSION, "images": man["images"]}


def version_text() -> str:
    """What `imubench --version` prints."""
    b = build_info()
    lines = [f"imubench {b['version']} (source {b['revision']}; protocol version {b['protocol_version']})"]
    where = {"wheel": "installed package", "checkout": "source checkout", "none": "none found"}[b["source"]]
    lines.append(f"compiled parts: {where} ({b['location']})")
    if not b["images"]:
        lines.append("firmware images: none" + (" built (make firmware)" if b["source"] == "checkout" else ""))
    for name, im in b["images"].items():
        elf = im["files"].get("imubench.elf", {})
        lines.append(f"firmware {name:<7} {im['fw_version']} (build {im['fw_build']}), "
                     f"elf sha256 {elf.get('sha256', '?')[:16]}")
    return "\n".join(lines)
