"""Shared plumbing for the benchmarks: timing, machine facts, JSON/markdown output.

Each benchmark sets ``OMP_WAIT_POLICY=PASSIVE`` before it imports torch: with another
process busy on the cores, OpenMP's spin-wait makes 2-thread ops wait on spinning threads
(benchmarks/results/busy.md).
"""

from __future__ import annotations

import json
import os
import re
import statistics
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def timeit(fn, *, min_time: float = 0.2, repeats: int = 5, max_calls: int | None = None,
           clock=time.perf_counter) -> float:
    """Median over ``repeats`` of the mean seconds per call, each repeat running ``fn`` for at least
    ``min_time`` seconds (or ``max_calls`` calls) of ``clock`` (wall time; or e.g. ``time.process_time``,
    the CPU time, which other jobs on the cores do not inflate). A warm-up call first, then a timed one
    that sets how many calls run between two reads of the clock (about a millisecond's worth, as the
    standard library's ``timeit`` loops): a microsecond call is not timed with the clock's own cost
    (``process_time`` takes ~0.6 µs a read here)."""
    fn()
    start = time.perf_counter()
    fn()
    one = time.perf_counter() - start
    per_read = max(1, min(int(1e-3 / max(one, 1e-9)), max_calls or 1_000_000))
    samples = []
    for _ in range(repeats):
        calls, start = 0, clock()
        while True:
            for _ in range(per_read):
                fn()
            calls += per_read
            elapsed = clock() - start
            if elapsed >= min_time or (max_calls is not None and calls >= max_calls):
                break
        samples.append(elapsed / calls)
    return statistics.median(samples)


class Clock:
    """Wall and CPU (process) seconds since it was made. The machine is shared: CPU time is what the
    code itself used, wall time also holds the waits for the cores."""

    def __init__(self) -> None:
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def stop(self) -> tuple[float, float]:
        """``(wall, cpu)`` seconds since the clock was made."""
        return time.perf_counter() - self.wall, time.process_time() - self.cpu


def save(name: str, payload: dict, markdown: str) -> Path:
    """Write ``results/<name>.json`` and ``results/<name>.md``; return the JSON path."""
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(payload, indent=2) + "\n")
    (RESULTS / f"{name}.md").write_text(markdown)
    return path


def machine() -> dict:
    """``runtime.machine_info()`` plus ``IIWA_TORCH_NUMBA`` (whether the compiled paths were on).
    Imports torch when called, so a script that first runs child processes can call it after them."""
    from iiwa_torch.runtime import machine_info

    return machine_info() | {"IIWA_TORCH_NUMBA": os.environ.get("IIWA_TORCH_NUMBA", "unset (on)")}


def command(script: str) -> str:
    """The command line of this run: ``python benchmarks/<script's file name> <its arguments>``."""
    return " ".join([f"python benchmarks/{Path(script).name}", *sys.argv[1:]])


def markdown_table(headers: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


#: Arms read from pybullet_data's URDF files by ``robots.from_urdf``: name -> (file, end link).
URDF_ROBOTS = {
    "panda": ("franka_panda/panda.urdf", "panda_hand"),
    "xarm6": ("xarm/xarm6_robot.urdf", None),
    "kuka_iiwa": ("kuka_iiwa/model.urdf", None),
}


class Robot:
    """A benchmark's arm: ``chain``, the URDF text every peer loads (a preset's ``to_urdf``
    export, else the file itself), its ``end_link``, and ``path``, the file (None for a preset)."""

    def __init__(self, name: str) -> None:
        from iiwa_torch import robots

        self.name = name
        if name in robots.PRESETS:
            from iiwa_torch.urdf import to_urdf

            self.chain, self.path, self.end_link = robots.PRESETS[name](), None, "tool0"
            self.urdf = to_urdf(self.chain)
        elif name in URDF_ROBOTS:
            import pybullet_data

            file, end = URDF_ROBOTS[name]
            self.path = Path(pybullet_data.getDataPath()) / file
            self.chain = robots.from_urdf(self.path, end_link=end)
            self.end_link = self.chain.link_names[-1] if end is None else end
            self.urdf = self.path.read_text()
        else:
            raise ValueError(f"--robot must be one of {sorted(robots.PRESETS) + sorted(URDF_ROBOTS)}, got {name!r}")

    def rtb_ets(self):
        """roboticstoolbox's ETS of the same arm with its limits: a preset's DH table, else the URDF file read by
        roboticstoolbox itself (each ``package://NAME`` resolved to the folder NAME beside the file)."""
        import roboticstoolbox as rtb

        chain = self.chain
        if self.path is None:
            links = [
                rtb.RevoluteDH(a=a, alpha=al, d=d, offset=o, qlim=[lo, hi])
                for (a, al, d, o), lo, hi in zip(chain.dh.tolist(), *chain.limits.tolist())
            ]
            return rtb.DHRobot(links, base=chain.base.numpy(), tool=chain.tool.numpy()).ets()
        from roboticstoolbox.models.URDF.URDFRobot import URDF_file
        from xacrodoc import packages

        names = set(re.findall(r"package://([^/]+)/", self.urdf))
        packages.update_package_cache({name: str(self.path.parent / name) for name in names})
        # <transmission> blocks dropped: roboticstoolbox cannot read xarm6's (they hold no kinematics)
        elinks, name, _ = URDF_file(
            self.path, patch=lambda text: re.sub(r"<transmission.*?</transmission>", "", text, flags=re.S)
        )
        return rtb.Robot(elinks, name=name).ets(end=self.end_link)
