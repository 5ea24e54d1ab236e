"""The environment: the batched TorchRL env with its action grid, observation, metrics, reward terms and oracle.

The env's public names are importable from here: ``from mrchaos.env import EnvConfig, TangramEnv``.
"""

from mrchaos.env.tangram import (
    ROBOT_FAILURES,
    EnvConfig,
    NoiseConfig,
    OracleTargets,
    TangramEnv,
)

__all__ = ["EnvConfig", "NoiseConfig", "OracleTargets", "ROBOT_FAILURES", "TangramEnv"]
