"""Run a pack's jobs on the GPU machine inside one call's limit, and bring back one tarball.

The machine is lent for minutes and a call is killed at its ``timeout_s`` with everything it
started, so this runner keeps its own, earlier deadline: every job (each (method, seed), each
training run) is its own process group with a wall-clock limit of its own, capped by the
global ``--deadline-s`` less the seconds kept for packing up; a job that overruns is stopped
(SIGTERM, then SIGKILL) and what it wrote stays. The travelled wheels are installed first
with pip and no index (``--target``, about 10 s for SAPIEN), then the pack's setup jobs run
(what the jobs need made there, such as a collection too large to travel), and the jobs
start only if every setup job ended rc 0. At the end ``$OUT/results.tar.gz``
holds ``summary.json`` (per job: rc, seconds, timed out), the runner's and every job's log,
and the jobs' outputs, up to the size the tool brings back (outputs that do not fit go to
``results-1.tar.gz`` ..., and past ``--max-parts`` are left out and named in the summary);
``summary.json`` is also written beside it.

Standard library only: it runs before anything is installed, on the machine's Python 3.12.

Usage (on the machine, from the checkout's root):
    python3 bench/device/run.py --pack device_pack --deadline-s 540 [--parallel 7]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

REPO = Path(__file__).resolve().parents[2]
MIB = 1 << 20


@dataclass
class Job:
    """One process of the pack, and what became of it."""

    name: str
    argv: list[str]
    outputs: list[str]
    timeout_s: float | None
    env: dict[str, str]
    proc: subprocess.Popen | None = None
    log: IO[bytes] | None = None
    start: float = 0.0
    end: float = 0.0
    deadline: float = 0.0
    rc: int | None = None
    timed_out: bool = False
    killed_at: float | None = None
    status: str = "pending"  # pending | running | done | timed_out | not_started | skipped
    notes: list[str] = field(default_factory=list)


class Runner:
    """Starts up to ``parallel`` jobs at a time and stops each at its own deadline."""

    def __init__(self, jobs: list[Job], work: Path, logs: Path, env: dict[str, str],
                 parallel: int, end: float, grace_s: float, say) -> None:
        self.jobs, self.work, self.logs, self.env = jobs, work, logs, env
        self.parallel, self.end, self.grace_s, self.say = parallel, end, grace_s, say

    def command(self, job: Job) -> list[str]:
        """``w2e`` is the CLI of this checkout, ``python`` this interpreter: the same spec
        runs here and on the machine, where no ``w2e`` script is installed."""
        head, rest = job.argv[0], job.argv[1:]
        if head == "w2e":
            return [sys.executable, "-m", "w2e_ros.cli", *rest]
        if head in ("python", "python3"):
            return [sys.executable, *rest]
        return job.argv

    def start(self, job: Job, now: float) -> None:
        job.log = open(self.logs / f"{job.name}.log", "wb")  # noqa: SIM115 (closed in finish)
        job.start = now
        job.deadline = min(now + job.timeout_s, self.end) if job.timeout_s else self.end
        job.proc = subprocess.Popen(self.command(job), cwd=self.work, stdout=job.log,
                                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    env={**self.env, **job.env}, start_new_session=True)
        job.status = "running"
        self.say(f"start {job.name} (pid {job.proc.pid}, {job.deadline - now:.0f} s left)")

    def stop(self, job: Job, now: float) -> None:
        """SIGTERM to the job's process group, SIGKILL after the grace period."""
        assert job.proc is not None
        sig = signal.SIGTERM if job.killed_at is None else signal.SIGKILL
        if job.killed_at is None:
            job.killed_at = now
            job.timed_out = True
            self.say(f"overrun {job.name}: stopping it after {now - job.start:.1f} s")
        with contextlib.suppress(ProcessLookupError):
            os.killpg(job.proc.pid, sig)

    def finish(self, job: Job, now: float) -> None:
        assert job.proc is not None and job.log is not None
        job.rc, job.end = job.proc.returncode, now
        job.log.close()
        with contextlib.suppress(ProcessLookupError):  # stragglers of its group, if any
            os.killpg(job.proc.pid, signal.SIGKILL)
        job.status = "timed_out" if job.timed_out else "done"
        self.say(f"end {job.name}: rc {job.rc}, {job.end - job.start:.1f} s"
                 + (" (timed out)" if job.timed_out else ""))

    def run(self) -> None:
        pending = list(self.jobs)
        running: list[Job] = []
        while pending or running:
            now = time.monotonic()
            for job in list(running):
                assert job.proc is not None
                if job.proc.poll() is not None:
                    running.remove(job)
                    self.finish(job, now)
                elif now >= job.deadline and (job.killed_at is None
                                              or now >= job.killed_at + self.grace_s):
                    self.stop(job, now)
            while pending and len(running) < self.parallel and now < self.end:
                job = pending.pop(0)
                self.start(job, now)
                running.append(job)
            if pending and now >= self.end and not running:
                for job in pending:
                    job.status = "not_started"
                    job.notes.append("the global deadline came before a slot")
                    self.say(f"not started {job.name}: no time left")
                pending.clear()
            time.sleep(0.1)


