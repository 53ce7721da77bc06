"""A task's run is usable by every tool: the task contract checked before anything is written, the run's
task recorded and rebuilt (``mcrs-eval policy=<run>`` beside a random baseline, ``mcrs-export``), a resume
and its evaluations, the fingerprint, and episodes that end before the time limit. The task here,
:class:`Rendezvous`, is defined in this test file (not in the package), as a user's would be."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, StepCounter, TransformedEnv

from mcrs.experiment.config import ConfigError, compose
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.training.replay import episodes_from_rollout
from mcrs.experiment.training.task import Task, make_task
from mcrs.experiment.training.trainer import Experiment
from mcrs.policies.task_runs import UniformAllowed, evaluate_task_run, load_task_run
from mcrs.tasks import MatrixGameTask

REPO = Path(__file__).resolve().parents[1]
MOVES = torch.tensor([[0, 0], [0, 1], [0, -1], [1, 0], [-1, 0]])  # stay, up, down, right, left


class RendezvousEnv(EnvBase):
    """Two agents on a ``size`` x ``size`` grid must meet: -1 a step while apart; the episode terminates
    when they share a cell (early), else StepCounter truncates it. Moves off the grid are masked."""

    batch_locked = True

    def __init__(self, num_envs: int, size: int = 5, device: str | torch.device = "cpu") -> None:
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.size, E, dev = size, num_envs, self.device
        self.pos = torch.zeros(E, 2, 2, dtype=torch.int64, device=dev)
        self.generator = torch.Generator().manual_seed(0)
        self.observation_spec = Composite(
            agents=Composite(
                observation=Bounded(0.0, 1.0, shape=(E, 2, 4), device=dev),
                action_mask=Binary(n=5, shape=(E, 2, 5), dtype=torch.bool, device=dev),
                shape=(E, 2),
                device=dev,
            ),
            state=Bounded(0.0, 1.0, shape=(E, 4), device=dev),
            shape=(E,),
            device=dev,
        )
        self.action_spec = Composite(
            agents=Composite(action=Categorical(5, shape=(E, 2), device=dev), shape=(E, 2), device=dev),
            shape=(E,),
            device=dev,
        )
        self.reward_spec = Composite(reward=Unbounded(shape=(E, 1), device=dev), shape=(E,), device=dev)
        flag = Categorical(2, shape=(E, 1), dtype=torch.bool, device=dev)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), shape=(E,), device=dev)

    def _observe(self, met: torch.Tensor) -> TensorDict:
        E, s = self.batch_size[0], self.size
        scaled = self.pos.float() / (s - 1)  # [E, 2, 2]
        other = scaled.flip(1)
        after = self.pos.unsqueeze(2) + MOVES.to(self.device)  # [E, 2, 5, 2]
        mask = ((after >= 0) & (after < s)).all(-1)
        agents = TensorDict(
            observation=torch.cat([scaled, other], -1),
            action_mask=mask,
            batch_size=[E, 2],
            device=self.device,
        )
        return TensorDict(
            agents=agents, state=scaled.flatten(1), done=met, terminated=met.clone(), batch_size=[E]
        )

    def _set_seed(self, seed: int | None) -> None:
        self.generator = torch.Generator().manual_seed(0 if seed is None else seed)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        E = self.batch_size[0]
        which = torch.ones(E, dtype=torch.bool)
        if tensordict is not None and "_reset" in tensordict.keys():  # noqa: SIM118
            which = tensordict.get("_reset").reshape(E).cpu()
        fresh = torch.randint(0, self.size, (E, 2, 2), generator=self.generator)
        apart = (fresh[:, 0] != fresh[:, 1]).any(-1, keepdim=True).unsqueeze(-1)
        fresh = torch.where(apart, fresh, (self.size - 1) - fresh * 0)  # met at reset: start in a corner
        fresh[:, 0] = torch.where(apart.squeeze(-1), fresh[:, 0], torch.zeros_like(fresh[:, 0]))
        self.pos = torch.where(which.view(E, 1, 1), fresh.to(self.device), self.pos)
        return self._observe(torch.zeros(E, 1, dtype=torch.bool, device=self.device))

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(("agents", "action"))
        self.pos = (self.pos + MOVES.to(self.device)[action]).clamp(0, self.size - 1)
        met = (self.pos[:, 0] == self.pos[:, 1]).all(-1, keepdim=True)
        out = self._observe(met)
        out.set("reward", torch.where(met, 0.0, -1.0))
        return out


class Rendezvous(Task):
    """A user's task, in a test file: the rendezvous gridworld with StepCounter's time limit."""

    n_agents, n_actions, obs_dim, state_shape = 2, 5, 4, (4,)

    def __init__(self, size: int = 5, max_steps: int = 10) -> None:
        self.size, self.max_steps, self.name = size, max_steps, f"rendezvous{size}"

    def make_env(self, num_envs: int, device: torch.device) -> EnvBase:
        return TransformedEnv(RendezvousEnv(num_envs, self.size, device), StepCounter(self.max_steps))

    def settings(self) -> dict:
        return {"size": self.size, "max_steps": self.max_steps}


class NoTruncated(Rendezvous):
    """The env without StepCounter: no ("next", "truncated"), which the loop reads."""

    def make_env(self, num_envs: int, device: torch.device) -> EnvBase:
        return RendezvousEnv(num_envs, self.size, device)


RUN = [
    "algo=qmix",
    "threads=1",
    "logger.progress_bar=false",
    "train.num_envs=16",
    "train.batch_episodes=32",
    "train.replay_episodes=2000",
    "train.total_env_steps=8000",
    "train.eval_interval=1600",
    "train.eval_episodes=64",
    "train.checkpoint_interval=1600",
    "train.eps_anneal_steps=3200",
    "train.target_update_episodes=64",
    "train.optimizer=adam",
    "train.lr=0.002",
    "model.hidden_dim=32",
]


def _rows(run_dir: Path, name: str = "eval/episode_reward") -> list[tuple[int, float]]:
    with (run_dir / "logs" / "scalars" / f"{name}.csv").open() as f:
        return [(int(row[0]), float(row[1])) for row in csv.reader(f)]


# ---------------------------------------------------------------------------------------- the contract
def test_an_env_without_truncated_is_refused_at_build_leaving_nothing(tmp_path: Path) -> None:
    """The key the loop reads at the first collection is checked when the task is built: one line naming
    it, and the run directory is never made (no config.yaml, logs/ or lock left behind)."""
    run_dir = tmp_path / "run"
    with pytest.raises(ConfigError) as error:
        Experiment(compose(*RUN), run_dir, task=NoTruncated())
    message = str(error.value)
    assert "'truncated'" in message and "StepCounter" in message and "\n" not in message
    assert not run_dir.exists()


def test_make_task_rebuilds_a_spec_and_refuses_bad_nodes_in_one_line() -> None:
    game = MatrixGameTask(torch.tensor([[5.0, 0.0], [0.0, 1.0]]))
    rebuilt = make_task(game.spec())
    assert isinstance(rebuilt, MatrixGameTask) and torch.equal(rebuilt.payoff, game.payoff)
    assert make_task(Rendezvous(4, 7).spec()).settings() == {"size": 4, "max_steps": 7}
    for node, expected in [
        ({"_target_": "no_such_module.Task"}, r"task\._target_=no_such_module\.Task: cannot import"),
        ({"_target_": "os.path.join"}, r"task\._target_=os\.path\.join: not a Task class"),
        ({"_target_": f"{__name__}.Rendezvous", "sise": 3}, r"task: Rendezvous: .*sise.*\['size', 'max_steps'\]"),
        ({"size": 3}, r"task: expected a node with _target_"),
    ]:  # fmt: skip
        with pytest.raises(ConfigError, match=expected) as error:
            make_task(node)
        assert "\n" not in str(error.value)


def test_first_episode_only_pads_an_early_end_and_drops_the_rest_of_the_row() -> None:
    """Row 0 ends at step 2 (terminated) and goes on with a next episode that the batch cuts; row 1 lasts
    the whole batch. One item per row: row 0's first episode, padded and masked after its 3 steps."""
    E, T = 2, 5
    done = torch.zeros(E, T, 1, dtype=torch.bool)
    done[0, 2] = done[0, 4] = done[1, 4] = True
    batch = TensorDict(
        {
            "obs": torch.arange(E * T, dtype=torch.float32).view(E, T, 1),
            "action": torch.ones(E, T, dtype=torch.int64),
            "step_count": torch.tensor([[0, 1, 2, 0, 1], [0, 1, 2, 3, 4]]).unsqueeze(-1),
            "next": {
                "obs": torch.arange(E * T, dtype=torch.float32).view(E, T, 1) + 100,
                "reward": -torch.ones(E, T, 1),
                "done": done,
                "terminated": done.clone(),
                "truncated": torch.zeros_like(done),
            },
        },
        batch_size=[E, T],
    )
    items = episodes_from_rollout(batch, ["obs"], "action", first_episode_only=True)
    assert items.batch_size == (2, T + 1)
    assert items["filled"][0].tolist() == [True] * 3 + [False] * 3
    assert items["reward"][0].squeeze(-1).tolist() == [-1, -1, -1, 0, 0, 0]
    assert items["terminated"][0].squeeze(-1).tolist() == [False, False, True, False, False, False]
    assert items["obs"][0].squeeze(-1).tolist() == [0, 1, 2, 102, 102, 102]  # o_L repeated on the padding
    assert items["filled"][1].sum() == T


