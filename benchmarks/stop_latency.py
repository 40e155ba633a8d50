"""How fast ``train.py`` answers a scheduler's SIGTERM at the paper's size, and when its first ETA appears.

Runs ``train.py --algo pearlplus --env AntVelMeta-v0`` with the YAML's paper-size entry (3x300 networks, 3x200 encoder,
meta-batch 16 x 256 rows, 2,000 gradient steps an iteration), only its initial collection shortened
(``num_initial_steps``) so that the gradient steps start within a minute, in a child process with one torch thread.
It prints the seconds from the start to the first ETA line, sends SIGTERM ``--sigterm-after`` seconds after that line
(inside the first iteration's gradient steps), and prints the seconds from the SIGTERM to the process's exit, its
exit status and what ``interrupted.json`` says. A scheduler kills after its grace period (docker 10 s, Kubernetes and
SLURM 30 s): the stop must land well within it.

    python benchmarks/stop_latency.py [--sigterm-after 20] [--initial-steps 40] [--folder /tmp/stop_latency]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sigterm-after", type=float, default=20.0, help="seconds after the first ETA line")
    parser.add_argument("--initial-steps", type=int, default=40, help="num_initial_steps per training task")
    parser.add_argument("--folder", default="/tmp/stop_latency", help="the run folder root (-f)")
    args = parser.parse_args()
    command = [
        sys.executable,
        str(ROOT / "train.py"),
        "--algo",
        "pearlplus",
        "--env",
        "AntVelMeta-v0",
        "-f",
        args.folder,
        "--num-threads",
        "1",
        "--seed",
        "0",
        "-params",
        f"num_initial_steps:{args.initial_steps}",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    start = time.monotonic()
    child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=ROOT)
    eta_at: float | None = None
    sent_at: float | None = None
    lines: queue.Queue[str] = queue.Queue()

    def read_lines() -> None:
        for line in child.stdout or []:
            lines.put(line.rstrip("\n"))

    threading.Thread(target=read_lines, daemon=True).start()
    seen: list[str] = []
    exited: float | None = None
    while exited is None or not lines.empty():
        if exited is None and child.poll() is not None:
            exited = time.monotonic()
        try:
            line = lines.get(timeout=0.05)
        except queue.Empty:
            line = None
        if line is not None:
            seen.append(line)
            if eta_at is None and line.startswith("ETA of the whole run"):
                eta_at = time.monotonic()
                print(f"first ETA {eta_at - start:.0f} s after the start: {line}", flush=True)
            if line.startswith(("So far:", "First iteration:", "Received", "Stopped by", "Training:")):
                print(f"  [{time.monotonic() - start:5.0f} s] {line[:220]}", flush=True)
        if eta_at is not None and sent_at is None and time.monotonic() - eta_at >= args.sigterm_after:
            child.send_signal(signal.SIGTERM)
            sent_at = time.monotonic()
            print(f"SIGTERM sent {sent_at - start:.0f} s after the start", flush=True)
    if sent_at is not None and exited is not None:
        print(f"exit status {child.returncode}; {exited - sent_at:.1f} s from SIGTERM to exit")
    else:
        print(f"exit status {child.returncode}; no SIGTERM sent (no ETA line)")
    for line in seen:
        if line.startswith(("Stopped by", "Saving")):
            print(f"  {line[:300]}")
    for record in Path(args.folder).glob("pearlplus/AntVelMeta-v0_*/interrupted.json"):
        print(f"{record}: {json.loads(record.read_text())}")
    print(f"CPU: {platform.processor() or platform.machine()}, one torch thread")


if __name__ == "__main__":
    main()
