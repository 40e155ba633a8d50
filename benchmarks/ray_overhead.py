"""Wall time of ``python -m pearl_paper.reproduce run`` with ``--backend local`` against ``--backend ray`` (docs/scale.md).

Each repeat runs the same command once per backend, alternating, into fresh results folders: the whole command
(interpreter start, planning, and for Ray: starting a local Ray, the trial actors, the Tune loop, shutting Ray down),
as a user sees it. The load average before each command is printed beside it (the machine may be shared).

    python benchmarks/ray_overhead.py                       # one smoke run (safe-point, alpha-0.1, seed 0), 3 repeats
    python benchmarks/ray_overhead.py --variants alpha-0 alpha-0.1 alpha-1 alpha-5 --families safe-point \\
        safe-point-crash5 --jobs 2 --repeats 1             # the 8 runs of the smoke safe-point experiment
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def timed_run(backend: str, args: argparse.Namespace, results_dir: Path) -> float:
    command = [sys.executable, "-m", "pearl_paper.reproduce", "run", "safe-point", "--budget", "smoke"]
    command += ["--seeds", args.seeds, "--family", *args.families, "--variants", *args.variants]
    command += ["--results-dir", str(results_dir), "--backend", backend, "--jobs", str(args.jobs)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    start = time.perf_counter()
    proc = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"{backend} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--families", nargs="+", default=["safe-point"])
    parser.add_argument("--variants", nargs="+", default=["alpha-0.1"])
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    times: dict[str, list[float]] = {"local": [], "ray": []}
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(args.repeats):
            for backend in ("local", "ray"):
                load = os.getloadavg()[0]
                elapsed = timed_run(backend, args, Path(tmp) / f"{backend}{repeat}")
                times[backend].append(elapsed)
                print(f"repeat {repeat} {backend:5s}: {elapsed:6.1f} s (load average {load:.2f} before)", flush=True)
    local, ray = statistics.median(times["local"]), statistics.median(times["ray"])
    print(f"median: local {local:.1f} s, ray {ray:.1f} s, overhead {ray - local:+.1f} s ({ray / local:.2f}x)")


if __name__ == "__main__":
    main()