def test_the_random_baseline_plays_only_allowed_actions() -> None:
    task = Rendezvous()
    mask = torch.zeros(64, 2, 5, dtype=torch.bool)
    mask[..., 1] = mask[:, 1, 3] = True
    td = UniformAllowed(task, seed=0)(TensorDict({("agents", "action_mask"): mask}, batch_size=[64]))
    action = td.get(("agents", "action"))
    assert (action[:, 0] == 1).all() and set(action[:, 1].tolist()) == {1, 3}


# ------------------------------------------------------------------------- a run, rebuilt by every tool
def test_a_custom_task_run_records_its_task_and_resumes_with_one_row_a_step(tmp_path: Path) -> None:
    """The run's config.yaml names the task (an importable class and its settings); its fingerprint holds
    the task's settings and no env.*; a resume rebuilds the task from the run alone, and evaluate() right
    after it adds no second row at the checkpoint's step."""
    config = compose(*RUN, "train.total_env_steps=320", "train.eval_interval=160", "train.eval_episodes=8")
    Experiment(config, tmp_path, task=Rendezvous()).run()
    saved = (tmp_path / "config.yaml").read_text()
    assert f"_target_: {__name__}.Rendezvous" in saved and "size: 5" in saved
    fingerprint = torch.load(ckpt.checkpoint_path(tmp_path), weights_only=False)["fingerprint"]
    assert fingerprint["task.size"] == 5 and fingerprint["task.name"] == "rendezvous5"
    assert not [k for k in fingerprint if k.startswith("env.")]
    from omegaconf import OmegaConf

    from mcrs.experiment.config import as_typed

    resumed = Experiment(
        as_typed(OmegaConf.load(tmp_path / "config.yaml")), tmp_path, resume=True
    )  # no task=
    assert isinstance(resumed.task, Rendezvous) and resumed.counters.env_steps == 320
    resumed.evaluate()
    resumed.close()
    assert [step for step, _ in _rows(tmp_path)] == [0, 160, 320]


