"""The MCRS-LCR environment as a batched TorchRL ``EnvBase`` with ``batch_size=[num_envs]``.

Keys (``E = num_envs``, ``N = n_uavs``)::

    ("agents", "observation")   [E, N, obs_dim]  float32, paper eqs. 18-21
    ("agents", "action_mask")   [E, N, 8]        bool, on-grid moves less those the shields forbid
    ("agents", "action")        [E, N]           int64 in 0..7
    ("agents", "reading")       [E, N]           bool, this step's sensor reading (True = "F")
    ("agents", "position")      [E, N, 2]        int64 cell (x, y)
    "state"                     [E, state_dim]   float32, paper eq. 22
    "state_map"                 [E, 2, L1, L2]   float32, global m(U) and m(F) as an image
    "state_counts"              [E, L1*L2, 2]    int16 global (positive, negative) counts per cell;
                                                 float32 when evidence_decay > 0
    "step_count"                [E, 1]           int64
    "reward"                    [E, 1]           float32 team reward r1 + r2 + r3 + r4
    "reward_terms"              [E, 4]           float32 (r1, r2, r3, r4)
    "done" / "terminated" / "truncated"  [E, 1]  bool; episodes end by the time limit only
    ("metrics", name)           [E]              float32 running episode metrics (``METRICS``)

The state's maps are a function of ``state_counts``, which the episodic memory stores as compact states.
With ``expose_beliefs=True`` there are also ``("agents", "belief_map")`` ``[E, N, 2, L1, L2]``, each UAV's
fused m(U) and m(F), and ``"neighbours"`` ``[E, N, N]``, this step's communication graph."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from mcrs.env.config import EnvConfig, scenario
from mcrs.env.core import METRICS, N_ACTIONS, MCRSCore, StepResult, counts_dtype


class MCRSEnv(EnvBase):
    """Multi-UAV reconnaissance and search with limited communication range, batched over environments.

    Args:
        config: an :class:`EnvConfig` or a preset name (``"map10"``, ``"map15"``, ``"map20"``).
        device: overrides ``config.device``.
        **overrides: config fields to change, e.g. ``num_envs=1024, comm_range=3.0``.
    """

    batch_locked = True

    def __init__(
        self, config: EnvConfig | str = "map10", device: str | torch.device | None = None, **overrides
    ):
        if isinstance(config, str):
            config = scenario(config, **overrides)
        elif overrides:
            config = config.replace(**overrides)
        if device is not None:
            config = config.replace(device=str(device))  # one source of truth for policies and the core
        device = torch.device(config.device)
        super().__init__(device=device, batch_size=torch.Size([config.num_envs]))
        self.config = config
        self.core = MCRSCore(config, device=device)
        self.n_agents = config.n_uavs
        self._make_specs()

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        E, N, dev = self.config.num_envs, self.config.n_uavs, self.device
        specs = spec_leaves(self.config, E, dev)

        def composite(leaves: dict[str, Any], shape: tuple[int, ...]) -> Composite:
            nested = {
                k: composite(v, (*shape, N) if k == "agents" else shape) if isinstance(v, dict) else v
                for k, v in leaves.items()
            }
            return Composite(nested, shape=shape, device=dev)

        self.observation_spec = composite(specs["observation"], (E,))
        self.action_spec = composite(specs["action"], (E,))
        self.reward_spec = composite(specs["reward"], (E,))
        self.done_spec = composite(specs["done"], (E,))

    # ------------------------------------------------------------------ EnvBase hooks
    def _set_seed(self, seed: int | None) -> None:
        self.core.seed(0 if seed is None else seed)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():  # noqa: SIM118 (a TensorDict)
            mask = tensordict.get("_reset").reshape(self.config.num_envs)
        return self._to_tensordict(self.core.reset(mask), with_reward=False)

    def reset_to(
        self, uav_positions: torch.Tensor, no_fly_positions: torch.Tensor, target_positions: torch.Tensor
    ) -> TensorDictBase:
        """Start every environment from a given scene (see :meth:`MCRSCore.reset_to`) and return the reset
        tensordict."""
        return self._to_tensordict(
            self.core.reset_to(uav_positions, no_fly_positions, target_positions), with_reward=False
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        result = self.core.step(tensordict.get(("agents", "action")))
        return self._to_tensordict(result)

    def _to_tensordict(self, result: StepResult, with_reward: bool = True) -> TensorDict:
        E = self.config.num_envs
        # Keep the action spec's mask current, so that rand_action / rand_step draw only allowed moves.
        self.full_action_spec["agents", "action"].update_mask(result.action_mask)
        truncated = result.truncated.unsqueeze(-1)
        agents = {
            "observation": result.observation,
            "action_mask": result.action_mask,
            "reading": result.reading,
            "position": result.position,
        }
        root = {
            "state": result.state,
            "state_map": result.state_map,
            "state_counts": result.state_counts,
            "step_count": result.step_count.unsqueeze(-1),
            "reward_terms": result.reward_terms,
            "metrics": TensorDict(result.metrics, batch_size=[E], device=self.device),
            "done": truncated,
            "terminated": torch.zeros_like(truncated),
            "truncated": truncated.clone(),
        }
        if with_reward:
            root["reward"] = result.reward.unsqueeze(-1)
        if result.belief_map is not None:
            agents["belief_map"] = result.belief_map
            root["neighbours"] = result.neighbours
        root["agents"] = TensorDict(agents, batch_size=[E, self.n_agents], device=self.device)
        return TensorDict(root, batch_size=[E], device=self.device)


def spec_leaves(config: EnvConfig, num_envs: int, device: str | torch.device) -> dict[str, dict[str, Any]]:
    """Return the specs of :class:`MCRSEnv` for ``config`` as nested dicts of leaf specs, without building an
    env.

    The keys are ``observation``, ``action``, ``reward`` and ``done``. Plain dicts are used because
    TorchRL's ``Composite`` cannot hold a ``Bounded`` spec on the ``meta`` device, where
    :mod:`mcrs.experiment.training.resources` sizes a step without allocating anything."""
    c, E, N, dev = config, num_envs, config.n_uavs, torch.device(device)
    agents: dict[str, Any] = {
        "observation": Bounded(-1.0, 1.0, shape=(E, N, c.obs_dim), dtype=torch.float32, device=dev),
        "action_mask": Binary(n=N_ACTIONS, shape=(E, N, N_ACTIONS), dtype=torch.bool, device=dev),
        "reading": Categorical(2, shape=(E, N), dtype=torch.bool, device=dev),
        "position": Bounded(
            torch.zeros(E, N, 2, dtype=torch.int64, device=dev),
            torch.tensor([c.width - 1, c.height - 1], device=dev).expand(E, N, 2).clone(),
            shape=(E, N, 2),
            dtype=torch.int64,
            device=dev,
        ),
    }
    observation: dict[str, Any] = {
        "agents": agents,
        "state": Bounded(-1.0, 1.0, shape=(E, c.state_dim), dtype=torch.float32, device=dev),
        "state_map": Bounded(0.0, 1.0, shape=(E, 2, c.width, c.height), dtype=torch.float32, device=dev),
        "state_counts": Bounded(
            0,
            c.n_uavs * (c.max_steps + 1),
            shape=(E, c.width * c.height, 2),
            dtype=torch.float32 if c.evidence_decay > 0 else counts_dtype(c),
            device=dev,
        ),
        "step_count": Bounded(0, c.max_steps, shape=(E, 1), dtype=torch.int64, device=dev),
        "reward_terms": Unbounded(shape=(E, 4), dtype=torch.float32, device=dev),
        "metrics": {name: Unbounded(shape=(E,), dtype=torch.float32, device=dev) for name in METRICS},
    }
    if c.expose_beliefs:
        agents["belief_map"] = Bounded(
            0.0, 1.0, shape=(E, N, 2, c.width, c.height), dtype=torch.float32, device=dev
        )
        observation["neighbours"] = Binary(n=N, shape=(E, N, N), dtype=torch.bool, device=dev)
    done = Categorical(2, shape=(E, 1), dtype=torch.bool, device=dev)
    return {
        "observation": observation,
        "action": {"agents": {"action": Categorical(N_ACTIONS, shape=(E, N), dtype=torch.int64, device=dev)}},
        "reward": {"reward": Unbounded(shape=(E, 1), dtype=torch.float32, device=dev)},
        "done": {"done": done, "terminated": done.clone(), "truncated": done.clone()},
    }
