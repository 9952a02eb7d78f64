"""Start, stop and clean up ROS node processes without ``ros2 launch`` (plain Python, no rclpy).

Used by ``w2e_ros.bringup`` and the multi-process tests. The facts it is built around:
nodes must run under the venv's Python (the wheels set LD_LIBRARY_PATH at
start-up); a node sent SIGTERM in its first second can miss it, so stopping is TERM, wait,
TERM again, then KILL; killed nodes leave Fast DDS shared-memory files in /dev/shm.
"""

from __future__ import annotations

import argparse
import fcntl
import itertools
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path

SHM_DIR = Path("/dev/shm")
SOURCE_ROOT = Path(__file__).resolve().parents[2]
"""The directory holding the w2e_ros and sim_bridge packages."""
_SHM_PATTERNS = ("fastrtps_*", "sem.fastrtps_*")


def venv_python() -> str:
    """The Python that runs the nodes: this interpreter (the venv's when run from it)."""
    return sys.executable


def ros_env(
    domain_id: int | None = None,
    log_dir: str | os.PathLike | None = None,
    localhost_only: bool = True,
    base: dict[str, str] | None = None,
) -> dict[str, str]:
    """An environment for node processes: domain, log directory, discovery kept on this host.

    Unbuffered output so prefixed node logs arrive line by line.
    """
    env = dict(os.environ if base is None else base)
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(int(domain_id))
    if log_dir is not None:
        Path(log_dir).mkdir(parents=True, exist_ok=True)
        env["ROS_LOG_DIR"] = str(log_dir)
    if localhost_only:
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    # children import the same source tree as this process, installed or not
    root = str(SOURCE_ROOT)
    paths = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    if root not in paths:
        env["PYTHONPATH"] = os.pathsep.join([root, *paths])
    env["PYTHONUNBUFFERED"] = "1"
    return env


_DOMAIN_BASE = (os.getpid() * 7 + int(time.time() * 1000)) % 100
_DOMAIN_COUNT = itertools.count()


_DOMAIN_LOCKS: dict[int, int] = {}  # domain -> the fd of its lock file, latest last
DOMAIN_LOCKS_HELD = 8  # a process holds its latest picks only (a test session makes hundreds)
DOMAIN_LOCK_DIR = Path(tempfile.gettempdir()) / "w2e_domains"


