"""The prepared GPU-machine run on this CPU in seconds: pack ``tiny.json``, run it, show.

Before spending device minutes: the tiny spec's setup job (it makes the trainings' data
from the travelled synthetic collection, test/synthetic.py), two 2-step trainings on it and
one job that sleeps past its 3 s limit on purpose go
through the same pack.py and run.py as a real spec; the summary shows rc 0 for the
trainings and the overrun stopped and marked timed out. test/test_device_run.py asserts it.

Usage: python bench/device/dry_run.py [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--keep", type=Path, default=None,
                   help="work here and keep it (default: a temporary folder, removed)")
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="w2e_dry_") as tmp:
        base = a.keep or Path(tmp)
        sys.path.insert(0, str(REPO / "test"))
        from synthetic import synthetic_data

        synthetic_data(obs_per_cat=2, per_obs=16, num_points=256).save_shard(
            base / "root" / "data" / "device_tiny" / "shard-00000.npz")
        py = sys.executable
        r = subprocess.run([py, str(HERE / "pack.py"), str(HERE / "tiny.json"),
                            "--root", str(base / "root"), "--out", str(base / "pack")])
        if r.returncode:
            return r.returncode
        subprocess.run([py, str(HERE / "run.py"), "--pack", str(base / "pack"), "--out",
                        str(base / "OUT"), "--deadline-s", "50", "--reserve-s", "5",
                        "--work", str(base / "work"), "--site", str(base / "site")])
        with tarfile.open(base / "OUT" / "results.tar.gz") as tar:
            print("\n".join(sorted(tar.getnames())))
        summary = json.loads((base / "OUT" / "summary.json").read_text())
        for j in summary.get("setup", []) + summary["jobs"]:
            print(f"{j['name']:10s} {j['status']:10s} rc {j['rc']} {j['seconds']} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
