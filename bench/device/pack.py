"""Pack what one GPU-machine call needs beside the working tree, and refuse what cannot travel.

The device tool sends the working tree (tracked and untracked-not-ignored files) and the
ignored paths named in ``carry``, 64 MiB in all. This script turns a job spec (a JSON file in
``bench/device/``) into one git-ignored folder, ``device_pack/`` by default, that the call
carries: the spec's jobs with their matrices expanded (``pack.json``), the collections and
checkpoints they read (``inputs/``, under the same relative paths the jobs name) and the
wheels the machine lacks (``wheels/``, from local wheel folders). The sizes are checked
before anything is copied, so an oversized pack fails here in a second, not on the machine.

A spec::

    {"name": "train_pull", "parallel": 7, "deadline_s": 540,
     "wheels": ["transforms3d==0.4.2"],       # names (optionally ==version) found in --wheels
     "slim": ["sapien"],                      # wheels to slim first (bench/device/slim.py)
     "inputs": ["data/train/cfw"],            # files or folders, relative to --root
     "env": {"W2E_X": "1"},                   # for every job
     "setup": [{"name": "testset", "argv": "w2e collect --out data/t ..."}],  # first, all rc 0
     "jobs": [{"name": "s{seed}", "matrix": {"seed": [0, 1]},
               "argv": "w2e train --data data/train/cfw --seed {seed} --out runs/s{seed}",
               "outputs": ["runs/s{seed}"], "timeout_s": 500}]}

Usage: python bench/device/pack.py bench/device/train_pull.json [--out device_pack]
       [--wheels .whl] [--download] [--limit-mib 64]; exit 2 when the pack would not fit.
Then run ``bench/device/run.py`` on the machine (bench/REPRODUCE.md, "The GPU machine").
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the runner beside it: stdlib only
from run import link_or_copy  # noqa: E402
from slim import SlimError, slimmed  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
MIB = 1 << 20
MARKER = "pack.json"
# what the GPU machine runs (measured there, bench/REPRODUCE.md): CPython 3.12 on x86-64 manylinux
DEVICE_PYTHON = "312"
DEVICE_PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64",
                    "manylinux2014_x86_64", "manylinux1_x86_64")


class PackError(Exception):
    """A pack that cannot be made or would not fit: one line for the user."""


def expand_jobs(spec: dict[str, Any], key: str = "jobs") -> list[dict[str, Any]]:
    """One concrete job per matrix point: ``{key}`` in name, argv and outputs filled in.

    Every (method, seed) becomes its own process on the machine, so the expansion happens
    here, once, and the runner never interprets a spec. ``key`` picks the phase: ``jobs``,
    or ``setup`` (what the jobs need made on the machine, e.g. a collection too large to
    travel; the runner runs it first and starts the jobs only if every setup job ends rc 0)."""
    jobs: list[dict[str, Any]] = []
    for job in spec.get(key, []):
        matrix = job.get("matrix", {})
        keys = list(matrix)
        for values in itertools.product(*(matrix[k] for k in keys)) if keys else [()]:
            fill = dict(zip(keys, (str(v) for v in values), strict=True))
            argv = job["argv"]
            argv = shlex.split(argv) if isinstance(argv, str) else list(argv)
            jobs.append({
                "name": job["name"].format(**fill),
                "argv": [a.format(**fill) for a in argv],
                "outputs": [o.format(**fill) for o in job.get("outputs", [])],
                "timeout_s": job.get("timeout_s"),
                "env": {k: str(v).format(**fill) for k, v in job.get("env", {}).items()},
            })
    names = [j["name"] for j in jobs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise PackError(f"job names repeat: {', '.join(dup)}")
    bad = [n for n in names if not re.fullmatch(r"[A-Za-z0-9._-]+", n)]
    if bad:
        raise PackError(f"job names must be letters, digits, '.', '_', '-': {', '.join(bad)}")
    return jobs


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "_", name).lower()


def wheel_fits_device(filename: str) -> bool:
    """Whether a wheel installs on the machine's CPython 3.12 / x86-64 (pure ones always)."""
    parts = filename[:-4].split("-")
    if len(parts) < 5:
        return False
    pys, abis, plat = (t.split(".") for t in parts[-3:])
    dev = int(DEVICE_PYTHON)
    if "none" in abis:
        py_ok = any(t in ("py3", f"py{dev}", f"cp{dev}") for t in pys)
    elif "abi3" in abis:  # cp3x-abi3 installs on every later CPython 3
        py_ok = any(t.startswith("cp3") and t[2:].isdigit() and int(t[2:]) <= dev for t in pys)
    else:
        py_ok = f"cp{dev}" in pys and f"cp{dev}" in abis
    plat_ok = "any" in plat or any(p.startswith("manylinux") and p.endswith("x86_64")
                                   for p in plat)
    return py_ok and plat_ok


