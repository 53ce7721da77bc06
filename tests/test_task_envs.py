"""Tasks for other environments: PettingZoo parallel envs (``task=simple_spread``) and VMAS scenarios
(``task=vmas_navigation``) in the experiment's key contract, and QMIX trained on each through
``mcrs-train task=...``, then evaluated (``mcrs-eval policy=<run>``, beside the random baseline) and
exported (``mcrs-export``)."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import check_env_specs

from mcrs.experiment.config import ConfigError
from mcrs.experiment.training.task import check_env, make_task, with_agent_state
from mcrs.tasks.pettingzoo import PettingZooTask

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::UserWarning")
REPO = Path(__file__).resolve().parents[1]
CPU = torch.device("cpu")


class Corridor(ParallelEnv):
    """Two agents step along a corridor of 4 cells; an agent's dict observation carries its action mask
    (no step left at cell 0); the episode terminates when both reach cell 3 (early). No ``state()``."""

    metadata = {"name": "corridor_v0"}  # noqa: RUF012

    def __init__(self) -> None:
        self.possible_agents = ["a_0", "a_1"]
        self.pos: dict[str, int] = {}

    def observation_space(self, agent: str) -> spaces.Dict:
        return spaces.Dict(
            {"observation": spaces.Box(0, 3, (1,), np.float32), "action_mask": spaces.MultiBinary(2)}
        )

    def action_space(self, agent: str) -> spaces.Discrete:
        return spaces.Discrete(2)  # 0: left, 1: right

    def _obs(self) -> dict[str, Any]:
        return {
            a: {"observation": np.array([p], np.float32), "action_mask": np.array([p > 0, 1], np.int8)}
            for a, p in self.pos.items()
        }

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        self.agents = list(self.possible_agents)
        self.pos = {a: 0 for a in self.agents}
        return self._obs(), {a: {} for a in self.agents}

    def step(self, actions: dict[str, int]) -> tuple[dict, ...]:
        for a, move in actions.items():
            self.pos[a] = min(3, max(0, self.pos[a] + (1 if move else -1)))
        end = all(p == 3 for p in self.pos.values())
        obs = self._obs()
        rewards = {a: float(self.pos[a]) for a in self.agents}
        terms = {a: end for a in self.agents}
        truncs = {a: False for a in self.agents}
        if end:
            self.agents = []
        return obs, rewards, terms, truncs, {a: {} for a in terms}


def corridor() -> Corridor:
    return Corridor()


def test_simple_spread_is_a_task_whose_team_reward_is_the_agents_sum() -> None:
    task = make_task({"_target_": "mcrs.tasks.pettingzoo.PettingZooTask", "max_steps": 4,
                      "env_kwargs": {"N": 2, "max_cycles": 4}})  # fmt: skip
    assert (task.n_agents, task.n_actions, task.obs_dim, task.state_shape) == (2, 5, 12, (24,))
    env = task.make_env(3, CPU)
    check_env(task, env)
    check_env_specs(env)  # every key the env writes matches its specs' shapes, dtypes and domains
    env.set_seed(7)
    td = env.reset()
    actions = torch.tensor([[1, 2], [3, 4], [0, 1]])
    td.set(("agents", "action"), actions)
    out = env.step(td)["next"]
    from mpe2 import simple_spread_v3

    direct = simple_spread_v3.parallel_env(N=2, max_cycles=4)
    direct.reset(seed=7 + 1)  # env 1 of the batch: seed + 1
    _, rewards, *_ = direct.step({"agent_0": 3, "agent_1": 4})
    assert out["reward"][1, 0].item() == pytest.approx(sum(rewards.values()), abs=1e-5)
    assert torch.allclose(out["state"][1], torch.as_tensor(direct.state(), dtype=torch.float32))
    for _ in range(3):
        td = env.step(out.set(("agents", "action"), actions))
        out = td["next"]
    assert out["truncated"].all() and not out["terminated"].any()  # max_steps: truncated, not terminated


def test_dict_observations_give_the_masks_and_an_early_end_terminates() -> None:
    task = PettingZooTask(f"{__name__}:corridor", max_steps=10)
    assert (task.obs_dim, task.n_actions, task.has_state, task.state_shape) == (1, 2, False, (2,))
    env = with_agent_state(task.make_env(2, CPU), task, 2, 8, CPU)
    td = env.reset()
    assert td["agents", "action_mask"][0].tolist() == [[False, True], [False, True]]  # no left at cell 0
    right = TensorDictModule(
        lambda mask: torch.ones(mask.shape[:-1], dtype=torch.int64),
        [("agents", "action_mask")],
        [("agents", "action")],
    )
    rollout = env.rollout(10, right, break_when_any_done=False)
    terminated = rollout["next", "terminated"].squeeze(-1)
    assert terminated[:, 2].all() and not terminated[:, :2].any()  # both at cell 3 after 3 steps
    assert torch.equal(rollout["state"][:, 1], rollout["agents", "observation"][:, 1].flatten(-2))
    assert task.episode_metrics(rollout)["episode_reward"].tolist() == [12.0, 12.0]  # (1+1)+(2+2)+(3+3)


def test_bad_task_settings_are_one_line_naming_the_field() -> None:
    for node, expected in [
        ({"reward": "max"}, r"task\.reward='max': allowed values are sum, mean"),
        ({"env": "no_such_env_module"}, r"task\.env=no_such_env_module: cannot import"),
        ({"env_kwargs": {"N": 2, "colour": 3}}, r"task\.env_kwargs: .*colour"),
    ]:
        with pytest.raises(ConfigError, match=expected) as error:
            make_task({"_target_": "mcrs.tasks.pettingzoo.PettingZooTask", **node})
        assert "\n" not in str(error.value)


def test_vmas_task_keys_sum_the_agents_rewards_and_join_their_observations() -> None:
    pytest.importorskip("vmas")
    from mcrs.tasks.vmas import VmasTask

    task = make_task(
        {"_target_": "mcrs.tasks.vmas.VmasTask", "max_steps": 4, "scenario_kwargs": {"n_agents": 2}}
    )
    assert isinstance(task, VmasTask) and (task.n_agents, task.n_actions, task.state_shape) == (
        2,
        9,
        (2 * task.obs_dim,),
    )
    env = task.make_env(3, CPU)
    check_env(task, env)
    env.set_seed(0)
    rollout = env.rollout(6, break_when_any_done=False)
    torch.testing.assert_close(rollout["next", "reward"], rollout["next", "agents", "reward"].sum(-2))
    torch.testing.assert_close(rollout["state"], rollout["agents", "observation"].flatten(-2))
    assert rollout["agents", "action_mask"].all()
    assert rollout["next", "truncated"][:, 3].all()  # StepCounter(max_steps=4)


# ------------------------------------------------------------------------------ through the command line
def _tool(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "HYDRA_FULL_ERROR": "0",
        "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
    }
    out = subprocess.run(
        [sys.executable, "-m", *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=900
    )
    assert out.returncode == 0, (out.stdout[-1500:], out.stderr[-1500:])
    return out


def _train_eval_export(tmp_path: Path, task: str, overrides: list[str]) -> dict[str, dict[str, float]]:
    run_dir = tmp_path / "run"
    _tool(["mcrs.train", f"task={task}", "algo=qmix", *overrides, "threads=1", "logger.progress_bar=false",
           "train.optimizer=adam", "train.lr=0.001", "train.batch_episodes=32", "train.target_update_episodes=100",
           f"hydra.run.dir={run_dir}"], tmp_path)  # fmt: skip
    _tool(
        [
            "mcrs.evaluate",
            f"policy={run_dir}",
            "episodes=128",
            "seed=5",
            f"hydra.run.dir={tmp_path / 'eval'}",
        ],
        tmp_path,
    )
    with (tmp_path / "eval" / "metrics.csv").open() as f:
        table = {
            row["policy"]: {k: float(v) for k, v in row.items() if k.endswith("_mean")}
            for row in csv.DictReader(f)
        }
    out = _tool(["mcrs.export_agent", str(run_dir), str(tmp_path / "agent.pt2")], tmp_path)
    assert f"on {task}" in out.stdout and (tmp_path / "agent.pt2").is_file()
    return {"trained" if name != "random" else name: values for name, values in table.items()}


@pytest.mark.slow
def test_qmix_through_mcrs_train_on_simple_spread_beats_random(tmp_path: Path) -> None:
    table = _train_eval_export(
        tmp_path, "simple_spread",
        ["train.total_env_steps=40000", "train.num_envs=8", "train.eps_anneal_steps=20000",
         "train.eval_interval=10000", "train.eval_episodes=32"],
    )  # fmt: skip
    trained, random = table["trained"]["episode_reward_mean"], table["random"]["episode_reward_mean"]
    print(f"simple_spread: trained {trained:.2f}, random {random:.2f}")
    assert trained > random + 5.0, table


@pytest.mark.slow
def test_qmix_through_mcrs_train_on_vmas_navigation_with_early_ends_beats_random(tmp_path: Path) -> None:
    pytest.importorskip("vmas")
    table = _train_eval_export(
        tmp_path, "vmas_navigation",
        ["task.scenario_kwargs.n_agents=2", "train.total_env_steps=32000", "train.num_envs=16",
         "train.eps_anneal_steps=12000", "train.eval_interval=8000", "train.eval_episodes=32"],
    )  # fmt: skip
    trained, random = table["trained"], table["random"]
    print(f"vmas_navigation: trained {trained}, random {random}")
    assert trained["episode_reward_mean"] > random["episode_reward_mean"] + 0.5, table
    with (tmp_path / "run" / "logs" / "scalars" / "train" / "episode_length.csv").open() as f:
        lengths = [float(row[1]) for row in csv.reader(f)]
    assert min(lengths) < 50.0, (
        lengths
    )  # episodes ended early (every agent on its goal), padded in the replay
