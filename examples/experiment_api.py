"""The Python API, cell by cell: build a config, run an ``Experiment``, evaluate it, plot its learning curve,
add a callback, resume. The ``# %%`` markers are cells (VS Code, PyCharm and Jupytext run them one at a
time); the file also runs as a script:

    .venv/bin/python examples/experiment_api.py                          # 6,000 env steps of QMIX on map10
    MCRS_EXAMPLE_STEPS=400 MCRS_EXAMPLE_OUT=/tmp/api .venv/bin/python examples/experiment_api.py   # tiny

It writes into ``MCRS_EXAMPLE_OUT`` (default ``outputs/example_api``): the run directory ``run/`` and
``learning_curve.png``. docs/API.md explains each step.
"""

# %% Settings: how long to train and where to write
from __future__ import annotations

import copy
import os
from pathlib import Path

import mcrs

STEPS = int(os.environ.get("MCRS_EXAMPLE_STEPS", "6000"))  # env steps of the first session
OUT = Path(os.environ.get("MCRS_EXAMPLE_OUT", "outputs/example_api"))
OUT.mkdir(parents=True, exist_ok=True)
RUN_DIR = OUT / "run"

# %% Build: the typed config `mcrs-train <overrides>` would run (ConfigError names a bad key or value)
config = mcrs.compose(
    "algo=qmix",
    "env=map10",
    "seed=0",
    f"train.total_env_steps={STEPS}",
    "train.num_envs=8",  # episodes collected at once
    "train.batch_episodes=8",
    "train.replay_episodes=500",
    "train.eval_episodes=8",
    "train.target_update_episodes=40",
    "threads=1",
)
config.train.eval_interval = max(STEPS // 6, 1)  # a dataclass: fields change in Python too
config.train.eps_anneal_steps = max(STEPS // 2, 1)
config.train.checkpoint_interval = STEPS
config.logger.log_interval = max(STEPS // 6, 1)
config.overwrite = True  # run the notebook again: replace the previous run in RUN_DIR
print(config.algo.mixer, config.env.name, config.env.comm_range, config.train.total_env_steps)


# %% A callback: the hooks of the training loop, its state kept in every checkpoint
class EvalHistory(mcrs.Callback):
    """Keeps (env step, greedy reward) of every evaluation; the history survives a resume."""

    name = "eval_history"  # keys its checkpoint state and its time/eval_history_s timer

    def __init__(self) -> None:
        self.history: list[tuple[int, float]] = []

    def on_evaluation_end(self, metrics: dict[str, float]) -> None:
        self.history.append((self.experiment.counters.env_steps, metrics["episode_reward"]))

    def state_dict(self) -> dict:
        return {"history": [list(point) for point in self.history]}

    def load_state_dict(self, state: dict) -> None:
        self.history = [(int(s), float(r)) for s, r in state["history"]]


# %% Run: train to train.total_env_steps; returns the last greedy evaluation
history = EvalHistory()
experiment = mcrs.Experiment(config, RUN_DIR, callbacks=[history])
metrics = experiment.run()
checkpointed = list(history.history)  # what the final checkpoint holds (evaluate() below adds one)
print(
    f"after {experiment.counters.env_steps} env steps: greedy episode reward {metrics['episode_reward']:.2f}"
)

# %% Evaluate: the trained policy again, and the greedy-uncertainty heuristic on the same episodes
from mcrs.evaluate import evaluate_policy  # noqa: E402 (a notebook imports where it needs to)

trained = experiment.evaluate()  # the train.eval_episodes fixed-seed episodes of every evaluation
heuristic = evaluate_policy(
    experiment.env_config, "greedy", config.train.eval_episodes, config.train.eval_seed
)
greedy_mean = heuristic["episode_reward"][0]
print(f"trained {trained['episode_reward']:.2f}, greedy heuristic {greedy_mean:.2f} (same episodes)")

# %% Resume: a longer budget continues the same run (counters, replay, random state, callbacks' state)
longer = copy.deepcopy(config)  # the same run: only the mutable fields (length, logging) may differ
longer.train.total_env_steps = 2 * STEPS
resumed_history = EvalHistory()
resumed = mcrs.Experiment(longer, RUN_DIR, resume=True, callbacks=[resumed_history])
assert resumed_history.history == checkpointed  # the callback's state came back from the checkpoint
final = resumed.run()
print(
    f"resumed to {resumed.counters.env_steps} env steps: greedy episode reward {final['episode_reward']:.2f}"
)

# %% Plot: the learning curve from the run's CSV log, against the heuristic
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from mcrs.experiment.run.logging import read_scalar_rows, scalar_file  # noqa: E402

rows = read_scalar_rows(scalar_file(RUN_DIR, "eval/episode_reward"))
fig = Figure(figsize=(6, 3.5), layout="constrained")
FigureCanvasAgg(fig)
ax = fig.add_subplot()
ax.plot([s for s, _ in rows], [r for _, r in rows], marker="o", label="QMIX (greedy evaluation)")
ax.axhline(greedy_mean, color="k", ls="--", label="greedy-uncertainty heuristic")
ax.set(xlabel="env steps", ylabel="episode reward", title=f"{config.env.name}: QMIX, seed {config.seed}")
ax.legend(loc="lower right")
curve = OUT / "learning_curve.png"
fig.savefig(curve, dpi=100)
print(f"learning curve ({len(rows)} evaluations): {curve}")
print(f"run directory: {RUN_DIR} (checkpoints/last.pt, logs/scalars/, config.yaml)")