def find_wheel(requirement: str, folders: list[Path]) -> Path | None:
    """The first wheel in ``folders`` named (and versioned, with ``==``) as ``requirement``
    that installs on the machine."""
    name, _, version = requirement.partition("==")
    for folder in folders:
        for whl in sorted(folder.glob("*.whl")) if folder.is_dir() else []:
            parts = whl.name.split("-")
            if (_norm(parts[0]) == _norm(name) and (not version or parts[1] == version)
                    and wheel_fits_device(whl.name)):
                return whl
    return None


def download_command(requirement: str, dest: Path) -> list[str]:
    """pip's own download of a wheel for the machine (its Python and platform, no deps)."""
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
           "--python-version", DEVICE_PYTHON[0] + "." + DEVICE_PYTHON[1:],
           "--implementation", "cp", "-d", str(dest), requirement]
    for p in DEVICE_PLATFORMS:
        cmd[-1:-1] = ["--platform", p]
    return cmd


def tree_bytes(root: Path) -> int:
    """Bytes of a file, or of every file under a folder (links as links, as they travel)."""
    if root.is_file() or root.is_symlink():
        return root.lstat().st_size
    return sum(p.lstat().st_size for p in root.rglob("*") if p.is_file() or p.is_symlink())


def working_tree_bytes(repo: Path) -> int:
    """What the device tool sends of the checkout without ``carry``: tracked and
    untracked-not-ignored files, and a ``shared/`` folder inside it."""
    try:
        out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others",
                              "--exclude-standard"], cwd=repo, capture_output=True,
                             check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return 0  # not a git checkout (a copy): only the pack counts
    names = {n for n in out.decode().split("\0") if n}
    total = sum((repo / n).lstat().st_size for n in names if (repo / n).is_file()
                or (repo / n).is_symlink())
    shared = repo / "shared"
    if shared.is_dir():
        total += sum(p.lstat().st_size for p in shared.rglob("*") if p.is_file()
                     and str(p.relative_to(repo)) not in names)
    return total


