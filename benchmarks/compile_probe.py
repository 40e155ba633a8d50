"""torch.compile on this CPU, probed: three critics of the `cpu` preset's size (2x128 ReLU, 28 inputs: Walker2D-vel's
observation, action and latent) forward and backward on 1,024 rows (8 tasks x 128), one thread, eager against
``torch.compile`` (inductor), in interleaved rounds. Prints the medians and the compile time (a cold compile fills
inductor's on-disk cache; a second run is warm).

Then the whole step: the bare PEARL+ step of ``benchmarks/throughput.py`` at the cpu size, eager against the same step
with its loss (every forward pass, the encoder, the frozen-critic passes) compiled; backward runs through the compiled
graph, the fused Adam and the Polyak update stay eager.

    python -m benchmarks.compile_probe [--rounds 7] [--steps 100]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch as th
import torch.nn as nn

from benchmarks.throughput import SIZES, BareStep

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
    print(
        f"critics: eager {e:.2f} ms, compiled {c:.2f} ms a pass (medians of {args.rounds} interleaved rounds of {args.steps})"
    )
    print(f"critics: eager / compiled {e / c:.2f}; compile {compile_s:.1f} s")

    th.manual_seed(0)
    plain = BareStep(SIZES["cpu"], prior=True)
    th.manual_seed(0)
    with_compiled_loss = BareStep(SIZES["cpu"], prior=True)
    start = time.perf_counter()
    loss = th.compile(with_compiled_loss.loss)
    with_compiled_loss.update(loss())
    compile_s = time.perf_counter() - start

    def compiled_step() -> None:
        with_compiled_loss.update(loss())

    steps = max(args.steps // 5, 1)
    for fn in (plain.step, compiled_step):
        timed(fn, 3)
    eager, fast = [], []
    for _ in range(args.rounds):
        eager.append(timed(plain.step, steps))
        fast.append(timed(compiled_step, steps))
    e, c = statistics.median(eager), statistics.median(fast)
    print(f"bare PEARL+ step: eager {e:.2f} ms, loss compiled {c:.2f} ms (medians of {args.rounds} rounds of {steps})")
    print(f"bare PEARL+ step: eager / compiled {e / c:.2f}; compile {compile_s:.1f} s")


if __name__ == "__main__":
    main()
