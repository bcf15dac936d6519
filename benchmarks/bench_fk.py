"""FK, end position, all frames, Jacobian and FK forward+backward: iiwa-torch against its peers, one run.

    python benchmarks/bench_fk.py [--quick] [--robot NAME] [--threads 1 2] [--max-batch N]

Peers measured in the same run on the same arm (default the iiwa 14 preset; ``--robot`` takes a
preset's name or ``panda``, ``xarm6``, ``kuka_iiwa``: pybullet_data's URDF files read by
``robots.from_urdf``): pytorch_kinematics (batched torch) on the same URDF (a preset's
``to_urdf`` export, else the file itself), roboticstoolbox's C++ ``ETS.eval`` and pinocchio
(C++, called once per configuration from Python), a plain batched 4x4-matmul torch chain
(our small-batch kernel, forced on every size) and the floor: a torch copy of the output's
size. Prints per-configuration times and ratios; writes results/fk.json and results/fk.md
(``fk_<robot>.*`` for another arm).
"""

from __future__ import annotations

import argparse
import functools
import os
import subprocess
import sys

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported

import numpy as np  # noqa: E402
import torch  # noqa: E402
from common import Robot, command, machine, markdown_table, save, timeit  # noqa: E402

from iiwa_torch import kinematics  # noqa: E402

ROBOT = CHAIN = GEOMETRY = None  # set by setup(--robot)
SIZES = {
    "fk": [1, 1_000, 100_000, 1_000_000],
    "position": [1, 1_000, 100_000, 1_000_000],
    "fk_all": [1, 1_000, 100_000],
    "jacobian": [1, 1_000, 10_000, 100_000],
    "fk_backward": [1, 1_000, 100_000],
}


def ours(op: str, q: torch.Tensor):
    if op == "fk_backward":
        qg = q.clone().requires_grad_()
        return lambda: CHAIN.fk(qg)[..., :3, 3].sum().backward()
    return lambda: getattr(CHAIN, op)(q)


def matmul_chain(op: str, q: torch.Tensor):
    """The 4x4-product kernel on any batch size (what a plain torch chain does)."""
    if op != "fk":
        return None
    g = CHAIN.geometry(q.dtype)
    return lambda: kinematics.end_pose_matmul(g, q)


def setup(name: str) -> None:
    """The arm of this run and its geometry in both dtypes."""
    global ROBOT, CHAIN, GEOMETRY
    ROBOT = Robot(name)
    CHAIN = ROBOT.chain
    GEOMETRY = {dtype: CHAIN.geometry(dtype) for dtype in (torch.float32, torch.float64)}


# Compiled lazily, on first call (once per dtype).
FUSED = torch.compile(lambda q: kinematics.end_pose(GEOMETRY[q.dtype], q), dynamic=True)


def compiled(op: str, q: torch.Tensor):
    """Our elementwise kernel through ``torch.compile`` (inductor), for FK from batch 1,000 up."""
    if op != "fk" or q.shape[0] < 1_000:
        return None
    return lambda: FUSED(q)


@functools.cache
def pk_chain(dtype: torch.dtype):
    import pytorch_kinematics as pk

    return pk.build_serial_chain_from_urdf(ROBOT.urdf.encode(), ROBOT.end_link).to(dtype=dtype)


def pytorch_kinematics(op: str, q: torch.Tensor):
    serial = pk_chain(q.dtype)
    if op == "fk":
        return lambda: serial.forward_kinematics(q).get_matrix()
    if op == "position":  # pk has no position-only path: the pose's translation
        return lambda: serial.forward_kinematics(q).get_matrix()[..., :3, 3]
    if op == "fk_all":
        return lambda: [t.get_matrix() for t in serial.forward_kinematics(q, end_only=False).values()]
    if op == "jacobian":
        return lambda: serial.jacobian(q)
    qg = q.clone().requires_grad_()
    return lambda: serial.forward_kinematics(qg).get_matrix()[..., :3, 3].sum().backward()


