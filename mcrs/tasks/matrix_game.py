"""The one-step cooperative matrix game of the QTRAN and QPLEX papers, as a batched TorchRL ``EnvBase``.

Two players pick one of three actions at once and share the payoff::

              b=0   b=1   b=2
        a=0     8   -12   -12
        a=1   -12     0     0
        a=2   -12     0     0

The optimum (0, 0) is surrounded by penalties, so a monotonic mixer (QMIX, VDN) trained on uniformly random
joint actions settles on a safe sub-optimal action. QPLEX's mixer can represent the whole table and, with
its matrix-game settings (:data:`QPLEX_MATRIX_GAME`), finds (0, 0) on most seeds. It serves as a second,
independent TorchRL task for the mixers and the loss. Keys (``E = num_envs``, ``N`` players, ``A``
actions)::

    ("players", "observation")   [E, N, N]  float32, the player's one-hot id
    ("players", "action_mask")   [E, N, A]  bool, every action allowed
    ("players", "action")        [E, N]     int64 in 0..A-1
    "global_state"               [E, 2]     float32 one-hot phase: (1, 0) before the move, (0, 1) after
    "reward"                     [E, 1]     float32, the shared payoff
    "done" / "terminated" / "truncated"  [E, 1]  bool; every episode terminates after one step

The env has no ``step_count``; TorchRL's ``StepCounter`` adds it (:func:`make_matrix_game`), as for any
third-party task."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Composite
from torchrl.envs import Compose, EnvBase, StepCounter, TransformedEnv

from mcrs.experiment.training.task import Task
from mcrs.models.acting import recurrent_primer
from mcrs.objectives import ValueFactorisationLoss
from mcrs.tasks.specs import done_spec, group_action_spec

#: The non-monotonic payoff of QTRAN (Son et al. 2019, table 1) and QPLEX (Wang et al. 2021, table 1).
PAYOFF = torch.tensor([[8.0, -12.0, -12.0], [-12.0, 0.0, 0.0], [-12.0, 0.0, 0.0]])
GROUP = "players"
STATE_KEY = "global_state"
STEP_KEYS = ((GROUP, "observation"), (GROUP, "action_mask"), STATE_KEY)
#: QPLEX's matrix-game mixer settings (its ``qplex.yaml``): 10 heads of 3-layer advantage extractors. The
#: default, its SMAC setting (``qplex_sc2.yaml``), does not find (0, 0) here.
QPLEX_MATRIX_GAME: dict[str, int] = {"n_kernels": 10, "adv_hypernet_layers": 3}


class MatrixGameEnv(EnvBase):
    """A one-step cooperative matrix game for ``N`` players, batched over ``num_envs`` environments.

    The dynamics are deterministic, so there is nothing to seed; random actions come from torch's global
    generator.

    Args:
        payoff: the shared payoff of shape ``[A] * N`` (``N >= 2``); ``payoff[a_1, ..., a_N]`` is paid for
            the joint action ``(a_1, ..., a_N)``.
    """

    batch_locked = True

    def __init__(
        self, num_envs: int = 1, payoff: torch.Tensor = PAYOFF, device: str | torch.device | None = None
    ) -> None:
        payoff = torch.as_tensor(payoff, dtype=torch.float32)
        if payoff.ndim < 2 or len(set(payoff.shape)) != 1:
            raise ValueError(f"payoff must have shape [A] * N with N >= 2 players, got {tuple(payoff.shape)}")
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.num_envs, self.n_players, self.n_actions = num_envs, payoff.ndim, payoff.shape[0]
        self.payoff = payoff.contiguous().to(self.device)
        # payoff.flatten()[(a * strides).sum()] == payoff[a_1, ..., a_N]: one gather for all envs and players.
        self._strides = torch.tensor(self.payoff.stride(), dtype=torch.int64, device=self.device)
        self._make_specs()

    def _make_specs(self) -> None:
        E, N, A, dev = self.num_envs, self.n_players, self.n_actions, self.device
        self.observation_spec = Composite(
            {
                GROUP: Composite(
                    observation=Bounded(0.0, 1.0, shape=(E, N, N), dtype=torch.float32, device=dev),
                    action_mask=Binary(n=A, shape=(E, N, A), dtype=torch.bool, device=dev),
                    shape=(E, N),
                    device=dev,
                ),
                STATE_KEY: Bounded(0.0, 1.0, shape=(E, 2), dtype=torch.float32, device=dev),
            },
            shape=(E,),
            device=dev,
        )
        self.action_spec = group_action_spec(GROUP, E, N, A, dev)
        low, high = self.payoff.min().item(), self.payoff.max().item()
        self.reward_spec = Composite(
            reward=Bounded(low, high, shape=(E, 1), dtype=torch.float32, device=dev), shape=(E,), device=dev
        )
        self.done_spec = done_spec(E, dev)

    # ------------------------------------------------------------------ EnvBase hooks
    def _set_seed(self, seed: int | None) -> None:
        """Nothing to seed: the game is deterministic."""

    def _observe(self, after_move: bool) -> TensorDict:
        E, N, A, dev = self.num_envs, self.n_players, self.n_actions, self.device
        players = TensorDict(
            {
                "observation": torch.eye(N, device=dev).expand(E, N, N).clone(),
                "action_mask": torch.ones(E, N, A, dtype=torch.bool, device=dev),
            },
            batch_size=[E, N],
            device=dev,
        )
        phase = torch.zeros(E, 2, device=dev)
        phase[:, int(after_move)] = 1.0
        ended = torch.full((E, 1), after_move, dtype=torch.bool, device=dev)
        return TensorDict(
            {
                GROUP: players,
                STATE_KEY: phase,
                "done": ended,
                "terminated": ended.clone(),
                "truncated": torch.zeros_like(ended),
            },
            batch_size=[E],
            device=dev,
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        # Every env is either being reset or has not moved yet (an episode is one step), so the start
        # observation is right for the whole batch, whatever the "_reset" mask says.
        return self._observe(after_move=False)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get((GROUP, "action"))  # [E, N]
        out = self._observe(after_move=True)
        out.set("reward", self.payoff.flatten()[(action * self._strides).sum(-1)].unsqueeze(-1))
        return out


class MatrixGameTask(Task):
    """The matrix game as a :class:`~mcrs.experiment.training.task.Task`, e.g. ``Experiment(config, run_dir,
    task=MatrixGameTask())``. Its metric is the episode reward, the joint action's payoff: 8 at the optimum
    (0, 0) under greedy evaluation. ``payoff`` defaults to :data:`PAYOFF`."""

    name = "matrix_game"
    group = GROUP
    state_key = STATE_KEY
    max_steps = 1

    def __init__(self, payoff: torch.Tensor = PAYOFF) -> None:
        self.payoff = torch.as_tensor(payoff, dtype=torch.float32).clone()
        self.n_agents, self.n_actions = self.payoff.ndim, self.payoff.shape[0]
        self.obs_dim, self.state_shape = self.n_agents, (2,)

    def make_env(self, num_envs: int, device: torch.device) -> MatrixGameEnv:
        return MatrixGameEnv(num_envs, self.payoff, device)

    def settings(self) -> dict[str, Any]:
        return {"payoff": self.payoff.tolist()}

    def fingerprint(self) -> dict[str, Any]:
        return {**super().fingerprint(), "task.payoff": self.payoff.flatten().tolist()}


def make_matrix_game(
    num_envs: int = 1, hidden_dim: int = 32, payoff: torch.Tensor = PAYOFF, device: str | torch.device = "cpu"
) -> TransformedEnv:
    """Return the matrix game with what the recurrent acting policy needs: ``step_count`` and its carried
    state."""
    base = MatrixGameEnv(num_envs, payoff, device)
    return TransformedEnv(
        base,
        Compose(
            StepCounter(),
            recurrent_primer(num_envs, base.n_players, hidden_dim, group=GROUP, device=base.device),
        ),
    )


def joint_action_values(loss: ValueFactorisationLoss, episodes: TensorDictBase) -> torch.Tensor:
    """Return ``Q_tot`` of every joint action at the first step of ``episodes[0]`` as a table ``[A] * N``. The
    maxima are each agent's own argmax, what QPLEX's advantage is measured against, so the table is what
    greedy acting maximises."""
    with torch.no_grad():
        q = loss.agent_values(episodes[:1])[0, 0]  # [N, A]
        N, A = q.shape
        joint = torch.stack(torch.unravel_index(torch.arange(A**N, device=q.device), (A,) * N), dim=-1)
        chosen = q.expand(A**N, N, A).gather(-1, joint.unsqueeze(-1)).squeeze(-1)  # [A^N, N]
        best = q.max(-1).values.expand(A**N, N)
        state = episodes.get(loss.tensor_keys.state)[0, 0].expand(A**N, -1)
        return loss.mix(chosen, state, joint, best).view((A,) * N)
