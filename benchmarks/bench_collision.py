"""Self + floor clearance of an arm's capsule model: iiwa-torch batched against coal and pybullet.

    python benchmarks/bench_collision.py [--quick] [--robot panda]

Ours: ``clearance(chain, q)`` on a batch of configurations (FK included), one thread (and the
compiled float64 row again on two), float64 and float32, by each of its two paths for such a
batch: the compiled kernel (numba, the default when installed) and the torch ops
(``compiled.ENABLED`` switched off, as ``IIWA_TORCH_NUMBA=0`` does; also what any query with
gradients runs). Peers, on the same capsules and pairs (the iiwa 14's preset model: 3 self pairs,
3 capsule-floor pairs; ``--robot panda``: pybullet_data's Panda with the capsules
``capsule_fit.urdf_capsules`` fits to its meshes, 31 self pairs and the floor pairs): coal (FCL's
successor, C++) and pybullet (``getClosestPoints``), called from a Python loop over a subset of the
configurations. The peers get their capsule poses precomputed (our FK, outside the timing), so
their times are their distance queries alone: the ratios favour them. Writes results/collision.json
and .md (``collision_panda`` with ``--robot panda``).
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported

import numpy as np  # noqa: E402
import torch  # noqa: E402
from common import Robot, markdown_table, save, timeit  # noqa: E402

from iiwa_torch import compiled  # noqa: E402
from iiwa_torch.capsule_fit import urdf_capsules  # noqa: E402
from iiwa_torch.collision import clearance, pairwise_clearance, robot_capsules  # noqa: E402
from iiwa_torch.runtime import machine_info  # noqa: E402


def capsule_poses(chain, caps, q: torch.Tensor):
    """Per configuration and capsule: centre (3,), rotation taking z to the axis (3, 3), length."""
    frames = chain.fk_all(q)[:, list(caps.frames)].numpy()  # (N, K, 4, 4)
    pts = caps.points.numpy()
    a = np.einsum("nkij,kj->nki", frames[..., :3, :3], pts[:, 0]) + frames[..., :3, 3]
    b = np.einsum("nkij,kj->nki", frames[..., :3, :3], pts[:, 1]) + frames[..., :3, 3]
    axis = b - a
    length = np.linalg.norm(axis, axis=-1)
    z = np.where(length[..., None] > 0, axis / np.maximum(length, 1e-300)[..., None], [0.0, 0, 1.0])  # a sphere: any
    helper = np.where(np.abs(z[..., :1]) < 0.9, [1.0, 0, 0], [0, 1.0, 0])
    x = np.cross(z, helper)
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    rot = np.stack([x, np.cross(z, x), z], -1)
    return (a + b) / 2, rot, length


def quaternion(rot: np.ndarray) -> list[float]:
    """(x, y, z, w) of a rotation matrix whose trace is not near -1 (true here: z maps to the axis)."""
    w = np.sqrt(max(1.0 + np.trace(rot), 1e-12)) / 2
    return [(rot[2, 1] - rot[1, 2]) / (4 * w), (rot[0, 2] - rot[2, 0]) / (4 * w), (rot[1, 0] - rot[0, 1]) / (4 * w), w]


def time_ours(chain, caps, q: torch.Tensor, rows: list) -> dict:
    """``clearance`` on ``q`` by each path and dtype: seconds per configuration, keyed "<path> <dtype>";
    a table row each (the torch path's with fk_all's time for scale) appended to ``rows``."""
    batch, ours, enabled = q.shape[0], {}, compiled.ENABLED
    paths = (["compiled"] if enabled else []) + ["torch"]
    for path in paths:
        compiled.ENABLED = path == "compiled"
        for dtype in (torch.float64, torch.float32):
            qd = q.to(dtype)
            seconds = timeit(lambda qd=qd: clearance(chain, qd, capsules=caps), repeats=5)
            key = f"{path} {dtype}".replace("torch.", "")
            ours[key] = seconds / batch
            note = ""
            if path == "torch":
                fk = timeit(lambda qd=qd: chain.fk_all(qd), repeats=5)
                note = f"for scale, fk_all (every 4x4 frame) alone {fk / batch * 1e9:,.0f}"
            rows.append([f"iiwa-torch, {key}", batch, f"{seconds / batch * 1e9:,.0f}", note])
            print(" | ".join(map(str, rows[-1])), flush=True)
    compiled.ENABLED = enabled
    if enabled and (os.cpu_count() or 1) > 1:  # the compiled kernel over 2 threads (CLEARANCE_THREADS_BATCH)
        torch.set_num_threads(2)
        seconds = timeit(lambda: clearance(chain, q, capsules=caps), repeats=5)
        torch.set_num_threads(1)
        ratio = ours["compiled float64"] * batch / seconds
        rows.append(["iiwa-torch, compiled float64, 2 threads", batch, f"{seconds / batch * 1e9:,.0f}",
                     f"{ratio:.2f}x its 1-thread time"])
        print(" | ".join(map(str, rows[-1])), flush=True)
    return ours


def coal_runner(radii: list, centre: np.ndarray, rot: np.ndarray, length: np.ndarray, pair_idx: list):
    """coal's distance over every configuration and pair, as ``run() -> (configs, pairs)`` distances."""
    import coal

    subset = len(centre)
    shapes = [coal.Capsule(r, float(length[0, k])) for k, r in enumerate(radii)]
    floor = coal.Halfspace(np.array([0.0, 0.0, 1.0]), 0.0)
    ident = coal.Transform3s()
    poses = [[coal.Transform3s(rot[n, k], centre[n, k]) for k in range(len(radii))] for n in range(subset)]
    request, result = coal.DistanceRequest(), coal.DistanceResult()

    def run_coal() -> np.ndarray:
        out = np.empty((subset, len(pair_idx)))
        for n in range(subset):
            pose = poses[n]
            for p, (i, j) in enumerate(pair_idx):
                other, other_pose = (floor, ident) if j is None else (shapes[j], pose[j])
                out[n, p] = coal.distance(shapes[i], pose[i], other, other_pose, request, result)
        return out

    return run_coal


