"""Gymnasium environments of iiwa-torch (see issue: reaching env)."""


def register_envs() -> None:
    """Register the environment ids with gymnasium (filled in by the env module)."""
