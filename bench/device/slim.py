"""Slim a wheel for the GPU machine: drop what the jobs never load, stub what is linked but
never called, so SAPIEN's wheel fits beside the working tree in the 64 MiB that may travel.

SAPIEN 3.0.3's cp312 wheel is 48.9 MiB; the simulator (PhysX, URDF loading, our ray-cast
camera) needs a third of it. Dropped: C++ headers (``include/``, 2.9 MiB zipped), the stereo
sensor's projector patterns (``sensor/assets/``, 6.9 MiB, read only when a StereoDepthSensor is
made), the macOS Vulkan loader and OIDN's CUDA device (1 MiB). Stubbed: Intel's denoiser core
(``libOpenImageDenoise_core``, 16.5 MiB), which ``libsvulkan2`` links for ray-traced rendering
through ``libOpenImageDenoise``: both become tiny libraries of the same names whose functions
fail (no device, an error code), so SAPIEN imports and simulates and a denoiser request gets an
error rather than a crash. Measured: the slim cp311 wheel installed with ``pip --target``
imports, loads our objects and runs trials with the same outcomes (bench/REPRODUCE.md, "The
GPU machine").
"""

from __future__ import annotations

import base64
import fnmatch
import hashlib
import shutil
import subprocess
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

# the twelve entry points libsvulkan2 imports (nm -D --undefined-only libsvulkan2.so | grep oidn)
OIDN_STUB = r"""
#include <stddef.h>
static const char *msg = "OpenImageDenoise is not shipped in this slim SAPIEN wheel";
void *oidnNewCUDADevice(const int *ids, const void *streams, int n) { return NULL; }
void oidnCommitDevice(void *d) {}
void oidnReleaseDevice(void *d) {}
int oidnGetDeviceError(void *d, const char **out) { if (out) *out = msg; return 1; }
void *oidnNewFilter(void *d, const char *type) { return NULL; }
void oidnCommitFilter(void *f) {}
void oidnExecuteFilter(void *f) {}
void oidnReleaseFilter(void *f) {}
void oidnSetFilterBool(void *f, const char *name, int value) {}
void oidnSetFilterImage(void *f, const char *name, void *buf, int format, size_t w, size_t h,
                        size_t offset, size_t pixel_stride, size_t row_stride) {}
void *oidnNewSharedBuffer(void *d, void *ptr, size_t size) { return NULL; }
void oidnReleaseBuffer(void *b) {}
"""


@dataclass(frozen=True)
class Recipe:
    """What to drop (glob patterns on the wheel's paths) and which files to replace by a
    stub library: path -> (C source, soname)."""

    drop: tuple[str, ...]
    stubs: dict[str, tuple[str, str]] = field(default_factory=dict)


OIDN = "sapien/oidn_library/"
RECIPES = {
    "sapien": Recipe(
        drop=("sapien/include/*", "sapien/sensor/assets/*", "sapien/vulkan_library/*.dylib",
              OIDN + "libOpenImageDenoise_device_cuda*"),
        stubs={OIDN + "libOpenImageDenoise_core.so.2.0.1": ("", "libOpenImageDenoise_core.so.2"),
               OIDN + "libOpenImageDenoise.so.2.0.1": (OIDN_STUB, "libOpenImageDenoise.so.2")}),
}


class SlimError(Exception):
    """A wheel that cannot be slimmed here (no C compiler, an unknown recipe)."""


def _record_hash(data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"sha256={digest}"


def build_stub(source: str, soname: str, out: Path) -> bytes:
    """A shared library named ``soname`` from C ``source``, built with the local compiler
    (x86-64 ELF, no dependencies beyond libc: it loads on the machine as it does here)."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise SlimError("no C compiler (cc/gcc) to build the stub libraries")
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "stub.c"
        src.write_text(source or "/* an empty library: its dependents need only the name */\n")
        subprocess.run([cc, "-shared", "-fPIC", "-O2", f"-Wl,-soname,{soname}", "-o", str(out),
                        str(src)], check=True, capture_output=True)
    return out.read_bytes()


def slim_wheel(src: Path, dest: Path, recipe: Recipe) -> dict[str, int]:
    """Write ``dest``: ``src`` without the dropped files and with the stubs, its RECORD
    rewritten to match (pip checks nothing else). Returns bytes dropped and kept."""
    dropped = 0
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dest, "w", zipfile.ZIP_DEFLATED,
                                                      compresslevel=9) as zout, \
            tempfile.TemporaryDirectory() as tmp:
        record_name = next(n for n in zin.namelist() if n.endswith(".dist-info/RECORD"))
        record: list[str] = []
        for info in zin.infolist():
            name = info.filename
            if name == record_name:
                continue
            if any(fnmatch.fnmatch(name, pat) for pat in recipe.drop):
                dropped += info.compress_size
                continue
            if name in recipe.stubs:
                dropped += info.compress_size
                data = build_stub(*recipe.stubs[name], Path(tmp) / Path(name).name)
            else:
                data = zin.read(name)
            out_info = zipfile.ZipInfo(name, date_time=info.date_time)
            out_info.external_attr = info.external_attr
            out_info.compress_type = zipfile.ZIP_DEFLATED
            zout.writestr(out_info, data)
            if not name.endswith("/"):
                record.append(f"{name},{_record_hash(data)},{len(data)}")
        record.append(f"{record_name},,")
        zout.writestr(record_name, "\n".join(record) + "\n")
    return {"dropped": dropped, "bytes": dest.stat().st_size}


def slimmed(whl: Path, cache: Path) -> Path:
    """The slim wheel of ``whl`` (its package's recipe), built once into ``cache``."""
    name = whl.name.split("-")[0].lower()
    if name not in RECIPES:
        raise SlimError(f"no slimming recipe for {name} (known: {', '.join(RECIPES)})")
    dest = cache / whl.name
    if not dest.exists() or dest.stat().st_mtime < whl.stat().st_mtime:
        cache.mkdir(parents=True, exist_ok=True)
        part = dest.with_suffix(".part")
        slim_wheel(whl, part, RECIPES[name])
        part.replace(dest)
    return dest
