"""Training, evaluation and tuning of stable-baselines3 agents on the envs (the ``rl`` extra)."""

from iiwa_torch.checks import require

for _module in ("stable_baselines3", "yaml"):  # first: the modules here import them
    require(_module, "rl")