def install_wheels(pack: Path, wheels: list[str], site: Path, say) -> tuple[int, float, str]:
    """pip install the travelled wheels into ``site`` without an index or dependencies."""
    if not wheels:
        return 0, 0.0, ""
    t = time.monotonic()
    site.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps",
           "--no-compile", "--no-cache-dir", "--upgrade", "--target", str(site),
           *(str(pack / "wheels" / w) for w in wheels)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    dt = time.monotonic() - t
    say(f"wheels: {len(wheels)} installed into {site} in {dt:.1f} s (rc {r.returncode})")
    return r.returncode, dt, (r.stdout + r.stderr)[-4000:]


def link_inputs(pack: Path, inputs: list[str], work: Path) -> None:
    """The jobs see each input at the relative path they name, inside ``work``: hard links
    (copies across file systems), not symbolic ones, which the collections' ``rglob`` and the
    benchmark's run discovery would not follow below the top."""
    for rel in inputs:
        src, dst = pack / "inputs" / rel, work / rel
        if dst.exists():
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.is_dir():
            shutil.copytree(src, dst, copy_function=link_or_copy)
        else:
            link_or_copy(src, dst)


def link_or_copy(src: str | Path, dst: str | Path) -> None:
    """Hard link where the file system allows (inputs cost no space), else a copy."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def host_info() -> dict[str, Any]:
    info: dict[str, Any] = {"python": platform.python_version(), "cpus": os.cpu_count(),
                            "machine": platform.machine(), "node": platform.node()}
    if shutil.which("nvidia-smi"):
        r = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True)
        info["gpus"] = r.stdout.strip().splitlines()
    return info


def collect_files(jobs: list[Job], work: Path, logs: Path, limit: int, parts: int
                  ) -> tuple[list[list[tuple[Path, str]]], list[str]]:
    """Logs and outputs as (file, name in the tarball), in at most ``parts`` tarballs of at
    most ``limit`` bytes each before compression: the logs in the first, then the outputs
    smallest first, each into the first tarball it fits; the names of those that fit none.

    The tool brings back 8 files of 16 MiB: seven checkpoints of 4 MB need a second part."""
    first = [(p, f"logs/{p.name}") for p in sorted(logs.iterdir())]
    bins: list[list[tuple[Path, str]]] = [first]
    room = [limit - sum(p.stat().st_size for p, _ in first)]
    outs: list[tuple[int, Path, str]] = []
    seen: set[str] = set()
    for job in jobs:
        for rel in job.outputs:
            base = work / rel
            if not base.exists():
                job.notes.append(f"output {rel} missing")
            paths = [base] if base.is_file() else sorted(base.rglob("*")) if base.is_dir() else []
            for p in paths:
                name = f"outputs/{p.relative_to(work)}"
                if p.is_file() and name not in seen:
                    seen.add(name)
                    outs.append((p.stat().st_size, p, name))
    left_out = []
    for size, p, name in sorted(outs, key=lambda t: (t[0], t[2])):
        i = next((i for i, r in enumerate(room) if size <= r), None)
        if i is None and len(bins) < parts and size <= limit:
            bins.append([])
            room.append(limit)
            i = len(bins) - 1
        if i is None:
            left_out.append(name)
            continue
        bins[i].append((p, name))
        room[i] -= size
    return bins, left_out


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pack", type=Path, default=REPO / "device_pack")
    p.add_argument("--out", type=Path, default=os.environ.get("OUT"),
                   help="where results.tar.gz goes (default $OUT, the tool's return folder)")
    p.add_argument("--deadline-s", type=float, default=None,
                   help="every job ends by then (default: the pack's, else 540 s for a "
                        "600 s call)")
    p.add_argument("--reserve-s", type=float, default=15.0,
                   help="seconds before the deadline kept for stopping jobs and the tarball")
    p.add_argument("--grace-s", type=float, default=5.0, help="SIGTERM to SIGKILL")
    p.add_argument("--parallel", type=int, default=None,
                   help="jobs at a time (default: the pack's, else the CPU count)")
    p.add_argument("--work", type=Path, default=None,
                   help="the jobs' working folder (default: a new temporary one)")
    p.add_argument("--site", type=Path, default=Path(tempfile.gettempdir()) / "w2e_site",
                   help="where the travelled wheels are installed")
    p.add_argument("--max-tar-mib", type=float, default=15.5,
                   help="what one tarball may hold before compression (the tool brings "
                        "back files of at most 16 MiB)")
    p.add_argument("--max-parts", type=int, default=4,
                   help="tarballs at most: results.tar.gz, then results-1.tar.gz ... for "
                        "outputs that do not fit the first (the tool brings back 8 files)")
    return p


def _job_env(manifest: dict, site: Path, parallel: int) -> dict[str, str]:
    """Every job's environment: the travelled wheels and this checkout importable, the cores
    shared out between the jobs running at once."""
    threads = max(1, (os.cpu_count() or 1) // parallel)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": str(threads),
           **manifest.get("env", {})}
    env["PYTHONPATH"] = os.pathsep.join(
        [*([str(site)] if manifest["wheels"] else []), str(REPO),
         *([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])])
    return env


def _skip(jobs: list[Job], why: str) -> None:
    for job in jobs:
        job.status = "skipped"
        job.notes.append(why)


def _job_record(j: Job, t0: float) -> dict[str, Any]:
    return {"name": j.name, "argv": j.argv, "status": j.status, "rc": j.rc,
            "timed_out": j.timed_out, "timeout_s": j.timeout_s,
            "start_s": round(j.start - t0, 2) if j.start else None,
            "seconds": round(j.end - j.start, 2) if j.end else None,
            "outputs": j.outputs, "notes": j.notes}


def _summary(manifest: dict, setup: list[Job], jobs: list[Job], t0: float, deadline: float,
             parallel: int, wheels: tuple[int, float], tarballs: list[str],
             left_out: list[str]) -> dict:
    rc, wheel_s = wheels
    return {
        "pack": manifest["name"], "commit": manifest.get("commit"), "host": host_info(),
        "deadline_s": deadline, "parallel": parallel, "wheels_s": round(wheel_s, 2),
        "wheels_rc": rc, "seconds": round(time.monotonic() - t0, 2), "tarballs": tarballs,
        "left_out": left_out,
        "setup": [_job_record(j, t0) for j in setup],
        "jobs": [_job_record(j, t0) for j in jobs],
    }


def _write_tarballs(out: Path, stage: Path, tarballs: list[str], bins: list) -> None:
    """The summary first in results.tar.gz, then each bin's files; summary.json beside."""
    out.mkdir(parents=True, exist_ok=True)
    for i, (tarball, files) in enumerate(zip(tarballs, bins, strict=True)):
        with tarfile.open(out / tarball, "w:gz") as tar:
            if i == 0:
                tar.add(stage / "summary.json", "results/summary.json")
            for path, name in files:
                tar.add(path, f"results/{name}")
    shutil.copy(stage / "summary.json", out / "summary.json")


