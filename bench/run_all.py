"""Run every benchmark under bench/ in turn (`make bench`); each prints a markdown table."""

from __future__ import annotations

import shlex
import subprocess
import sys
from pathlib import Path

BENCHES = [
    "synth_speed.py", "validate_speed.py", "hand_model_speed.py", "fit_hand_speed.py",
    "bench_sfm.py", "steady_bench.py", "registration_bench.py", "accuracy.py", "catalog_bench.py",
    "contactmap_speed.py", "detect_speed.py", "core_scaling.py", "build_overhead.py",
    "scale.py --short", "build_memory.py --commit 50 200 800",
]
"""Each entry: a script under bench/ and its arguments."""


def main() -> int:
    here = Path(__file__).parent
    status = 0
    for name in BENCHES:
        print(f"\n## {name}\n", flush=True)
        script, *args = shlex.split(name)
        status |= subprocess.call([sys.executable, str(here / script), *args])
    return status


if __name__ == "__main__":
    raise SystemExit(main())