def pk_fk_difference() -> float:
    """Largest difference between pytorch_kinematics' end pose and ours (float64, 64 random q)."""
    q = CHAIN.random_q(64, generator=torch.Generator().manual_seed(1))
    return float((pytorch_kinematics("fk", q)().double() - CHAIN.fk(q)).abs().max())


def floor(op: str, q: torch.Tensor):
    """A plain copy of a tensor the size of the output: the memory-bound limit."""
    n = CHAIN.n_joints
    shape = {"fk": (4, 4), "position": (3,), "fk_all": (n + 1, 4, 4), "jacobian": (6, n)}.get(op)
    if shape is None:
        return None
    out = torch.empty(q.shape[0], *shape, dtype=q.dtype)
    return out.clone


def per_call_cpp(q64: torch.Tensor) -> dict:
    """roboticstoolbox ETS.eval and pinocchio, one configuration per call (float64)."""
    res = {}
    qs = q64.numpy()
    try:
        import roboticstoolbox  # noqa: F401

        ets = ROBOT.rtb_ets()
        res["roboticstoolbox ETS.eval"] = timeit(lambda: [ets.eval(x) for x in qs]) / len(qs)
    except ImportError:
        pass
    try:
        import pinocchio as pin

        model = pin.buildModelFromXML(ROBOT.urdf)
        data, frame = model.createData(), model.getFrameId(ROBOT.end_link)
        # the file's joints off the chain (the Panda's fingers) held at their neutral values
        rows = [model.joints[model.getJointId(name)].idx_q for name in CHAIN.joint_names]
        full = np.tile(pin.neutral(model), (len(qs), 1))
        full[:, rows] = qs

        def run():
            for x in full:
                pin.framesForwardKinematics(model, data, x)
                data.oMf[frame].homogeneous  # noqa: B018

        res["pinocchio framesForwardKinematics"] = timeit(run) / len(qs)
    except ImportError:
        pass
    return res


_PEAK_SCRIPT = """
import re, sys, torch
sys.path.insert(0, {here!r})
from common import Robot
def status(key):
    return int(re.search(key + r":\\s+(\\d+) kB", open("/proc/self/status").read()).group(1)) / 1024
chain = Robot({robot!r}).chain
chain.fk(torch.zeros(10, chain.n_joints))
base = status("VmRSS")
open("/proc/self/clear_refs", "w").write("5")  # reset the high-water mark VmHWM
q = torch.rand({batch}, chain.n_joints).mul_(2).sub_(1)
chain.fk(q)
print(status("VmHWM") - base)
"""


def peak_memory_mb(batch: int) -> float:
    """Peak resident memory (MB) of one float32 FK of ``batch`` configurations in a fresh
    process, above its size after imports (Linux ``VmHWM``); includes the input and output."""
    here = os.path.dirname(os.path.abspath(__file__))
    script = _PEAK_SCRIPT.format(batch=batch, robot=ROBOT.name, here=here)
    return float(subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout)


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small sizes, one thread (a smoke run)")
    parser.add_argument("--robot", default="iiwa14", help="a preset's name, or panda, xarm6, kuka_iiwa (URDF)")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts (default 1 2)")
    parser.add_argument("--max-batch", type=int, default=None, help="skip larger batches (on a loaded machine)")
    return parser.parse_args()


RUNNERS = {
    "iiwa-torch": ours,
    "pytorch_kinematics": pytorch_kinematics,
    "matmul chain": matmul_chain,
    "torch.compile": compiled,
    "copy floor": floor,
}
HEADERS = [
    "op",
    "batch",
    "dtype",
    "threads",
    "ours ns/config",
    "pytorch_kinematics ns/config",
    "speed-up vs pk",
    "speed-up vs matmul chain",
    "speed-up vs torch.compile",
    "ours / copy floor",
]


