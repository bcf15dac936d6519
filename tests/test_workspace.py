"""Workspace volume, envelopes and dexterity: closed forms and KUKA's datasheet."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from iiwa_torch import robots
from iiwa_torch.dh import DHChain
from iiwa_torch.workspace import (
    DATASHEET,
    Section,
    dexterity,
    dexterity_map,
    envelopes,
    extent,
    frame_point,
    occupancy,
    plot_workspace,
    volume,
)

PI2 = math.pi / 2


def gen(seed=0):
    return torch.Generator().manual_seed(seed)


def planar2(l1=1.0, l2=0.5):
    return DHChain([(l1, 0, 0, 0), (l2, 0, 0, 0)], name="planar2")


def spherical_arm(l1=0.5, l2=0.3):
    """Spherical shoulder at the origin, elbow, then the wrist-centre-like frame-5 origin
    (independent of q5); full joint ranges: the reachable set is the shell |l1-l2| <= |p| <= l1+l2."""
    table = [(0, -PI2, 0, 0), (0, PI2, 0, 0), (0, PI2, l1, 0), (0, -PI2, 0, 0), (0, 0, l2, 0)]
    return DHChain(table, name="shell")


def test_planar_annulus_area():
    l1, l2 = 1.0, 0.5
    exact = math.pi * ((l1 + l2) ** 2 - (l1 - l2) ** 2)
    v = volume(planar2(l1, l2), 0.01, section="xy", n_start=1 << 19, generator=gen())
    assert v.converged
    assert v.low <= exact <= v.high
    # The half-weighted boundary is second order in h: 0.5% at h = 1 cm, far inside the bracket (+-2.5%).
    assert v.estimate == pytest.approx(exact, rel=5e-3)


def test_sphere_shell_volume_xyz_and_revolved():
    l1, l2 = 0.5, 0.3
    exact = 4 / 3 * math.pi * ((l1 + l2) ** 3 - (l1 - l2) ** 3)
    chain = spherical_arm(l1, l2)
    rz = volume(chain, 0.005, section=Section.RZ, n_start=1 << 20, generator=gen(1))
    assert rz.low <= exact <= rz.high
    assert rz.estimate == pytest.approx(exact, rel=5e-3)
    xyz = volume(chain, 0.02, section="xyz", n_start=1 << 20, max_samples=1 << 22, generator=gen(2))
    assert xyz.low <= exact <= xyz.high
    assert xyz.estimate == pytest.approx(exact, rel=2e-2)


def test_the_side_view_turns_about_the_base_axis_wherever_the_base_is():
    """A base moved sideways and tilted (a URDF arm off the world origin): rings about the world z axis
    made the shell six times too big."""
    l1, l2 = 0.5, 0.3
    exact = 4 / 3 * math.pi * ((l1 + l2) ** 3 - (l1 - l2) ** 3)
    base = torch.eye(4, dtype=torch.float64)
    base[:3, 3] = torch.tensor([1.0, -0.4, 0.3], dtype=torch.float64)
    base[:3, :3] = torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=torch.float64)  # 90 deg about x
    moved = DHChain(spherical_arm(l1, l2).dh, base=base)
    rz = volume(moved, 0.005, section=Section.RZ, n_start=1 << 20, generator=gen(1))
    assert rz.low <= exact <= rz.high and rz.estimate == pytest.approx(exact, rel=5e-3)
    reach = extent(moved, 20_000, generator=gen(3))  # the shell about the base origin: |z| and r up to l1 + l2
    assert reach.r_max == pytest.approx(l1 + l2, abs=0.01) and reach.z_max == pytest.approx(l1 + l2, abs=0.01)
    assert reach.z_min == pytest.approx(-(l1 + l2), abs=0.01)


def test_shell_envelopes_are_the_two_circles():
    l1, l2, h = 0.5, 0.3, 0.005
    occ = occupancy(spherical_arm(l1, l2), 1 << 20, h, section="rz", generator=gen(3))
    z, r_out, r_in = envelopes(occ)
    assert z.min() == pytest.approx(-(l1 + l2), abs=h) and z.max() == pytest.approx(l1 + l2, abs=h)
    mid = np.abs(z) < 0.6 * (l1 + l2)
    assert np.allclose(r_out[mid], np.sqrt((l1 + l2) ** 2 - z[mid] ** 2), atol=1.5 * h)
    hole = np.abs(z) < 0.15
    assert np.allclose(r_in[hole], np.sqrt((l1 - l2) ** 2 - z[hole] ** 2), atol=1.5 * h)
    # Off the hole the inner envelope is the axis; the ring cells next to it hold volume 2 pi r h^2,
    # so few samples land there and a 1M-sample run leaves some of the first cells unhit.
    assert np.all(r_in[np.abs(z) > l1 - l2 + h] <= 8 * h)


def test_wrist_centre_is_fixed_in_the_flange_frame():
    chain = robots.iiwa14()
    home = chain.fk_all(torch.zeros(7, dtype=torch.float64))
    assert home[5, 2, 3].item() == pytest.approx(1.180) and home[6, 2, 3].item() == pytest.approx(1.180)
    assert torch.allclose(frame_point(chain, 5), torch.tensor([0, 0, -0.126], dtype=torch.float64), atol=1e-12)
    with pytest.raises(ValueError, match="not a point of the end effector"):
        frame_point(chain, 3)  # the elbow moves with q5..q7


def test_iiwa_wrist_set_is_a_solid_of_revolution():
    # (q1 + pi, -q2, q3, -q4) puts the wrist centre on the same point, so the set at q1 = 0 is
    # invariant under a half turn and joint 1's +-170 deg sweeps it through the full circle:
    # the RZ section's ring volumes are exact for it.
    chain = robots.iiwa14()
    q = chain.random_q(100, generator=gen(10))
    flipped = q * torch.tensor([1, -1, 1, -1, 1, 1, 1], dtype=q.dtype) + torch.tensor(
        [math.pi, 0, 0, 0, 0, 0, 0], dtype=q.dtype
    )
    wrist = chain.fk_all(q)[:, 5, :3, 3]
    assert torch.allclose(chain.fk_all(flipped)[:, 5, :3, 3], wrist, atol=1e-12)


@pytest.mark.parametrize("name", ["iiwa14", "iiwa7"])
def test_datasheet_dimensions_of_the_wrist_centre(name):
    chain = robots.PRESETS[name]()
    ds = {k: v / 1000 for k, v in DATASHEET[name].items() if k != "volume"}
    home = chain.fk_all(torch.zeros(7, dtype=torch.float64))[:, 2, 3]
    assert chain.fk(torch.zeros(7, dtype=torch.float64))[2, 3].item() == pytest.approx(ds["A"], abs=1e-9)
    assert home[1].item() == pytest.approx(ds["C"], abs=1e-9)  # shoulder
    assert (home[3] - home[1]).item() == pytest.approx(ds["D"], abs=1e-9)  # shoulder to elbow
    assert (home[5] - home[3]).item() == pytest.approx(ds["E"], abs=1e-9)  # elbow to wrist centre
    ext = extent(chain, 1 << 20, point=frame_point(chain, 5), generator=gen(4))
    # Sample extremes lie inside by < 2 mm at 1M samples (the density peaks at these stretched poses).
    assert ds["B"] - 2e-3 < ext.z_max <= ds["B"] + 1e-9
    assert ds["G"] - 2e-3 < ext.r_max <= ds["G"] + 1e-9
    # F, the depth below the base: upper arm at q2 = 120 deg, forearm straight down, l_bs - l_se/2 - l_ew:
    # -0.260 m for the iiwa 7 (the datasheet's 260 mm) but -0.250 m for the iiwa 14, where the datasheet
    # says 255 mm; the 5 mm are not in the kinematics (no joint range or length gives them).
    depth = ds["C"] - ds["D"] / 2 - ds["E"]
    assert -depth - 2e-3 < -ext.z_min <= -depth + 1e-9
    assert abs(-depth - ds["F"]) == pytest.approx(0.0 if name == "iiwa7" else 0.005, abs=1e-9)


def test_datasheet_volume_is_the_wrist_centre_envelope():
    chain = robots.iiwa14()
    wrist = volume(chain, 0.01, section="rz", point=frame_point(chain, 5), n_start=1 << 20, generator=gen(5))
    flange = volume(chain, 0.02, section="rz", n_start=1 << 20, max_samples=1 << 21, generator=gen(6))
    # The wrist centre's set measures 1.89 m^3 (bracket +-2.5% at h = 1 cm, estimate within 0.5%);
    # KUKA's 1.8 m^3 is 5% lower (the iiwa 7: 1.76 vs 1.7, 3.5%), so the datasheet volume is of
    # the wrist centre, rounded down or with a margin; the flange's set (3.3 m^3) is far off.
    assert 1.85 < wrist.estimate < 1.92
    assert 0 < wrist.estimate / DATASHEET["iiwa14"]["volume"] - 1 < 0.07
    assert flange.estimate / DATASHEET["iiwa14"]["volume"] > 1.7


def test_dexterity_planar_closed_form():
    l1, l2 = 1.0, 0.5
    q = planar2(l1, l2).random_q(200, generator=gen(7))
    d = dexterity(planar2(l1, l2), q, position_only=True)
    exact = l1 * l2 * q[:, 1].sin().abs()
    assert torch.allclose(d.manipulability, exact, atol=1e-12)
    # The singular values of the 2-link planar Jacobian: its Gram matrix's eigenvalues.
    jxy = torch.stack(
        [
            torch.stack([-l1 * q[:, 0].sin() - l2 * q.sum(1).sin(), -l2 * q.sum(1).sin()], -1),
            torch.stack([l1 * q[:, 0].cos() + l2 * q.sum(1).cos(), l2 * q.sum(1).cos()], -1),
        ],
        -2,
    )
    eig = torch.linalg.eigvalsh(jxy.transpose(-1, -2) @ jxy)
    assert torch.allclose(d.sigma_min, eig[:, 0].clamp(min=0).sqrt(), atol=1e-9)
    assert torch.allclose(d.condition, (eig[:, 1] / eig[:, 0]).sqrt(), rtol=1e-6)
    stretched = dexterity(planar2(l1, l2), torch.zeros(2, dtype=torch.float64), position_only=True)
    assert stretched.manipulability.item() == 0 and stretched.condition.item() == math.inf


def test_an_exact_singularity_of_a_urdf_arm_has_an_infinite_condition():
    """Its sigma_min is rounding (1e-16), not 0: the condition was 1.8e16 on the Panda at q = 0."""
    pybullet_data = pytest.importorskip("pybullet_data")
    panda = robots.from_urdf(f"{pybullet_data.getDataPath()}/franka_panda/panda.urdf", end_link="panda_hand")
    d = dexterity(panda, torch.zeros(7, dtype=torch.float64))  # joints 1 and 3 on one line
    assert d.condition.item() == math.inf and d.sigma_min.item() < 1e-15
    assert math.isfinite(dexterity(panda, panda.random_q(generator=gen(4))).condition.item())


def test_volume_refuses_a_cap_below_its_start():
    with pytest.raises(ValueError, match=r"max_samples \(10\) must be at least n_start \(1000\)"):
        volume(planar2(), 0.05, section="xy", n_start=1000, max_samples=10)


def test_plot_workspace_checks_its_own_arguments_before_sampling(tmp_path):
    arm = robots.iiwa14()
    for kwargs, error, message in [
        ({"datasheet": {"A": 1}}, ValueError, "datasheet must be a DATASHEET entry"),
        ({"datasheet": "iiwa14"}, ValueError, "datasheet must be a DATASHEET entry"),
        ({"seed": "a"}, TypeError, "seed must be an integer"),
        ({"manipulability_path": tmp_path / "no" / "m.png"}, FileNotFoundError, "does not exist"),
    ]:
        with pytest.raises(error, match=message):
            plot_workspace(arm, tmp_path / "side.png", n_samples=1 << 30, **kwargs)  # would sample for minutes


def test_dexterity_takes_a_real_bool():
    arm = robots.iiwa14()
    with pytest.raises(TypeError, match="position_only"):
        dexterity(arm, arm.random_q(2), position_only="no")  # a non-empty string was True


def test_dexterity_iiwa_singular_and_shapes():
    chain = robots.iiwa14()
    q = chain.random_q(4, 5, generator=gen(8))
    d = dexterity(chain, q)
    assert d.manipulability.shape == (4, 5) and (d.manipulability > 0).all()
    jac = chain.jacobian(q)
    assert torch.allclose(d.manipulability, torch.linalg.det(jac @ jac.transpose(-1, -2)).sqrt(), rtol=1e-8)
    home = dexterity(chain, torch.zeros(7, dtype=torch.float64))  # stretched: joint axes 1, 3, 5, 7 aligned
    assert home.sigma_min.item() < 1e-12 and home.manipulability.item() < 1e-12


def test_dexterity_map_bins_match_direct_evaluation():
    chain = planar2()
    dm = dexterity_map(chain, 4000, 0.1, position_only=True, generator=gen(9))
    assert dm.count.sum() == 4000
    # w = l1 l2 |sin q2| and r^2 = l1^2 + l2^2 + 2 l1 l2 cos q2: w is a function of r, so within a
    # cell at radius r the mean and max approach it.
    nr = dm.count.shape[0]
    r = (np.arange(nr) + 0.5) * dm.h
    cos2 = np.clip((r**2 - 1.25) / 1.0, -1, 1)
    expect = 0.5 * np.sqrt(1 - cos2**2)
    filled = dm.count.sum(1) > 0
    mean_r = (dm.mean * dm.count).sum(1)[filled] / dm.count.sum(1)[filled]
    assert np.all(np.abs(mean_r - expect[filled]) < 0.12)
    assert np.all(dm.max <= 0.5 + 1e-12)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"h": 0.0}, "h must be a positive"),
        ({"h": float("nan")}, "h must be a positive"),
        ({"section": "side"}, "section must be one of"),
        ({"point": [0, 0]}, "point must be"),
        ({"h": 1e-4}, "use a larger h"),
    ],
)
def test_bad_input(kwargs, match):
    args = {"h": 0.05, **kwargs}
    with pytest.raises(ValueError, match=match):
        occupancy(planar2(), 10, **args)


def test_bad_counts_and_frames():
    with pytest.raises(ValueError, match="n_samples must be a positive integer"):
        occupancy(planar2(), 0, 0.05)
    with pytest.raises(ValueError, match="frame must be an integer"):
        frame_point(planar2(), 3)
    occ = occupancy(planar2(), 10, 0.05, section="xy")
    with pytest.raises(ValueError, match="different grid"):
        occupancy(planar2(), 10, 0.1, section="xy", counts=occ)
    # another point as far from the end effector: the same grid, another set's counts
    occ = occupancy(planar2(), 10, 0.05, section="xy", point=[0.1, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"counts counts the point \(0.1, 0.0, 0.0\), not \(0.0, 0.1, 0.0\)"):
        occupancy(planar2(), 10, 0.05, section="xy", point=[0.0, 0.1, 0.0], counts=occ)
    with pytest.raises(ValueError, match="RZ occupancy"):
        envelopes(occ)
