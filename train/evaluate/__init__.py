"""Compare a trained policy with the analytic and the gradient IK on the same held-out goals.

    python -m train.evaluate --model train/policies/ppo_reach --goals 1000 --seed 0 --out reports/ppo_reach

``--env-kwargs key=value ...`` overrides the env options of the policy's config (values are
YAML), e.g. ``--env-kwargs collision=terminate`` to evaluate a policy trained without
collision checks on the default env (collision-free goals).

``--model`` is a run directory of ``train.train`` (or a shipped policy folder) holding
``model.zip``, ``config.yaml`` and, if the run normalised observations, ``vecnormalize.pkl``.
The goals are the FK of ``--goals`` configurations drawn within the joint limits with
``--seed`` (a stream separate from the training's), every arm starting at home.

Methods, each on every goal:

- ``policy``: the deterministic policy, closed loop for the env's 50 steps (2.5 s at
  dt = 0.05 s), no early stop: the final error says whether it reached the goal and stayed;
- ``controller`` (residual policies, :class:`train.residual.ResidualDLSPolicy`, only): the same
  policy with its learned correction set to zero, i.e. the DLS step and its safety layer alone:
  what the network adds is the difference between the two rows;
- ``analytic_ik``: ``iiwa_torch.ik.analytic.iiwa_solve`` (arm-angle sweep, within limits),
  nearest solution to home. It solves the full pose: for position goals it is given the
  pose the goal was drawn from (a harder problem than the position alone);
- ``gradient_ik``: ``iiwa_torch.ik.solve`` from home, position-only for position goals.

The IK answers are end configurations, not motions: their "steps to reach" is the number
of env steps a straight full-speed joint move from home needs, and their path length the
straight-line joint distance. Collisions: the capsule model of ``iiwa_torch.collision`` in the
env's world (``GoalSet.world()``: its floor and, for ``IiwaReachObstacles-v0``, each goal's own
obstacles, which both IK solvers are given too; with ``collision="off"``, the preset's floor at
z = 0); the policy is checked at every step of its rollout (and at its final configuration
alone), the IK at its solution. Outputs in ``--out``: ``report.json`` (keys in
docs/training.md), ``report.md``, ``final_q.npz`` (each method's final joint angles, rad) and
PNG plots (``rollouts_obstacles.png`` for an env with obstacles).
"""

from .command import evaluate, load_policy, main, read_compare
from .methods import METHODS, controller_alone, ik_world, run_ik, run_policy
from .metrics import ORIENTATION_TOL, TOLERANCES, collision_metrics, number_spacing, summarise
from .plots import make_plots, picture_goals
from .report import verdict, write_markdown

__all__ = ["evaluate", "load_policy", "main", "read_compare", "METHODS", "controller_alone", "ik_world", "run_ik",
           "run_policy", "ORIENTATION_TOL", "TOLERANCES", "collision_metrics", "number_spacing", "summarise",
           "make_plots", "picture_goals", "verdict", "write_markdown"]