def _copy(src: Path, dst: Path) -> None:
    """Hard links where the file system allows (packing 50 MB costs nothing), else copies."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.is_dir():
        shutil.copytree(src, dst, copy_function=link_or_copy, symlinks=False)
    else:
        link_or_copy(src, dst)


def pack(spec_path: Path, out: Path, root: Path, wheel_dirs: list[Path], limit_mib: float,
         tree: int | None = None, download: bool = False) -> dict[str, Any]:
    """Check sizes, then write the pack folder; returns its manifest."""
    spec = json.loads(spec_path.read_text())
    jobs = expand_jobs(spec)
    if not jobs:
        raise PackError(f"{spec_path}: no jobs")
    setup = expand_jobs(spec, "setup")
    clash = sorted({j["name"] for j in setup} & {j["name"] for j in jobs})
    if clash:
        raise PackError(f"setup and job names repeat: {', '.join(clash)}")
    inputs = [str(Path(p)) for p in spec.get("inputs", [])]
    for rel in inputs:
        if Path(rel).is_absolute() or ".." in Path(rel).parts:
            raise PackError(f"input {rel}: must be a path inside {root}")
        if not (root / rel).exists():
            raise PackError(f"input {rel}: not found under {root}")
    wheels: list[Path] = []
    for req in spec.get("wheels", []):
        whl = find_wheel(req, wheel_dirs)
        if whl is None and download and wheel_dirs:
            wheel_dirs[0].mkdir(parents=True, exist_ok=True)
            subprocess.run(download_command(req, wheel_dirs[0]), check=False)
            whl = find_wheel(req, wheel_dirs)
        if whl is None:
            where = ", ".join(str(d) for d in wheel_dirs) or "no wheel folder"
            fetch = shlex.join(download_command(req, wheel_dirs[0] if wheel_dirs else REPO))
            raise PackError(f"wheel {req}: none for CPython {DEVICE_PYTHON} x86-64 in {where} "
                            f"(--download runs: {fetch})")
        wheels.append(whl)
    slim = {_norm(n) for n in spec.get("slim", [])}
    full = {w.name: w.stat().st_size for w in wheels}
    try:  # the slim wheels are built once, beside the wheels they come from
        wheels = [slimmed(w, w.parent / "slim") if _norm(w.name.split("-")[0]) in slim else w
                  for w in wheels]
    except SlimError as e:
        raise PackError(str(e)) from None
    sizes = {rel: tree_bytes(root / rel) for rel in inputs}
    sizes.update({f"wheels/{w.name}": w.stat().st_size for w in wheels})
    pack_bytes = sum(sizes.values())
    tree = working_tree_bytes(REPO) if tree is None else tree
    limit = int(limit_mib * MIB)
    if tree + pack_bytes > limit:
        big = ", ".join(f"{k} {v / MIB:.1f}" for k, v in
                        sorted(sizes.items(), key=lambda kv: -kv[1])[:3])
        raise PackError(f"pack {pack_bytes / MIB:.1f} MiB + working tree {tree / MIB:.1f} MiB "
                        f"= {(tree + pack_bytes) / MIB:.1f} MiB is over the {limit_mib:g} MiB "
                        f"that may travel (largest: {big} MiB)")
    if out.exists():
        if any(out.iterdir()) and not (out / MARKER).exists():
            raise PackError(f"{out} exists and is not a pack: not overwriting it")
        shutil.rmtree(out)
    for rel in inputs:
        _copy(root / rel, out / "inputs" / rel)
    for whl in wheels:
        _copy(whl, out / "wheels" / whl.name)
    manifest = {
        "name": spec.get("name", spec_path.stem), "spec": str(spec_path),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"), "commit": _commit(),
        "parallel": spec.get("parallel"), "deadline_s": spec.get("deadline_s"),
        "env": {k: str(v) for k, v in spec.get("env", {}).items()},
        "inputs": inputs, "wheels": [w.name for w in wheels], "setup": setup, "jobs": jobs,
        "slimmed": {w.name: {"from_bytes": full[w.name], "bytes": w.stat().st_size}
                    for w in wheels if w.parent.name == "slim"},
        "bytes": {"pack": pack_bytes, "working_tree": tree, "limit": limit},
    }
    (out / MARKER).write_text(json.dumps(manifest, indent=1))
    return manifest


def _commit() -> str | None:
    r = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True)
    return r.stdout.strip() or None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("spec", type=Path, help="job spec (bench/device/*.json)")
    p.add_argument("--out", type=Path, default=REPO / "device_pack",
                   help="pack folder; inside the checkout it must be git-ignored (carry it)")
    p.add_argument("--root", type=Path, default=REPO,
                   help="where the spec's inputs are found (default: the checkout)")
    p.add_argument("--wheels", type=Path, nargs="*", default=[REPO / ".whl"],
                   help="folders holding wheels for the machine (default .whl)")
    p.add_argument("--download", action="store_true",
                   help="fetch a missing wheel with pip download into the first --wheels")
    p.add_argument("--limit-mib", type=float, default=64.0,
                   help="what may travel: the working tree and the pack together")
    p.add_argument("--tree-bytes", type=int, default=None,
                   help="the working tree's size to count (default: measured with git)")
    a = p.parse_args(argv)
    try:
        m = pack(a.spec, a.out, a.root, a.wheels, a.limit_mib, a.tree_bytes, a.download)
    except PackError as e:
        print(f"pack: {e}", file=sys.stderr)
        return 2
    b = m["bytes"]
    print(f"pack {a.out}: {len(m['setup'])} setup jobs, {len(m['jobs'])} jobs, "
          f"{len(m['inputs'])} inputs, "
          f"{len(m['wheels'])} wheels; {b['pack'] / MIB:.1f} MiB + working tree "
          f"{b['working_tree'] / MIB:.1f} MiB of {b['limit'] / MIB:.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
