"""Training, resuming and evaluating with ``device: cuda``: the env on the CPU, the policy and the
update on the GPU. Marked ``cuda`` and skipped, with the reason, on a machine without one
(``benchmarks/workstation.py`` runs them where there is one)."""

from pathlib import Path

import pytest
import torch

from mrchaos.cli.train import main as train_main
from mrchaos.env.tangram import EnvConfig, TangramEnv
from mrchaos.learn.checkpoint import load_checkpoint
from mrchaos.learn.config import load_config
from mrchaos.learn.evaluate import policy_actor
from mrchaos.learn.policy import build_actor_critic
from mrchaos.tasks.sampler import MixConfig, TaskConfig

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "conf" / "smoke.yaml"

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(
        not torch.cuda.is_available(), reason="needs a CUDA device (torch.cuda.is_available() is False)"
    ),
]


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_a_cuda_run_trains_resumes_and_keeps_the_cuda_rng(tmp_path, precision):
    args = [str(SMOKE), f"runs_dir={tmp_path}", "device=cuda", f"precision={precision}", "checkpoint.every=1"]
    assert train_main([*args, "collector.total_frames=512", "--eval", "0"]) == 0
    run = tmp_path / "smoke"
    saved = load_checkpoint(run / "checkpoints" / "last.pt")
    assert "cuda" in saved["rng"], "a CUDA run's checkpoint keeps the CUDA generators' state"
    assert train_main(["--resume", str(run), "collector.total_frames=640", "--eval", "8"]) == 0
    after = load_checkpoint(run / "checkpoints" / "last.pt")
    assert after["frames"] == 640 and after["iteration"] == saved["iteration"] + 1


def test_a_policy_on_the_gpu_acts_in_an_env_on_the_cpu():
    cfg = load_config(SMOKE)
    env = TangramEnv(EnvConfig(num_worlds=4, task=TaskConfig(mix=MixConfig(chaos=1.0, cache=0.0))), seed=0)
    policy = build_actor_critic(cfg.policy, env.grid, env.view, env.action_spec).get_policy_operator().to("cuda")
    td = env.reset()
    action = policy_actor(policy)(env, td)
    assert action.device == env.device and action.shape[0] == 4
    env.step(td.set("action", action))