def measure(op: str, q: torch.Tensor, threads: int) -> tuple[dict, list]:
    """Every runner that has ``op`` on ``q``: the record (seconds per call) and its table row."""
    batch = q.shape[0]
    slow = batch >= 1_000_000
    times = {}
    for name, make in RUNNERS.items():
        fn = make(op, q)
        if fn is not None:
            times[name] = timeit(fn, min_time=0.0 if slow else 0.2, repeats=3 if slow else 5)
    rec = {"op": op, "batch": batch, "dtype": str(q.dtype).split(".")[1], "threads": threads, "seconds_per_call": times}
    t = times["iiwa-torch"]
    pk_ratio = times["pytorch_kinematics"] / t
    floor_t = times.get("copy floor")  # none for forward+backward
    mm, tc = times.get("matmul chain"), times.get("torch.compile")
    row = [
        op,
        batch,
        rec["dtype"],
        threads,
        f"{t / batch * 1e9:,.0f}",
        f"{times['pytorch_kinematics'] / batch * 1e9:,.0f}",
        f"**{pk_ratio:.1f}x**",
        f"{mm / t:.1f}x" if mm else "",
        f"{tc / t:.1f}x" if tc else "",
        f"{t / floor_t:.1f}x" if floor_t else "-",
    ]
    print(" | ".join(str(c) for c in row), flush=True)
    return rec, row


def markdown(fk_gap: float, rows: list, cpp: dict, single: float, mem: float | None, info: dict) -> str:
    """The batched table, the per-configuration table, the peak memory (if measured) and the machine."""
    source = "the preset's `to_urdf` export" if ROBOT.path is None else f"`{ROBOT.path.parent.name}/{ROBOT.path.name}`"
    md = (
        f"`{command(__file__)}`: "
        f"FK of {ROBOT.name} ({CHAIN.n_joints} joints, end link `{ROBOT.end_link}`; every peer reads {source}; "
        f"pytorch_kinematics' float64 FK differs from ours by at most {fk_gap:.1e}):\n\n"
    )
    md += markdown_table(HEADERS, rows)
    md += "\nPer configuration, one call each, float64, 1 thread:\n\n"
    md += markdown_table(
        ["library", "µs per configuration"],
        [[k, f"{v * 1e6:.2f}"] for k, v in cpp.items()]
        + [["iiwa-torch fk, batch 1 (one call)", f"{single * 1e6:.1f}"]],
    )
    if mem is not None:
        md += (
            f"\nPeak memory of one float32 FK of 1,000,000 configurations: {mem:.0f} MB"
            f" (input {4 * CHAIN.n_joints} MB and output 64 MB included)\n"
        )
    return md + f"\nMachine: {info}\n"


def main() -> None:
    args = parse_args()
    setup(args.robot)
    largest = 1_000 if args.quick else args.max_batch or max(max(bs) for bs in SIZES.values())
    sizes = {op: [b for b in bs if b <= largest] for op, bs in SIZES.items()}
    fk_gap = pk_fk_difference()
    g = torch.Generator().manual_seed(0)
    records, rows = [], []
    for n_threads in [1] if args.quick else args.threads:
        torch.set_num_threads(n_threads)
        for dtype in (torch.float32, torch.float64):
            for op, batches in sizes.items():
                for batch in batches:
                    rec, row = measure(op, CHAIN.random_q(batch, generator=g, dtype=dtype), n_threads)
                    records.append(rec)
                    rows.append(row)
    torch.set_num_threads(1)
    cpp = per_call_cpp(CHAIN.random_q(1000, generator=g))
    one = CHAIN.random_q(1, generator=g)[0]
    single = timeit(lambda: CHAIN.fk(one))
    mem = None if largest < 1_000_000 else peak_memory_mb(1_000_000)
    info = machine()
    md = markdown(fk_gap, rows, cpp, single, mem, info)
    print(md)
    name = "fk" if args.robot == "iiwa14" else f"fk_{args.robot}"
    path = save(
        f"{name}_quick" if args.quick else name,
        {
            "robot": args.robot,
            "fk_max_diff_vs_pytorch_kinematics": fk_gap,
            "machine": info,
            "records": records,
            "per_config_cpp_s": cpp,
            "fk_batch1_s": single,
            "peak_memory_mb_fk_1e6_f32": mem,
        },
        md,
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
