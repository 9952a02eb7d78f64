"""The failure diagnostic: a Fast DDS port still mapped after its file was removed is named,
with the process that maps it; a live port file is not."""

from __future__ import annotations

import mmap
import os

from w2e_ros.ros.processes import SHM_DIR, deleted_shm_ports


def _mapped(name: str) -> tuple[int, mmap.mmap]:
    fd = os.open(SHM_DIR / name, os.O_CREAT | os.O_RDWR, 0o600)
    os.ftruncate(fd, 4096)
    return fd, mmap.mmap(fd, 4096)


def test_a_port_whose_file_is_gone_is_named_with_its_process():
    gone, kept = f"fastrtps_port9{os.getpid()}", f"fastrtps_port8{os.getpid()}"
    fd1, m1 = _mapped(gone)
    fd2, m2 = _mapped(kept)
    try:
        (SHM_DIR / gone).unlink()
        ports = deleted_shm_ports().get(os.getpid(), [])
        assert gone in ports and kept not in ports
    finally:
        for fd, m in ((fd1, m1), (fd2, m2)):
            m.close()
            os.close(fd)
        (SHM_DIR / kept).unlink(missing_ok=True)
    assert gone not in deleted_shm_ports().get(os.getpid(), [])  # unmapped: no longer held