def _claim_domain(domain: int) -> bool:
    """Hold ``domain``'s lock file (flock: freed when this process dies, by any death) until
    this process exits or has picked DOMAIN_LOCKS_HELD newer domains; False when another living
    process holds it."""
    if domain in _DOMAIN_LOCKS:
        _DOMAIN_LOCKS[domain] = _DOMAIN_LOCKS.pop(domain)  # the latest again
        return True
    try:
        DOMAIN_LOCK_DIR.mkdir(parents=True, exist_ok=True)
        fd = os.open(DOMAIN_LOCK_DIR / f"{domain}.lock", os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:
        return True  # no lock directory (read-only /tmp): the order below still spreads runs
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return False
    _DOMAIN_LOCKS[domain] = fd
    while len(_DOMAIN_LOCKS) > DOMAIN_LOCKS_HELD:
        os.close(_DOMAIN_LOCKS.pop(next(iter(_DOMAIN_LOCKS))))
    return True


def pick_domain_id() -> int:
    """A ROS domain id in [100, 199] that no other living process on this host picked (a lock
    file per domain: two test runs or benchmarks at once once shared domain 117, and one's
    client called the other's planner), and not given twice by one process until all 100 were:
    a domain used again in a process meets the Fast DDS participant ids and shared-memory
    ports of its earlier use."""
    for _ in range(100):
        domain = 100 + (_DOMAIN_BASE + 37 * next(_DOMAIN_COUNT)) % 100
        if _claim_domain(domain):
            return domain
    raise RuntimeError(f"every ROS domain 100..199 is held by another process ({DOMAIN_LOCK_DIR})")


def stop_process(proc: subprocess.Popen, timeout: float = 5.0, group: bool = True) -> int | None:
    """Stop a node: SIGTERM, wait, SIGTERM again (a node may miss one sent while starting),
    then SIGKILL. ``group``: signal the process group (the child was started with
    ``start_new_session=True``). Returns the exit code.
    """

    def send(sig: int) -> None:
        try:
            if group:
                os.killpg(proc.pid, sig)
            else:
                proc.send_signal(sig)
        except (ProcessLookupError, PermissionError):
            pass

    if proc.poll() is not None:
        return proc.returncode
    for sig, wait in ((signal.SIGTERM, timeout * 0.6), (signal.SIGTERM, timeout * 0.4)):
        send(sig)
        try:
            return proc.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            continue
    send(signal.SIGKILL)
    try:
        return proc.wait(timeout=5.0)
    except subprocess.TimeoutExpired:
        return None


def shm_files() -> set[Path]:
    """Fast DDS shared-memory segments, port and lock files currently in /dev/shm."""
    out: set[Path] = set()
    for pattern in _SHM_PATTERNS:
        out.update(SHM_DIR.glob(pattern))
    return out


def _paths_in_use(ignore_pids: Iterable[int] = ()) -> set[str]:
    """Every /dev/shm path some live process has open or mapped (so must not be removed)."""
    used: set[str] = set()
    ignore = {str(p) for p in ignore_pids}
    for pid_dir in Path("/proc").glob("[0-9]*"):
        if pid_dir.name in ignore:
            continue
        try:
            for fd in (pid_dir / "fd").iterdir():
                try:
                    target = os.readlink(fd)
                except OSError:
                    continue
                if target.startswith("/dev/shm/"):
                    used.add(target)
            used.update(path for path, _ in _shm_mapped(pid_dir))
        except (OSError, PermissionError):
            continue
    return used


def _shm_mapped(pid_dir: Path) -> list[tuple[str, bool]]:
    """(path, file removed since) of every /dev/shm mapping of one process (OSError: gone)."""
    out = []
    with open(pid_dir / "maps") as maps:
        for line in maps:
            i = line.find("/dev/shm/")
            if i >= 0:
                path = line[i:].strip()
                out.append((path.removesuffix(" (deleted)"), path.endswith(" (deleted)")))
    return out


def deleted_shm_ports() -> dict[int, list[str]]:
    """pid -> the Fast DDS shared-memory ports it maps whose files are gone.

    A participant listening on, or sending to, a port whose file was removed and made again
    exchanges nothing with the port's new owner: seen once on CI, a test's client on a deleted
    port lost its requests. The test suite prints this beside every failure."""
    out: dict[int, list[str]] = {}
    for pid_dir in Path("/proc").glob("[0-9]*"):
        try:
            ports = sorted({Path(path).name for path, removed in _shm_mapped(pid_dir)
                            if removed and Path(path).name.startswith("fastrtps_port")})
        except OSError:
            continue
        if ports:
            out[int(pid_dir.name)] = ports
    return out


_PORT_NAME = re.compile(r"fastrtps_port(\d+)")


def shm_ports_in_use() -> set[int]:
    """Fast DDS shared-memory port numbers some live process maps or holds open (its own port,
    or a peer's it writes to, the file removed or not): a new participant must not take them."""
    return {int(m.group(1)) for path in _paths_in_use()
            if (m := _PORT_NAME.fullmatch(Path(path).name))}


def _stem(path: Path) -> str:
    """The Fast DDS object a shm file belongs to: ``fastrtps_port7411`` for the port segment,
    its ``_el`` listener lock and its ``sem.…_mutex`` semaphore alike."""
    name = path.name.removeprefix("sem.")
    for suffix in ("_mutex", "_el", "_sl"):
        name = name.removesuffix(suffix)
    return name


def dead_shm_files(before: set[Path] | None = None, ignore_pids: Iterable[int] = ()) -> list[Path]:
    """Fast DDS shm files that appeared since ``before`` and no live process uses.

    A segment, its lock file and its semaphore count together: a port whose segment a survivor
    still maps but whose lock file was removed is made again by the next participant that
    takes it, and the survivor then writes into the removed copy.
    ``ignore_pids``: processes whose use does not count.
    """
    candidates = shm_files() - (before or set())
    if not candidates:
        return []
    used = _paths_in_use(ignore_pids)
    kept = {_stem(Path(path)) for path in used}
    return sorted(p for p in candidates if str(p) not in used and _stem(p) not in kept)


def clean_shm(before: set[Path] | None = None, ignore_pids: Iterable[int] = ()) -> list[Path]:
    """Remove the ``dead_shm_files``; files of other runs on this host (present in ``before``,
    or still in use) are left alone. ``ignore_pids``: processes whose use does not count (this
    one, at exit, after its ROS contexts are shut down). Returns what was removed."""
    removed = []
    for path in dead_shm_files(before, ignore_pids):
        try:
            path.unlink()
            removed.append(path)
        except OSError:
            pass
    return removed


def clean_shm_at_exit(before: set[Path] | None = None) -> None:
    """At interpreter exit, remove the shm files this process and its children left behind
    (a process that used rclpy keeps its own files mapped until it exits)."""
    import atexit

    atexit.register(lambda: clean_shm(before, ignore_pids=(os.getpid(),)))


def main(argv: list[str] | None = None) -> int:
    """``python -m w2e_ros.ros.processes clean``: remove the Fast DDS shm files of dead
    processes (what ``make clean-ros`` runs); a file some live process uses stays."""
    p = argparse.ArgumentParser(description=main.__doc__.split(":")[0].strip("`"))
    p.add_argument("action", choices=["clean"])
    p.add_argument("-n", "--dry-run", action="store_true", help="list, remove nothing")
    a = p.parse_args(argv)
    dead = dead_shm_files() if a.dry_run else clean_shm()
    for path in dead:
        print(path)
    print(f"{'would remove' if a.dry_run else 'removed'} {len(dead)} Fast DDS shm file(s) "
          "no live process uses", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
