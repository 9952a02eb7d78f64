"""How many intra-op threads torch uses for a block of work."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run a block with at most ``n`` intra-op threads. Work made of many small ops (the
    approach check on the CPU, a heads-only fit) gains nothing from a second thread but
    synchronisation, and on a busy CPU OpenMP's spinning threads make each op wait: the
    approach check of 2048 candidates took 0.5-6.5 s with 2 threads and 50 ms with 1, with
    other processes busy on the 2-core CPU; 100 heads-only fine-tuning steps 6.7 s with 2
    threads and 1.1 s with 1."""
    before = torch.get_num_threads()
    torch.set_num_threads(min(n, before))
    try:
        yield
    finally:
        torch.set_num_threads(before)