@pytest.mark.slow
def test_a_custom_task_trains_resumes_evaluates_beside_random_and_exports(tmp_path: Path) -> None:
    """The user's task of this file through the whole tool chain: QMIX learns to meet (early ends), a resume
    goes on, ``mcrs-eval policy=<run>`` (a process of its own, the task rebuilt from the run) puts the
    trained agent clearly above the random baseline on the same episodes, and ``mcrs-export`` writes it."""
    run_dir = tmp_path / "run"
    first = compose(*RUN, "train.total_env_steps=4800")
    Experiment(first, run_dir, task=Rendezvous()).run()
    longer = compose(*RUN)
    final = Experiment(longer, run_dir, resume=True, task=Rendezvous()).run()
    rows = _rows(run_dir)
    assert [s for s, _ in rows] == [0, 1600, 3200, 4800, 6400, 8000]
    assert final["episode_reward"] > -4.0, rows  # met within 4 steps on average (the untrained: ~-8)
    lengths = _rows(run_dir, "eval/episode_reward")  # the reward counts the steps apart: early ends
    assert lengths[-1][1] > -9.5

    # the task's module (this file, imported by pytest as __name__) importable in the tools' processes
    here = Path(__file__).resolve().parent if "." not in __name__ else REPO
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(here), str(REPO), os.environ.get("PYTHONPATH", "")]),
    }
    out = subprocess.run(
        [sys.executable, "-m", "mcrs.evaluate", f"policy={run_dir}", "episodes=64", "seed=3",
         f"hydra.run.dir={tmp_path / 'eval'}"],
        capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    with (tmp_path / "eval" / "metrics.csv").open() as f:
        table = {row["policy"]: float(row["episode_reward_mean"]) for row in csv.DictReader(f)}
    trained, random = table[str(run_dir)], table["random"]
    assert "\n| run (qmix) " in (tmp_path / "eval" / "summary.md").read_text()  # the table: the run's name
    print(f"rendezvous: trained {trained:.2f}, random {random:.2f}")
    assert trained > random + 3.0, table
    # the same numbers in Python, on the same episodes
    again = evaluate_task_run(load_task_run(run_dir), 64, 3)
    assert abs(float(again["random"]["episode_reward"].mean()) - random) < 1e-4

    agent = tmp_path / "agent.pt2"
    out = subprocess.run(
        [sys.executable, "-m", "mcrs.export_agent", str(run_dir), str(agent)],
        capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    assert "on rendezvous5" in out.stdout and "2 agents, observation 4, 5 actions" in out.stdout
    from mcrs.policies.export import load_exported

    program, meta = load_exported(agent)
    assert meta["task"]["_target_"] == f"{__name__}.Rendezvous"
    obs, mask = torch.rand(3, 2, 4), torch.ones(3, 2, 5, dtype=torch.bool)
    action, hidden = program(obs, mask, torch.full((3, 2), -1), torch.zeros(3, 2, 32))
    assert action.shape == (3, 2) and hidden.shape == (3, 2, 32)