def pybullet_runner(client: int, radii: list, centre: np.ndarray, rot: np.ndarray, length: np.ndarray,
                    pair_idx: list):  # fmt: skip
    """pybullet's ``getClosestPoints`` in ``client`` over every configuration and pair, as ``run()``."""
    import pybullet as pb

    subset = len(centre)
    bodies = [
        pb.createMultiBody(
            0,
            pb.createCollisionShape(pb.GEOM_CAPSULE, radius=r, height=float(length[0, k]), physicsClientId=client),
            physicsClientId=client,
        )
        for k, r in enumerate(radii)
    ]
    plane = pb.createMultiBody(
        0, pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=client), physicsClientId=client
    )
    quats = [[quaternion(rot[n, k]) for k in range(len(radii))] for n in range(subset)]
    positions = centre.tolist()

    def run_pybullet() -> np.ndarray:
        out = np.empty((subset, len(pair_idx)))
        for n in range(subset):
            for k, body in enumerate(bodies):
                pb.resetBasePositionAndOrientation(body, positions[n][k], quats[n][k], physicsClientId=client)
            for p, (i, j) in enumerate(pair_idx):
                other = plane if j is None else bodies[j]
                hits = pb.getClosestPoints(bodies[i], other, 100.0, physicsClientId=client)
                out[n, p] = min(h[8] for h in hits)
        return out

    return run_pybullet


def compare(name: str, run, ref: np.ndarray, ours: dict, rows: list, payload: dict) -> None:
    """A peer's agreement with ``ref`` on separated pairs and its time per configuration against ours."""
    subset = len(ref)
    values = run()
    apart = ref > 1e-3  # penetration depths are defined differently; compare separated pairs
    agree = float(np.abs(values - ref)[apart].max())
    per = timeit(run, min_time=0.0, repeats=5) / subset  # median of 5 passes over the subset
    payload[f"{name}_max_abs_diff_m"] = agree
    ratios = {key: per / seconds for key, seconds in ours.items()}
    note = "ours " + ", ".join(f"{key} {ratio:,.1f}x" for key, ratio in ratios.items())
    rows.append([name, subset, f"{per * 1e9:,.0f}", f"{note} faster; max diff {agree:.1e} m"])
    print(" | ".join(map(str, rows[-1])), flush=True)
    payload[f"{name}_s_per_config"] = per
    payload[f"speedup_vs_{name}"] = ratios


def arm(name: str):
    """``(chain, capsules)``: the iiwa 14 preset and its model, or a pybullet_data URDF arm and the
    capsules fitted to its collision meshes."""
    robot = Robot(name)
    if robot.path is None:
        return robot.chain, robot_capsules(robot.chain)
    return robot.chain, urdf_capsules(robot.chain, robot.path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="20,000 configurations, 200 for the peers")
    parser.add_argument("--robot", default="iiwa14", help="iiwa14 (default) or panda (pybullet_data's URDF)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    batch, subset = (20_000, 200) if args.quick else (100_000, 2_000)
    chain, caps = arm(args.robot)
    q = chain.random_q(batch, generator=torch.Generator().manual_seed(0))
    pairs = pairwise_clearance(chain, q[:1], capsules=caps).pairs
    rows, payload = [], {"robot": args.robot, "batch": batch, "peer_subset": subset, "pairs": pairs,
                         "machine": machine_info()}  # fmt: skip
    ours = time_ours(chain, caps, q, rows)

    qs = q[:subset]
    ref = pairwise_clearance(chain, qs, capsules=caps).distance.numpy()  # (subset, P)
    poses = capsule_poses(chain, caps, qs)
    radii = caps.radii.tolist()
    index = {name: k for k, name in enumerate(caps.names)}
    pair_idx = [(index[a], None if b == "floor" else index[b]) for a, b in pairs]
    import pybullet as pb

    client = pb.connect(pb.DIRECT)
    peers = {
        "coal": coal_runner(radii, *poses, pair_idx),
        "pybullet": pybullet_runner(client, radii, *poses, pair_idx),
    }
    for name, run in peers.items():
        compare(name, run, ref, ours, rows, payload)
    pb.disconnect(client)
    payload["ours_s_per_config"] = ours
    payload["loadavg_after"] = list(os.getloadavg())
    floor = sum(b == "floor" for _, b in pairs)
    md = (
        f"# Self + floor clearance, {args.robot} capsule model ({len(pairs) - floor} self pairs + {floor} floor "
        "pairs), 1 thread\n\n"
        + markdown_table(["method", "configs", "ns/config", "note"], rows)
        + f"\nMachine: {payload['machine']}; load average after the run: {payload['loadavg_after']}\n"
    )
    print(save("collision" if args.robot == "iiwa14" else f"collision_{args.robot}", payload, md))


if __name__ == "__main__":
    main()
