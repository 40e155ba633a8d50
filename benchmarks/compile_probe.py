"""torch.compile on this CPU, probed: three critics of the `cpu` preset's size (2x128 ReLU, 28 inputs: Walker2D-vel's
observation, action and latent) forward and backward on 1,024 rows (8 tasks x 128), one thread, eager against
``torch.compile`` (inductor), in interleaved rounds. Prints the medians and the compile time (a cold compile fills
inductor's on-disk cache; a second run is warm).

The probe covers the critics' products only, not a whole PEARL+ step (optimizers, the frozen-critic passes, the
encoder): docs/speed.md says what it leaves open.

    python benchmarks/compile_probe.py [--rounds 7] [--steps 100]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch as th
import torch.nn as nn

ROWS, INPUTS, WIDTH, CRITICS = 1024, 28, 128, 3


def critic() -> nn.Module:
    return nn.Sequential(nn.Linear(INPUTS, WIDTH), nn.ReLU(), nn.Linear(WIDTH, WIDTH), nn.ReLU(), nn.Linear(WIDTH, 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--steps", type=int, default=100, help="forward-backward passes a round")
    args = parser.parse_args()
    th.set_num_threads(1)
    th.manual_seed(0)
    critics = [critic() for _ in range(CRITICS)]
    x = th.randn(ROWS, INPUTS)

    def step() -> None:
        sum(net(x).pow(2).mean() for net in critics).backward()  # type: ignore[union-attr]

    start = time.perf_counter()
    compiled: Callable[[], None] = th.compile(step)
    compiled()
    compile_s = time.perf_counter() - start

    def timed(fn: Callable[[], None], n: int) -> float:
        start = time.perf_counter()
        for _ in range(n):
            fn()
        return (time.perf_counter() - start) / n * 1e3

    for fn in (step, compiled):
        timed(fn, 10)
    eager, fast = [], []
    for _ in range(args.rounds):
        eager.append(timed(step, args.steps))
        fast.append(timed(compiled, args.steps))
    e, c = statistics.median(eager), statistics.median(fast)
    print(f"eager {e:.2f} ms, compiled {c:.2f} ms a pass (medians of {args.rounds} interleaved rounds of {args.steps})")
    print(f"eager / compiled {e / c:.2f}; compile {compile_s:.1f} s")


if __name__ == "__main__":
    main()
