"""CPU instructions per env step and per reset, counted by valgrind: noise-free on a shared machine.

    python benchmarks/step_instructions.py [--steps 2000] [IiwaReach-v0 IiwaReachPose-v0 ...]

Timings on this machine's 2 shared cores swing between runs (benchmarks/results/log.md); an instruction count
does not. For each id, the same script runs twice under ``valgrind --tool=cachegrind
--cache-sim=no``: once with ``--steps`` random-action steps through ``gymnasium.make`` (a
reset when an episode ends), once with none. The difference over the step count is the
cost of a step (its share of resets included). Each valgrind run takes about a minute.
Needs valgrind (``apt install valgrind``).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported


def run_steps(env_id: str, steps: int) -> None:
    """The measured body: warm up, then ``steps`` random-action steps."""
    import gymnasium as gym
    import numpy as np
    import torch

    import envs  # noqa: F401  (registers the ids)

    torch.set_num_threads(1)
    env = gym.make(env_id)
    env.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1, 1, (16, 7)).astype(np.float32)
    for i in range(200 + steps):  # the first 200 warm every path up in both runs
        _, _, terminated, truncated, _ = env.step(actions[i % 16])
        if terminated or truncated:
            env.reset()


def instructions(env_id: str, steps: int) -> int:
    command = ["valgrind", "--tool=cachegrind", "--cache-sim=no", "--cachegrind-out-file=/dev/null",
               sys.executable, __file__, "--child", env_id, "--steps", str(steps)]
    out = subprocess.run(command, capture_output=True, text=True, check=True).stderr
    return int(re.search(r"I\s+refs:\s+([\d,]+)", out).group(1).replace(",", ""))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ids", nargs="*", default=["IiwaReach-v0"])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        run_steps(args.child, args.steps)
        return
    if shutil.which("valgrind") is None:
        sys.exit("valgrind is not installed (apt install valgrind)")
    for env_id in args.ids:
        per_step = (instructions(env_id, args.steps) - instructions(env_id, 0)) / args.steps
        print(f"{env_id}: {per_step:,.0f} instructions per step (resets included), {args.steps:,} steps")


if __name__ == "__main__":
    main()