def main(argv: list[str] | None = None) -> int:
    p = _parser()
    a = p.parse_args(argv)
    t0 = time.monotonic()
    if a.out is None:
        p.error("--out or $OUT is needed")
    manifest = json.loads((a.pack / "pack.json").read_text())
    deadline = a.deadline_s or manifest.get("deadline_s") or 540.0
    parallel = a.parallel or manifest.get("parallel") or os.cpu_count() or 1
    reserve = min(a.reserve_s, deadline / 4)  # a short deadline still leaves jobs most of it
    work = a.work or Path(tempfile.mkdtemp(prefix="w2e_device_"))
    stage = Path(tempfile.mkdtemp(prefix="w2e_results_"))
    logs = stage / "logs"
    logs.mkdir(parents=True)
    work.mkdir(parents=True, exist_ok=True)
    runner_log = open(logs / "_runner.log", "w")  # noqa: SIM115 (closed below)

    def say(msg: str) -> None:
        line = f"[{time.monotonic() - t0:7.1f} s] {msg}"
        print(line, flush=True)
        runner_log.write(line + "\n")
        runner_log.flush()

    say(f"pack {manifest['name']} ({manifest.get('commit')}): {len(manifest['jobs'])} jobs, "
        f"{parallel} at a time, deadline {deadline:.0f} s, jobs end by {deadline - reserve:.0f} s")
    rc, wheel_s, pip_out = install_wheels(a.pack, manifest["wheels"], a.site, say)
    link_inputs(a.pack, manifest["inputs"], work)
    env = _job_env(manifest, a.site, parallel)
    setup, jobs = ([Job(j["name"], j["argv"], j["outputs"], j.get("timeout_s"),
                        j.get("env", {})) for j in manifest.get(phase, [])]
                   for phase in ("setup", "jobs"))
    end = t0 + deadline - reserve
    if rc != 0:
        say("wheels did not install: no job started\n" + pip_out)
        _skip(setup + jobs, "the wheels did not install")
    else:
        Runner(setup, work, logs, env, parallel, end, a.grace_s, say).run()
        failed_setup = [j.name for j in setup if j.rc != 0]
        if failed_setup:
            say(f"setup failed ({', '.join(failed_setup)}): no job started")
            _skip(jobs, f"setup job {', '.join(failed_setup)} did not end rc 0")
        else:
            Runner(jobs, work, logs, env, parallel, end, a.grace_s, say).run()
    bins, left_out = collect_files(setup + jobs, work, logs, int(a.max_tar_mib * MIB),
                                   a.max_parts)
    tarballs = ["results.tar.gz"] + [f"results-{i}.tar.gz" for i in range(1, len(bins))]
    summary = _summary(manifest, setup, jobs, t0, deadline, parallel, (rc, wheel_s), tarballs,
                       left_out)
    if left_out:
        say(f"left out of the tarball (over {a.max_tar_mib} MiB): {', '.join(left_out)}")
    failed = [j.name for j in setup + jobs if j.rc != 0]
    say(f"done: {len(setup + jobs) - len(failed)} of {len(setup + jobs)} jobs rc 0"
        + (f"; not: {', '.join(failed)}" if failed else ""))
    runner_log.close()
    (stage / "summary.json").write_text(json.dumps(summary, indent=1))
    _write_tarballs(a.out, stage, tarballs, bins)
    shutil.rmtree(stage, ignore_errors=True)
    return 0 if not failed else 1

if __name__ == "__main__":
    sys.exit(main())
