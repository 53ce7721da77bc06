"""The run's state in checkpoints: what :class:`~mcrs.experiment.training.trainer.Experiment` saves, checks
and restores.

:class:`RunState` writes ``last.pt`` (with the replay's block files), the weights at each step and
``last_good.pt``, checks a checkpoint's fingerprint against the run and puts the state back, the random state
last. It reads the experiment's parts through :class:`RunParts`.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any, Protocol

import torch
from omegaconf import OmegaConf
from torchrl.data import ReplayBuffer

from mcrs.experiment.config import RESUME_MUTABLE, as_dictconfig, to_container
from mcrs.experiment.run import checkpoint as ckpt
from mcrs.experiment.run.counters import Counters
from mcrs.experiment.run.history import LEGACY_EVAL_STEP, class_path, final_evaluation_from_log
from mcrs.experiment.run.logging import log_event
from mcrs.experiment.run.replay_store import ReplayStore, load_replay_state_dict, replay_state_dict
from mcrs.experiment.run.rundir import fingerprint, io_errors, truncate_csv_logs
from mcrs.experiment.schema import Config

__all__ = ["RESUME_ADVICE", "RunParts", "RunState"]

#: What a resume refused for a fingerprint field adds to its one line.
RESUME_ADVICE = {
    "algorithm.class": (
        ": the checkpoint's algo.name is an algorithm registered by a module this process has not imported; "
        "import it (it calls register_algorithm) before resuming, or install it under the entry-point group "
        "mcrs.algorithms (docs/API.md, 'An algorithm of your own')"
    )
}


#: Counters beyond this are no run's (int64 arithmetic on them must stay exact).
MAX_COUNTER = 2**62


def _whole(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= MAX_COUNTER


def check_resume_state(state: dict[str, Any], path: Path) -> None:
    """Check a checkpoint's counters, random state and bookkeeping before use, so an edited file is refused in
    one line."""

    def refuse(entry: str, value: Any, rule: str) -> None:
        shown = (
            repr(value)
            if not isinstance(value, torch.Tensor)
            else f"a {value.dtype} tensor of {value.numel()}"
        )
        raise ckpt.CheckpointError(f"{path}: entry {entry}: {shown} {rule}")

    counters = state.get("counters")
    if not isinstance(counters, dict):
        refuse("counters", counters, "is not a mapping of counters")
    for field in fields(Counters):
        if field.name not in counters:
            continue
        value = counters[field.name]
        if field.name == "update_credit":
            number = isinstance(value, (int, float)) and not isinstance(value, bool)
            if not number or not math.isfinite(value) or not 0 <= value <= MAX_COUNTER:
                refuse(f"counters.{field.name}", value, "is not a finite number >= 0")
        elif not _whole(value):
            refuse(f"counters.{field.name}", value, "is not a whole number >= 0")
    rng = state.get("rng")
    if not isinstance(rng, dict):
        refuse("rng", rng, "is not a mapping of random states")
    size = torch.get_rng_state().numel()
    states = [("rng.torch", rng.get("torch"), size)]
    if "cuda" in rng and torch.cuda.is_available():
        cuda = rng["cuda"]
        if not isinstance(cuda, (list, tuple)):
            refuse("rng.cuda", cuda, "is not a list of random states")
        sizes = [s.numel() for s in torch.cuda.get_rng_state_all()]
        states += [(f"rng.cuda[{k}]", s, sizes[k] if k < len(sizes) else -1) for k, s in enumerate(cuda)]
    for entry, value, expected in states:
        if not isinstance(value, torch.Tensor) or value.dtype != torch.uint8 or value.shape != (expected,):
            refuse(entry, value, f"is not a random state (a uint8 tensor of {expected} bytes)")
    step = state.get("last_eval_step")
    if step is not None and not _whole(step):
        refuse("last_eval_step", step, "is not a whole number >= 0")
    last_eval = state.get("last_eval", {})
    if not isinstance(last_eval, dict) or not all(
        isinstance(k, str) and isinstance(v, (int, float)) and not isinstance(v, bool)
        for k, v in last_eval.items()
    ):
        refuse("last_eval", last_eval, "is not a mapping of metric names to numbers")
    rows = state.get("logs", {}).get("rows") if isinstance(state.get("logs"), dict) else None
    if rows is not None and (
        not isinstance(rows, dict) or not all(isinstance(k, str) and _whole(v) for k, v in rows.items())
    ):
        refuse("logs.rows", rows, "is not a mapping of log names to row counts >= 0")


class Saved(Protocol):
    """A part whose state a checkpoint holds (the learner, a callback)."""

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


class SavedCallback(Saved, Protocol):
    name: str


class SavedLearner(Saved, Protocol):
    def weights(self) -> dict[str, Any]: ...


class IdentifiedTask(Protocol):
    def fingerprint(self) -> dict[str, Any]: ...


class Schedule(Protocol):
    def set_env_steps(self, env_steps: int) -> None: ...


class RunParts(Protocol):
    """What the run's state reads of the experiment."""

    config: Config
    run_dir: Path
    device: torch.device
    task: IdentifiedTask
    algorithm: object  # its class is part of the fingerprint
    learner: SavedLearner
    replay: ReplayBuffer
    callbacks: list[SavedCallback]
    epsilon: Schedule  # the exploration schedule, set to the restored step


