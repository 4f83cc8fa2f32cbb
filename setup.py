"""The compiled parts of the imubench wheel, built when the wheel is built (PEP 517 backend:
setuptools; the project's metadata is in pyproject.toml).

build_py compiles, with the project's own Makefile (one description of the C build for the
checkout and the wheel), into the setuptools build directory:

    imubench-sim          the virtual device (firmware core + drivers + sensor models, Linux)
    libimumodels.so       the same models for the ARM emulator (loaded through ctypes)
    f103, f4, qemu-f1, qemu-f4 / imubench.{elf,bin,hex,map}   the STM32 images (arm-none-eabi-gcc)

and puts them into the package as imubench/_data/ (bin/, lib/, firmware/<image>/) with
firmware/manifest.json (each image's firmware version, build id, sizes and SHA-256) and
build_info.json (package version, source revision). imubench.device.artifacts finds them there.

The source revision is `git describe --always --dirty` of the checkout; an sdist records it in
its REVISION file, so a wheel built from the sdist says the same. The images embed it as their
build id. -ffile-prefix-map maps the source directory away, so a wheel built from the checkout
and one built from its sdist carry the same files.

The wheel itself is byte for byte the same too (reproducible-builds.org, "SOURCE_DATE_EPOCH
specification", 2017): unless the environment sets SOURCE_DATE_EPOCH, it is set here to the
time of the last commit (`git log -1 --format=%ct`; an sdist records it in its
SOURCE_DATE_EPOCH file), and the wheel writer (bdist_wheel) stamps every zip entry with it and
writes the entries in sorted order. So `make dist`'s wheel, the one pip builds from the sdist
and one built from the tree have one SHA-256.

Building a wheel without gcc, make or the ARM compiler stops with an error: a wheel is never
silently without its virtual device or its images. An editable install (`pip install -e .`)
builds nothing here: the checkout uses `make sim firmware` and build/.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.command.sdist import sdist
from setuptools.dist import Distribution

try:
    from setuptools.command.bdist_wheel import bdist_wheel
except ImportError:                       # setuptools < 70.1: the wheel package's command
    try:
        from wheel.bdist_wheel import bdist_wheel
    except ImportError:                   # no wheel package: this setuptools builds no wheels at all
        bdist_wheel = None

ROOT = Path(__file__).resolve().parent
REVISION_FILE = "REVISION"
EPOCH_FILE = "SOURCE_DATE_EPOCH"
IMAGES = ("f103", "f4", "qemu-f1", "qemu-f4")
IMAGE_EXTS = ("elf", "bin", "hex", "map")
# tool -> Debian package that has it
TOOLS = {"make": "make", "gcc": "gcc", "arm-none-eabi-gcc": "gcc-arm-none-eabi",
         "arm-none-eabi-objcopy": "binutils-arm-none-eabi"}


class BuildError(SystemExit):
    def __init__(self, msg: str):
        super().__init__(f"error: imubench wheel: {msg}")


def source_revision() -> str:
    """git describe of the checkout, else the REVISION an sdist carries, else 'unknown'."""
    if (ROOT / ".git").exists():
        try:
            r = subprocess.run(["git", "-C", str(ROOT), "describe", "--always", "--dirty"],
                               capture_output=True, text=True, timeout=30)
            if r.returncode == 0 and r.stdout.strip():
                return r.stdout.strip()
        except OSError:
            pass
    f = ROOT / REVISION_FILE
    if f.is_file():
        return f.read_text().strip() or "unknown"
    return "unknown"


def source_date_epoch() -> str | None:
    """The commit time of the checkout (seconds since 1970), else the one an sdist carries."""
    if (ROOT / ".git").exists():
        try:
            r = subprocess.run(["git", "-C", str(ROOT), "log", "-1", "--format=%ct"],
                               capture_output=True, text=True, timeout=30)
            if r.returncode == 0 and r.stdout.strip().isdigit():
                return r.stdout.strip()
        except OSError:
            pass
    f = ROOT / EPOCH_FILE
    if f.is_file() and f.read_text().strip().isdigit():
        return f.read_text().strip()
    return None


if not os.environ.get("SOURCE_DATE_EPOCH") and source_date_epoch():
    # read by bdist_wheel's zip writer when it writes the wheel (in this process)
    os.environ["SOURCE_DATE_EPOCH"] = source_date_epoch()


def _first_line(cmd: list[str]) -> str:
    r = subprocess.run(cmd, capture_output=True, text=True)
    return (r.stdout.strip().splitlines() or ["?"])[0]


def build_native(build_dir: Path, dest: Path, version: str) -> None:
    """Compile the C parts with the Makefile into build_dir and copy them into dest
    (the package's _data directory in the build tree)."""
    missing = [f"{t} (Debian package {p})" for t, p in TOOLS.items() if shutil.which(t) is None]
    if missing:
        raise BuildError("cannot build the wheel's compiled parts (the virtual device and the STM32 "
                         f"images): missing {', '.join(missing)}; install them (sudo apt-get install "
                         f"{' '.join(sorted(set(TOOLS[t.split()[0]] for t in missing)))} libnewlib-arm-none-eabi) "
                         "or run `make system-deps` as root")
    revision = source_revision()
    try:
        rel = build_dir.relative_to(ROOT)      # relative: the link maps name the same paths
    except ValueError:
        rel = build_dir
    # from scratch every time: objects of an earlier build carry its build id in their debug
    # info (-g3 records the -D macros), which would make this wheel differ from the sdist's
    shutil.rmtree(build_dir, ignore_errors=True)
    prefix_map = f"-ffile-prefix-map={ROOT}=."
    targets = [f"{rel}/host/imubench-sim", f"{rel}/host/libimumodels.so", *(f"arm-{i}" for i in IMAGES)]
    jobs = [] if "-j" in os.environ.get("MAKEFLAGS", "") else [f"-j{os.cpu_count() or 1}"]
    cmd = ["make", "-s", *jobs, "-C", str(ROOT), f"BUILD={rel}", f"ARM_BUILD_ID={revision[:15]}",
           f"EXTRA_CFLAGS={prefix_map}", *targets]
    print("imubench: building the virtual device and the STM32 images: " + " ".join(cmd), flush=True)
    r = subprocess.run(cmd, stdout=sys.stdout, stderr=sys.stderr)
    if r.returncode != 0:
        raise BuildError(f"`{' '.join(cmd)}` failed (exit {r.returncode}); its output is above")

    sys.path.insert(0, str(ROOT / "host"))
    try:
        from imubench.device.artifacts import firmware_version, image_manifest
    finally:
        sys.path.pop(0)
    fw_version = firmware_version(ROOT / "firmware" / "core" / "core.c")
    proto = int(next(line.split()[2].rstrip("u") for line in
                     (ROOT / "firmware" / "core" / "protocol_gen.h").read_text().splitlines()
                     if line.startswith("#define IB_PROTOCOL_VERSION ")))

    if dest.exists():
        shutil.rmtree(dest)
    (dest / "bin").mkdir(parents=True)
    (dest / "lib").mkdir()
    b = ROOT / rel
    shutil.copyfile(b / "host" / "imubench-sim", dest / "bin" / "imubench-sim")
    shutil.copyfile(b / "host" / "libimumodels.so", dest / "lib" / "libimumodels.so")
    for f in (dest / "bin" / "imubench-sim", dest / "lib" / "libimumodels.so"):
        os.chmod(f, 0o755)
    for image in IMAGES:
        (dest / "firmware" / image).mkdir(parents=True)
        for ext in IMAGE_EXTS:
            src = b / "arm" / image / f"imubench.{ext}"
            if not src.is_file():
                raise BuildError(f"{src} was not built")
            shutil.copyfile(src, dest / "firmware" / image / f"imubench.{ext}")
            os.chmod(dest / "firmware" / image / f"imubench.{ext}", 0o644)
    manifest = image_manifest(dest / "firmware", fw_version, revision[:15], proto)
    (dest / "firmware" / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    info = {"version": version, "revision": revision,
            "compilers": {"cc": _first_line(["gcc", "--version"]),
                          "arm": _first_line(["arm-none-eabi-gcc", "--version"])}}
    (dest / "build_info.json").write_text(json.dumps(info, indent=2) + "\n")


class BuildPyWithNative(build_py):
    """build_py, then the compiled parts into imubench/_data (not for an editable install)."""

    def run(self):
        if getattr(self, "editable_mode", False):
            return super().run()
        # setuptools never removes a module deleted from the tree since the last build from
        # build/lib: start from an empty package so that the wheel is exactly this tree
        shutil.rmtree(Path(self.build_lib) / "imubench", ignore_errors=True)
        super().run()
        build_temp = Path(self.get_finalized_command("build").build_temp).resolve()
        build_native(build_temp / "native", Path(self.build_lib).resolve() / "imubench" / "_data",
                     self.distribution.get_version())


class SdistWithRevision(sdist):
    """The sdist records the source revision (REVISION), which has no git to ask."""

    def make_release_tree(self, base_dir, files):
        super().make_release_tree(base_dir, files)
        target = Path(base_dir) / REVISION_FILE
        if target.exists():
            target.unlink()                    # a hard link to the tree's file: never write through it
        target.write_text(source_revision() + "\n")
        epoch = Path(base_dir) / EPOCH_FILE
        if epoch.exists():
            epoch.unlink()
        stamp = os.environ.get("SOURCE_DATE_EPOCH") or source_date_epoch()
        if stamp:
            epoch.write_text(stamp + "\n")


class PlatformDistribution(Distribution):
    """Binary content: the package installs into platlib and the wheel is a platform wheel."""

    def has_ext_modules(self):
        return True


cmdclass = {"build_py": BuildPyWithNative, "sdist": SdistWithRevision}
if bdist_wheel is not None:
    class PlatformWheel(bdist_wheel):
        """A platform wheel (it carries a Linux executable and shared library), for any Python 3:
        nothing in it is built against the Python C API (the library is loaded through ctypes)."""

        def get_tag(self):
            _, _, plat = super().get_tag()
            return "py3", "none", plat

    cmdclass["bdist_wheel"] = PlatformWheel

setup(distclass=PlatformDistribution, cmdclass=cmdclass)
