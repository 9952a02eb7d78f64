"""The allocator setting: freed tensors stay mapped, so reusing them costs no page faults."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

_PROBE = """
import resource, sys
import torch
from w2e_ros.core.infra.allocator import keep_freed_memory
took = keep_freed_memory() if sys.argv[1] == "kept" else False
for _ in range(3):  # 64 MiB: above glibc's default mmap threshold; the heap grows twice
    torch.ones(16 << 20).sum()
faults = []
for _ in range(11):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    torch.ones(16 << 20).sum()
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(took, sorted(faults)[5])
"""


def _faults(mode: str, **env: str) -> tuple[bool, int]:
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True,
                         check=True, env={**os.environ, **env}).stdout.split()
    return out[0] == "True", int(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_kept_memory_is_reused_without_page_faults():
    took, kept = _faults("kept")
    _, default = _faults("default")
    assert took
    # the median call: by default each 64 MiB tensor is mmapped and faulted in again (16k
    # 4 KiB pages); kept, the heap's pages are reused (a rare call still grows the heap)
    assert default > 10_000, default
    assert kept < 1_000, kept


def test_the_environment_switch_leaves_the_defaults():
    took, _ = _faults("kept", W2E_DEFAULT_MALLOC="1")
    assert not took