class RunState:
    """The run's bookkeeping (counters, last evaluation, rows logged) and its checkpoints."""

    def __init__(self, parts: RunParts, counters: Counters) -> None:
        self.parts = parts
        self.counters = counters
        self.replay_store = ReplayStore(ckpt.checkpoint_path(parts.run_dir).parent)
        self.last_eval: dict[str, float] = {}
        self.last_eval_step: int | None = None  # the env step of last_eval (saved in checkpoints)
        self.evaluated_at: int | None = None  # the env step of this process's last evaluation
        self.log_rows: dict[str, int] = {}  # rows written to each log (kept in checkpoints)
        self.last_save = time.monotonic()  # when the last checkpoint was written (checkpoint_minutes)
        self._resume_rng: dict[str, Any] | None = None  # a loaded checkpoint's random state, put back last

    @property
    def run_dir(self) -> Path:
        return self.parts.run_dir

    def write_config(self) -> None:
        """Write ``config.yaml``; an MCRS run's has no ``task`` key (history.OLD_FORMS["no task in the
        fingerprint"])."""
        config = self.parts.config
        node = as_dictconfig(config)
        if config.task is None:
            node = OmegaConf.masked_copy(node, [k for k in node if k != "task"])
        with io_errors(f"write {self.run_dir / 'config.yaml'}"):
            self.run_dir.mkdir(parents=True, exist_ok=True)
            (self.run_dir / "config.yaml").write_text(OmegaConf.to_yaml(node, resolve=True))

    def state_dict(self, replay_inline: bool = True) -> dict[str, Any]:
        """The whole run, with the replay inline or as the manifest of its block files."""
        state = {
            "config": to_container(self.parts.config),
            "fingerprint": self.fingerprint(),
            "logs": {"rows": dict(self.log_rows)},
            "counters": asdict(self.counters),
            "learner": self.parts.learner.state_dict(),
            "callbacks": {cb.name: cb.state_dict() for cb in self.parts.callbacks},
            "last_eval": dict(self.last_eval),
            "last_eval_step": self.last_eval_step,  # a run is finished once it is its final step
            "rng": {"torch": torch.get_rng_state()},
        }
        if torch.cuda.is_available():
            state["rng"]["cuda"] = torch.cuda.get_rng_state_all()
        if self.parts.config.train.save_replay:
            if replay_inline:
                state["replay"] = replay_state_dict(self.parts.replay)
            else:
                state["replay_blocks"] = self.replay_store.save(self.parts.replay, state["fingerprint"])
        return state

    def fingerprint(
        self, config: dict[str, Any] | None = None, learner: dict[str, Any] | None = None
    ) -> dict:
        """What a checkpoint must share with this run, or with a checkpoint's ``config`` and ``learner``
        state."""
        learner = self.parts.learner.weights() if learner is None else learner
        config = to_container(self.parts.config) if config is None else config
        networks = {name: learner[name] for name in ("agent", "mixer") if name in learner}
        if config.get("task") is not None:  # another task: the unused scenario is not the run's identity
            config = {k: v for k, v in config.items() if k != "env"}
        out = fingerprint(config, networks, ckpt.VERSION, RESUME_MUTABLE)
        return {  # the format, the task's identity, the algorithm's class, then the config and networks
            "format.version": out.pop("format.version"),
            **self.parts.task.fingerprint(),
            "algorithm.class": class_path(type(self.parts.algorithm)),
            **out,
        }

    def save(self, name: str = ckpt.LAST) -> Path:
        """Atomically write ``checkpoints/<name>`` and, for ``last.pt``, the weights at this step. Only
        ``last.pt`` uses the replay's block files, so ``last_good.pt`` stays whole whatever later saves
        delete."""
        target = ckpt.checkpoint_path(self.run_dir, name)
        with io_errors(f"write checkpoint {target}", self.intact):  # judged after the failure
            path = self._save(name)
        log_event(f"checkpoint at env step {self.counters.env_steps}: {path}")
        return path

    def intact(self, advice: str = "free space or fix the directory, then ") -> str:
        """The checkpoint a resume would start from, said after an I/O error."""
        last = ckpt.checkpoint_path(self.run_dir)
        if not last.is_file():
            return "; no checkpoint had been written yet"
        return f"; the last checkpoint {last} is intact: {advice}resume={self.run_dir}"

    def _save(self, name: str) -> Path:
        last = name == ckpt.LAST
        path = ckpt.save_atomic(
            self.state_dict(replay_inline=not last), ckpt.checkpoint_path(self.run_dir, name)
        )
        if last:
            self.replay_store.commit()
            self.last_save = time.monotonic()
            weights = {
                "config": to_container(self.parts.config),
                "fingerprint": self.fingerprint(),
                "counters": asdict(self.counters),
                "learner": self.parts.learner.weights(),
            }
            ckpt.save_atomic(weights, ckpt.weights_path(self.run_dir, self.counters.env_steps))
            ckpt.prune_weights(self.run_dir, self.parts.config.train.keep_checkpoints)
        return path

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a checkpoint whose fingerprint matched, but not its random state."""
        saved = state.get("callbacks", {})
        self._check_callbacks(saved)  # before anything is restored
        self.parts.learner.load_state_dict(state["learner"])
        if "replay_blocks" in state:
            self.replay_store.load(self.parts.replay, state["replay_blocks"], self.fingerprint())
        else:  # last_good.pt; history.OLD_FORMS["inline replay"]
            load_replay_state_dict(self.parts.replay, state["replay"])
        for callback in self.parts.callbacks:
            if callback.name in saved:
                callback.load_state_dict(saved[callback.name])
        known = {f.name for f in fields(Counters)}
        self.counters = Counters(**{k: v for k, v in state["counters"].items() if k in known})
        self.last_eval = dict(state.get("last_eval", {}))
        self.last_eval_step = state.get("last_eval_step", LEGACY_EVAL_STEP)
        if self.last_eval_step == self.counters.env_steps:  # its row is logged: evaluate() right after the
            self.evaluated_at = self.last_eval_step  # resume adds no second row at this step
        self.parts.epsilon.set_env_steps(self.counters.env_steps)

    def _check_callbacks(self, saved: dict[str, Any]) -> None:
        """Refuse to drop a callback's saved state or start a callback with state from nothing."""
        names = {callback.name for callback in self.parts.callbacks}
        lost = [name for name, value in saved.items() if name not in names and value]
        if lost:
            raise ckpt.CheckpointError(
                f"the checkpoint holds the state of the callback {lost[0]!r}, which this run does not have: "
                "build the run with it (Experiment(..., callbacks=[...]), or its algorithm)"
                + (  # history.OLD_FORMS["callback state under 'callback'"]
                    f"; a callback class without its own name saved its state as {lost[0]!r}: set "
                    f"name = {lost[0]!r} on that class"
                    if lost[0] == "callback"
                    else ""
                )
            )
        for callback in self.parts.callbacks:
            if callback.name not in saved and callback.state_dict():
                raise ckpt.CheckpointError(
                    f"the checkpoint has no state for this run's {callback.name!r} callback (the run that "
                    "wrote it did not have it)"
                )

    def load(self, path: Path) -> None:
        """Check the checkpoint at ``path`` against this run and restore it; the logs lose the rows written
        after it."""
        state = ckpt.load_resumable(
            path, self.fingerprint(), self.fingerprint, self.parts.device, advice=RESUME_ADVICE
        )
        check_resume_state(state, path)  # before anything is restored
        self._resume_rng = state["rng"]  # restored last (restore_rng), once everything is built
        saved, ours = state.get("fingerprint") or {}, self.fingerprint()
        added = [k for k in ours if k.startswith("algo.options.") and saved and k not in saved]
        if added:  # history.OLD_FORMS["config field on one side only"]
            values = ", ".join(f"{k}={ours[k]!r}" for k in added)
            log_event(f"the checkpoint predates these settings of its algorithm: resumed with {values}")
        try:
            self.load_state_dict(state)
        except ckpt.CheckpointError as error:
            raise ckpt.CheckpointError(f"{path} cannot be loaded into this run: {error}") from None
        except (KeyError, TypeError, ValueError, RuntimeError) as error:  # what a fingerprint cannot see
            first = (str(error).strip().splitlines() or [type(error).__name__])[0]
            raise ckpt.CheckpointError(f"{path} cannot be loaded into this run: {first}") from None
        rows = state.get("logs", {}).get("rows")
        with io_errors(f"rewrite the logs of {self.run_dir}"):  # rows logged after the checkpoint go
            self.log_rows = truncate_csv_logs(self.run_dir, rows, self.counters.env_steps)

    def final_evaluation_written(self) -> bool:
        """Whether the run's final evaluation is done; a kill after the last checkpoint can leave it out."""
        step = self.counters.env_steps
        if self.last_eval_step != LEGACY_EVAL_STEP:
            return bool(self.last_eval) and self.last_eval_step == step
        return final_evaluation_from_log(  # history.OLD_FORMS["no last_eval_step"]
            self.run_dir,
            ckpt.checkpoint_path(self.run_dir),
            self.log_rows.get("eval/episode_reward"),
            step,
            bool(self.last_eval),
        )

    def restore_rng(self) -> None:
        """Put the checkpoint's random state back, last, since building the run may draw random numbers."""
        rng, self._resume_rng = self._resume_rng, None
        if rng is None:
            return
        torch.set_rng_state(rng["torch"].cpu())
        if "cuda" in rng and torch.cuda.is_available():
            torch.cuda.set_rng_state_all([s.cpu() for s in rng["cuda"]])
