"""Alias kept so that ``gymnasium.make("mrchaos.gym_env:Tangram-v0")`` goes on working; the env lives in
:mod:`mrchaos.env.gymnasium_env`."""

from mrchaos.env.gymnasium_env import TangramGymEnv

__all__ = ["TangramGymEnv"]
