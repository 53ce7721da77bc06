"""BenchMARL's QMIX on a VMAS scenario, run by ``mcrs-bench-benchmarl`` in BenchMARL's own environment.

Why a separate script: BenchMARL pins an older TorchRL than ours, so the two stacks cannot share one
process; ``mcrs-bench-benchmarl`` runs this file with BenchMARL's Python (``--benchmarl-python``), passing
the shared settings as JSON, and reads the result back as JSON. This file imports nothing of ``mcrs`` and
only the standard library at the top, so that it loads in either environment (the tests read
:func:`benchmarl_fields` without BenchMARL)::

    python benchmarks/benchmarl_side.py SETTINGS.json RESULT.json

The result: the greedy evaluations (frames, the team's return: per-agent rewards summed over agents and
over each episode's steps up to its first done, the unit of ``mcrs``'s ``episode_reward``), the run's wall
seconds, the seconds spent evaluating, and the versions.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


def benchmarl_fields(settings: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """BenchMARL's config fields for the shared ``settings`` (``experiment``, ``algorithm``, ``model``,
    ``task``): every field the comparison sets, the rest left at BenchMARL's defaults."""
    frames_per_batch = settings["n_envs"] * settings["max_steps"]
    return {
        "experiment": {
            "sampling_device": "cpu",
            "train_device": "cpu",
            "buffer_device": "cpu",
            "share_policy_params": True,
            "prefer_continuous_actions": False,
            "gamma": settings["gamma"],
            "lr": settings["lr"],
            "adam_eps": settings["adam_eps"],
            "clip_grad_norm": True,
            "clip_grad_val": settings["grad_clip"],
            "soft_target_update": False,
            "hard_target_update_frequency": settings["target_update_updates"],
            "exploration_eps_init": settings["eps_start"],
            "exploration_eps_end": settings["eps_end"],
            "exploration_anneal_frames": settings["eps_anneal_frames"],
            "max_n_iters": None,
            "max_n_frames": settings["frames"],
            "off_policy_collected_frames_per_batch": frames_per_batch,
            "off_policy_n_envs_per_worker": settings["n_envs"],
            "off_policy_n_optimizer_steps": settings["updates_per_batch"],
            # the same transitions per update as our batch of whole episodes
            "off_policy_train_batch_size": settings["batch_episodes"] * settings["max_steps"],
            "off_policy_memory_size": settings["replay_episodes"] * settings["max_steps"],
            "off_policy_init_random_frames": 0,
            "off_policy_use_prioritized_replay_buffer": False,
            "evaluation": True,
            "render": False,
            "evaluation_interval": settings["eval_interval"],
            "evaluation_episodes": settings["eval_episodes"],
            "evaluation_deterministic_actions": True,
            "loggers": [],
            "create_json": True,  # BenchMARL evaluates only when it logs somewhere
            "checkpoint_interval": 0,
            "checkpoint_at_end": False,
        },
        "algorithm": {
            "mixing_embed_dim": settings["mixing_embed_dim"],
            "delay_value": True,
            "loss_function": "l2",
        },
        "model": {"num_cells": [settings["hidden"], settings["hidden"]], "activation": "ReLU"},
        "task": {"max_steps": settings["max_steps"], **settings["scenario_kwargs"]},
    }


def team_return(rollout: Any, group: str = "agents") -> float:
    """The team's return of one evaluation episode: the group's rewards summed over agents and over the
    steps up to the first done (BenchMARL logs the mean over agents instead)."""
    done = rollout.get(("next", "done")).reshape(-1)
    end = int(done.nonzero()[0, 0]) + 1 if bool(done.any()) else done.numel()
    return float(rollout.get(("next", group, "reward"))[:end].sum())


class EvaluationRecord:
    """A BenchMARL callback (by its methods: BenchMARL calls them and pickles the object, so it lives at
    module level without BenchMARL's base class) that keeps the team's return at each evaluation, at the
    frames collected so far."""

    def __init__(self) -> None:
        self.experiment: Any = None  # set by BenchMARL
        self.evaluations: list[dict[str, float]] = []

    def __getstate__(self) -> dict[str, Any]:
        return {"evaluations": self.evaluations}  # BenchMARL pickles its callbacks, not the experiment

    def on_setup(self) -> None: ...
    def on_load_state_dict(self, state_dict: dict[str, Any]) -> None: ...
    def on_batch_collected(self, batch: Any) -> None: ...
    def on_train_step(self, batch: Any, group: str) -> None: ...
    def on_train_end(self, training_td: Any, group: str) -> None: ...
    def on_state_dict(self, state_dict: dict[str, Any]) -> None: ...

    def on_evaluation_end(self, rollouts: list[Any]) -> None:
        returns = [team_return(r) for r in rollouts]
        self.evaluations.append(
            {"frames": self.experiment.total_frames, "return": sum(returns) / len(returns)}
        )


def run(settings: dict[str, Any]) -> dict[str, Any]:
    """Train BenchMARL's QMIX with ``settings``; its evaluations and clocks."""
    import benchmarl
    import torch
    import torchrl
    from benchmarl.algorithms import QmixConfig
    from benchmarl.environments import VmasTask
    from benchmarl.experiment import Experiment, ExperimentConfig
    from benchmarl.models.mlp import MlpConfig

    torch.set_num_threads(settings["threads"])
    fields = benchmarl_fields(settings)
    record = EvaluationRecord()
    with tempfile.TemporaryDirectory() as folder:
        config = ExperimentConfig.get_from_yaml()
        for key, value in {**fields["experiment"], "save_folder": folder}.items():
            setattr(config, key, value)
        algorithm = QmixConfig.get_from_yaml()
        for key, value in fields["algorithm"].items():
            setattr(algorithm, key, value)
        model = MlpConfig.get_from_yaml()
        model.num_cells = fields["model"]["num_cells"]
        model.activation_class = getattr(torch.nn, fields["model"]["activation"])
        task = VmasTask[settings["scenario"].upper()].get_from_yaml()
        task.config.update(fields["task"])
        experiment = Experiment(
            task=task,
            algorithm_config=algorithm,
            model_config=model,
            critic_model_config=model,
            seed=settings["seed"],
            config=config,
            callbacks=[record],
        )
        evaluate = experiment._evaluation_loop
        eval_seconds = 0.0

        def timed_evaluation() -> None:
            nonlocal eval_seconds
            start = time.perf_counter()
            evaluate()
            eval_seconds += time.perf_counter() - start

        experiment._evaluation_loop = timed_evaluation  # the training loop calls it through self
        start = time.perf_counter()
        experiment.run()
        wall = time.perf_counter() - start
    return {
        "evaluations": record.evaluations,
        "frames": experiment.total_frames,
        "wall_s": wall,
        "eval_s": eval_seconds,
        "versions": {
            "benchmarl": benchmarl.__version__,
            "torchrl": torchrl.__version__,
            "torch": torch.__version__,
        },
        "fields": fields,
    }


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: benchmarl_side.py SETTINGS.json RESULT.json", file=sys.stderr)
        return 2
    settings = json.loads(Path(argv[0]).read_text())
    Path(argv[1]).write_text(json.dumps(run(settings), indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
