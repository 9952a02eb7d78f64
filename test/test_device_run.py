"""The prepared GPU-machine run (bench/device/), dry-run on the CPU with the tiny spec.

pack.py must refuse, before copying anything, a pack that would not travel; run.py must run
every job as its own process, stop the one that overruns its limit (keeping what it wrote),
and bring back one tarball whose summary says which job finished and which timed out.
"""

from __future__ import annotations

import ctypes
import importlib.util
import json
import shutil
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest
from synthetic import synthetic_data

REPO = Path(__file__).resolve().parents[1]
DEVICE = REPO / "bench" / "device"
MIB = 1 << 20


def _module(name: str):
    spec = importlib.util.spec_from_file_location(f"device_{name}", DEVICE / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def _wheel(folder: Path) -> Path:
    """A real, tiny pure-python wheel: what the machine lacks travels as such a file."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "w2e_probe-0.1-py3-none-any.whl"
    info = "w2e_probe-0.1.dist-info"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("w2e_probe/__init__.py", "MESSAGE = 'probe from a travelled wheel'\n")
        z.writestr(f"{info}/METADATA", "Metadata-Version: 2.1\nName: w2e_probe\nVersion: 0.1\n")
        z.writestr(f"{info}/WHEEL", "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: "
                                    "true\nTag: py3-none-any\n")
        z.writestr(f"{info}/RECORD", f"w2e_probe/__init__.py,,\n{info}/METADATA,,\n"
                                     f"{info}/WHEEL,,\n{info}/RECORD,,\n")
    return path


@pytest.fixture()
def root(tmp_path: Path) -> Path:
    """A checkout-like folder with the tiny collection the tiny spec names."""
    r = tmp_path / "root"
    synthetic_data(obs_per_cat=2, per_obs=16, num_points=256).save_shard(
        r / "data" / "device_tiny" / "shard-00000.npz")
    return r


def _pack(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(DEVICE / "pack.py"), *args],
                          capture_output=True, text=True, timeout=60)


def test_pack_refuses_what_would_not_travel_before_copying_anything(root, tmp_path):
    out = tmp_path / "pack"
    spec = str(DEVICE / "tiny.json")
    big = _pack([spec, "--root", str(root), "--out", str(out), "--tree-bytes", str(64 * MIB)])
    assert big.returncode == 2
    assert big.stderr.count("\n") == 1 and "over the 64 MiB" in big.stderr, big.stderr
    assert "data/device_tiny" in big.stderr  # it names what is large
    assert not out.exists()
    missing = _pack([spec, "--root", str(tmp_path), "--out", str(out), "--tree-bytes", "0"])
    assert missing.returncode == 2 and "data/device_tiny: not found" in missing.stderr
    # a wheel the spec asks for and no folder holds: refused, with the pip line that fetches it
    spec2 = tmp_path / "wheel.json"
    spec2.write_text(json.dumps({**json.loads((DEVICE / "tiny.json").read_text()),
                                 "wheels": ["transforms3d"]}))
    nowheel = _pack([str(spec2), "--root", str(root), "--out", str(out), "--tree-bytes", "0",
                     "--wheels", str(tmp_path / "none")])
    assert nowheel.returncode == 2 and "pip download" in nowheel.stderr
    assert "--python-version 3.12" in nowheel.stderr


def test_wheel_tags_and_matrix_expansion():
    pack = _module("pack")
    fits = pack.wheel_fits_device
    assert fits("transforms3d-0.4.2-py3-none-any.whl")
    assert fits("sapien-3.0.3-cp312-cp312-manylinux2014_x86_64.whl")
    assert fits("x-1.0-cp38-abi3-manylinux_2_17_x86_64.manylinux2014_x86_64.whl")
    assert not fits("fpsample-1.0.2-cp311-cp311-linux_x86_64.whl")  # the local build
    assert not fits("sapien-3.0.3-cp312-cp312-manylinux2014_aarch64.whl")
    spec = json.loads((DEVICE / "benchmark_pull.json").read_text())
    jobs = pack.expand_jobs(spec)
    assert len(jobs) == 15 and jobs[0]["name"] == "none_s0"
    assert "--seeds" in jobs[0]["argv"] and jobs[0]["argv"][jobs[0]["argv"].index("--seeds")
                                                            + 1] == "0"
    assert len(pack.expand_jobs(json.loads((DEVICE / "train_pull.json").read_text()))) == 7
    with pytest.raises(pack.PackError, match="repeat"):
        pack.expand_jobs({"jobs": [{"name": "a", "argv": "true"}, {"name": "a", "argv": "x"}]})


def test_tiny_pack_runs_every_job_as_its_own_process_and_stops_the_overrun(root, tmp_path):
    spec = json.loads((DEVICE / "tiny.json").read_text())
    spec["wheels"] = ["w2e_probe"]
    spec["jobs"].append({"name": "probe", "argv": ["python", "-c",
                         "import w2e_probe; print(w2e_probe.MESSAGE)"]})
    spec_path = tmp_path / "tiny_probe.json"
    spec_path.write_text(json.dumps(spec))
    _wheel(tmp_path / "wheels")
    out = tmp_path / "pack"
    r = _pack([str(spec_path), "--root", str(root), "--out", str(out), "--tree-bytes", "0",
               "--wheels", str(tmp_path / "wheels")])
    assert r.returncode == 0, r.stderr
    manifest = json.loads((out / "pack.json").read_text())
    assert [j["name"] for j in manifest["jobs"]] == ["train_s0", "train_s1", "overrun", "probe"]
    assert (out / "inputs" / "data" / "device_tiny" / "shard-00000.npz").is_file()
    assert (out / "wheels" / "w2e_probe-0.1-py3-none-any.whl").is_file()

    res = tmp_path / "OUT"
    run = subprocess.run(
        [sys.executable, str(DEVICE / "run.py"), "--pack", str(out), "--out", str(res),
         "--deadline-s", "50", "--reserve-s", "5", "--grace-s", "2", "--parallel", "4",
         "--work", str(tmp_path / "work"), "--site", str(tmp_path / "site")],
        capture_output=True, text=True, timeout=120)
    assert run.returncode == 1, run.stdout + run.stderr  # the overrun is not rc 0
    assert "overrun overrun" in run.stdout
    with tarfile.open(res / "results.tar.gz") as tar:
        names = set(tar.getnames())
        summary = json.load(tar.extractfile("results/summary.json"))
        overrun_log = tar.extractfile("results/logs/overrun.log").read().decode()
        probe_log = tar.extractfile("results/logs/probe.log").read().decode()
    assert summary == json.loads((res / "summary.json").read_text())
    jobs = {j["name"]: j for j in summary["jobs"]}
    for s in ("train_s0", "train_s1"):
        assert jobs[s]["rc"] == 0 and jobs[s]["status"] == "done" and not jobs[s]["timed_out"]
        assert f"results/outputs/runs/tiny_{s[-2:]}/model.pt" in names
        assert f"results/outputs/runs/tiny_{s[-2:]}/metrics.jsonl" in names
        assert f"results/logs/{s}.log" in names
    o = jobs["overrun"]
    assert o["timed_out"] and o["status"] == "timed_out" and o["rc"] != 0
    assert 3 <= o["seconds"] < 40  # its own 3 s limit, not the global one (45 s); slack for load
    assert "sleeping" in overrun_log and "results/outputs/overrun.txt" in names  # kept
    assert jobs["probe"]["rc"] == 0 and "probe from a travelled wheel" in probe_log
    # the trainings read what the setup job made there: it ran, and ran before them
    (prep,) = summary["setup"]
    assert prep["name"] == "prepare" and prep["rc"] == 0 and prep["status"] == "done"
    assert prep["start_s"] + prep["seconds"] <= jobs["train_s0"]["start_s"]
    assert "results/logs/prepare.log" in names
    assert summary["wheels_rc"] == 0 and summary["left_out"] == []
    assert "results/logs/_runner.log" in names


def test_the_global_deadline_stops_a_job_and_leaves_the_queue_unstarted(tmp_path):
    """One slot, a job with no limit of its own that sleeps past the deadline: it is stopped
    at the deadline less the reserve, and the job queued behind it never starts."""
    pack = tmp_path / "pack"
    pack.mkdir()
    sleep = ["python", "-c", "import time; time.sleep(120)"]
    (pack / "pack.json").write_text(json.dumps({
        "name": "deadline", "inputs": [], "wheels": [], "env": {},
        "jobs": [{"name": n, "argv": sleep, "outputs": []} for n in ("first", "second")]}))
    res = tmp_path / "OUT"
    r = subprocess.run([sys.executable, str(DEVICE / "run.py"), "--pack", str(pack),
                        "--out", str(res), "--deadline-s", "4", "--reserve-s", "1",
                        "--grace-s", "1", "--parallel", "1"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1
    jobs = {j["name"]: j for j in json.loads((res / "summary.json").read_text())["jobs"]}
    # stopped at the deadline less the reserve (3 s), not after its 120 s sleep; slack for load
    assert jobs["first"]["timed_out"] and 2.5 <= jobs["first"]["seconds"] < 60
    assert jobs["second"]["status"] == "not_started" and jobs["second"]["rc"] is None


def test_a_failed_setup_job_starts_no_job_and_says_why(tmp_path):
    """A setup job (a collection made on the machine) that fails: the jobs that would read
    its output are skipped, not run on nothing, and the summary names the setup job."""
    pack = tmp_path / "pack"
    pack.mkdir()
    (pack / "pack.json").write_text(json.dumps({
        "name": "setup", "inputs": [], "wheels": [], "env": {},
        "setup": [{"name": "collect", "argv": ["python", "-c", "raise SystemExit(3)"],
                   "outputs": []}],
        "jobs": [{"name": "bench", "argv": ["python", "-c", "open('ran', 'w')"],
                  "outputs": ["ran"]}]}))
    res = tmp_path / "OUT"
    r = subprocess.run([sys.executable, str(DEVICE / "run.py"), "--pack", str(pack),
                        "--out", str(res), "--deadline-s", "20", "--work",
                        str(tmp_path / "work")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "setup failed (collect)" in r.stdout
    summary = json.loads((res / "summary.json").read_text())
    assert summary["setup"][0]["rc"] == 3
    (bench,) = summary["jobs"]
    assert bench["status"] == "skipped" and bench["rc"] is None
    assert "collect" in bench["notes"][0] and not (tmp_path / "work" / "ran").exists()
    pack_mod = _module("pack")
    with pytest.raises(pack_mod.PackError, match="setup and job names repeat"):
        pack_mod.pack(_spec_with_setup_named(tmp_path, "train_s{seed}"), tmp_path / "p",
                      tmp_path, [], 64, tree=0)


def _spec_with_setup_named(tmp_path: Path, name: str) -> Path:
    spec = json.loads((DEVICE / "tiny.json").read_text())
    spec["inputs"] = []
    spec["setup"] = [{"name": name, "matrix": {"seed": [0]}, "argv": "true"}]
    path = tmp_path / "clash.json"
    path.write_text(json.dumps(spec))
    return path


def test_outputs_past_one_tarball_spill_into_more_parts_then_are_named(tmp_path):
    run = _module("run")
    logs, work = tmp_path / "logs", tmp_path / "work"
    logs.mkdir()
    (logs / "a.log").write_bytes(b"x" * 10)
    for i in range(4):
        (work / f"r{i}").mkdir(parents=True)
        (work / f"r{i}" / "model.pt").write_bytes(b"w" * 60)
    job = run.Job("a", ["true"], [f"r{i}" for i in range(4)] + ["gone"], None, {})
    bins, left = run.collect_files([job], work, logs, limit=130, parts=2)
    assert [len(b) for b in bins] == [3, 2]  # log + two checkpoints, then two
    assert left == [] and "output gone missing" in job.notes
    bins, left = run.collect_files([job], work, logs, limit=130, parts=1)
    assert left == ["outputs/r2/model.pt", "outputs/r3/model.pt"]


def _fake_sapien(folder: Path) -> Path:
    """A wheel laid out as SAPIEN's, with the parts the slim recipe drops or stubs."""
    folder.mkdir(parents=True, exist_ok=True)
    cp = f"cp{sys.version_info.major}{sys.version_info.minor}"  # pip installs it here
    path = folder / f"sapien-3.0.3-{cp}-{cp}-manylinux_2_28_x86_64.whl"
    info, oidn = "sapien-3.0.3.dist-info", "sapien/oidn_library/"
    files = {"sapien/__init__.py": "KEPT = True\n", "sapien/include/physx/PxPhysics.h": "x" * 5000,
             "sapien/sensor/__init__.py": "", "sapien/sensor/assets/patterns/d415.png": "p" * 9000,
             "sapien/vulkan_library/libvulkan.1.3.290.dylib": "m" * 100,
             "sapien/vulkan_library/libvulkan.so.1.3.224": "kept",
             oidn + "libOpenImageDenoise.so.2.0.1": "not an elf", oidn +
             "libOpenImageDenoise_core.so.2.0.1": "c" * 20000,
             oidn + "libOpenImageDenoise_device_cuda.so.2.0.1": "g" * 300,
             f"{info}/METADATA": "Metadata-Version: 2.1\nName: sapien\nVersion: 3.0.3\n",
             f"{info}/WHEEL": "Wheel-Version: 1.0\nRoot-Is-Purelib: false\n"
                              f"Tag: {cp}-{cp}-manylinux_2_28_x86_64\n"}
    with zipfile.ZipFile(path, "w") as z:
        for name, text in files.items():
            z.writestr(name, text)
        z.writestr(f"{info}/RECORD", "".join(f"{n},,\n" for n in files) + f"{info}/RECORD,,\n")
    return path


@pytest.mark.skipif(not (shutil.which("cc") or shutil.which("gcc")), reason="no C compiler")
def test_slim_sapien_drops_what_never_loads_and_stubs_the_denoiser(tmp_path):
    """The slim wheel keeps the package, drops headers, sensor patterns, the macOS loader and
    OIDN's CUDA device, replaces the denoiser by shared libraries of the same sonames that
    export what libsvulkan2 imports, and its RECORD matches what is in it (pip installs it)."""
    slim = _module("slim")
    src = _fake_sapien(tmp_path / "whl")
    out = slim.slimmed(src, tmp_path / "whl" / "slim")
    names = set(zipfile.ZipFile(out).namelist())
    assert "sapien/__init__.py" in names and "sapien/vulkan_library/libvulkan.so.1.3.224" in names
    assert not any(n.startswith(("sapien/include/", "sapien/sensor/assets/")) or
                   n.endswith(".dylib") or "device_cuda" in n for n in names)
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "-q",
                    "--target", str(target), str(out)], check=True, timeout=120)
    lib = target / "sapien" / "oidn_library"
    stub = subprocess.run(["nm", "-D", "--defined-only", str(lib / "libOpenImageDenoise.so.2.0.1")],
                          capture_output=True, text=True, check=True).stdout
    for fn in ("oidnNewCUDADevice", "oidnNewFilter", "oidnExecuteFilter", "oidnGetDeviceError"):
        assert f" T {fn}" in stub, fn
    core = ctypes.CDLL(str(lib / "libOpenImageDenoise_core.so.2.0.1"), ctypes.RTLD_LOCAL)
    assert core is not None  # loads as _oidn_tricks loads it, before the API library
    api = ctypes.CDLL(str(lib / "libOpenImageDenoise.so.2.0.1"), ctypes.RTLD_LOCAL)
    api.oidnNewCUDADevice.restype = ctypes.c_void_p
    assert api.oidnNewCUDADevice(None, None, 0) is None  # no device: SAPIEN reports, not crashes
    assert slim.slimmed(src, tmp_path / "whl" / "slim") == out  # built once
    with pytest.raises(slim.SlimError, match="no slimming recipe"):
        slim.slimmed(_wheel(tmp_path / "other"), tmp_path / "other" / "slim")
