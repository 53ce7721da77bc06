"""Our mixers and loss on VMAS navigation, a task we did not write, with TorchRL's own parts around them.

VMAS (``pip install "mcrs[vmas]"``) is a vectorised multi-robot simulator with TorchRL's ``VmasEnv``
wrapper. Navigation: each agent drives to its goal; the per-agent reward ``("agents", "reward")`` is the
agent's progress towards it (``shared_rew=False``); an episode ends early when every agent is on its
goal (terminated) or at ``max_steps`` (truncated, TorchRL's ``StepCounter``). Discrete actions (9 per
agent), no global state: the mixers read the stacked observations ``("agents", "observation")``
``[E, N, 6]`` as the state, as BenchMARL does.

Every learner uses the same TorchRL agent (``QValueActor`` over a parameter-shared ``MultiAgentMLP``),
``EGreedyModule`` exploration, ``Collector`` and replay buffer; they differ in mixer and loss:

    torchrl_qmix       TorchRL's QMixer        + TorchRL's QMixerLoss (the reference)
    qplex_qmixerloss   our QPLEXMixer          + TorchRL's QMixerLoss, unchanged
    qmix_qmixerloss    our QMixer (pymarl's 2-layer hypernetworks) + TorchRL's QMixerLoss
    qplex              our QPLEXMixer          + our ValueFactorisationLoss (double Q, episode pieces)
    qmix               our QMixer              + our ValueFactorisationLoss

QMixerLoss learns from single transitions with a team reward (the mean of the agents' rewards, BenchMARL's
``process_batch``); our loss learns from the episode pieces of :func:`episodes_from_rollout`
(``whole_episodes=False``: episodes that end early and pieces cut by the collector, padded and masked)
and reduces the per-agent rewards itself.
"""

from __future__ import annotations

import time
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, RandomSampler, ReplayBuffer
from torchrl.envs import EnvBase, StepCounter, TransformedEnv
from torchrl.modules import EGreedyModule, MultiAgentMLP, QValueActor
from torchrl.modules.models.multiagent import QMixer as TorchRLQMixer
from torchrl.objectives import HardUpdate, LossModule, ValueEstimators
from torchrl.objectives.multiagent import QMixerLoss

from mcrs.experiment.replay import episodes_from_rollout
from mcrs.models.mixers import QMixer, QPLEXMixer, mixer_module
from mcrs.objectives import ValueFactorisationLoss

LEARNERS = ("torchrl_qmix", "qplex_qmixerloss", "qmix_qmixerloss", "qplex", "qmix")
GROUP = "agents"
OBS = (GROUP, "observation")
#: Navigation without lidar (collisions off: the cheapest VMAS scenario with discrete actions that ends
#: episodes early), per-agent rewards.
SCENARIO: dict[str, Any] = {"n_agents": 3, "collisions": False, "shared_rew": False}


def make_vmas_env(
    num_envs: int, max_steps: int, seed: int, scenario: str = "navigation", **scenario_kwargs: Any
) -> TransformedEnv:
    """``VmasEnv`` with discrete actions and a ``StepCounter`` that truncates at ``max_steps``."""
    from torchrl.envs.libs.vmas import VmasEnv  # needs the optional vmas package

    kwargs = {**SCENARIO, **scenario_kwargs} if scenario == "navigation" else scenario_kwargs
    env = VmasEnv(scenario, num_envs=num_envs, continuous_actions=False, seed=seed, **kwargs)
    return TransformedEnv(env, StepCounter(max_steps))


def greedy_return(env: EnvBase, policy: TensorDictModule, max_steps: int, seed: int) -> float:
    """Mean over the env's batch of the team return (mean of the agents' rewards) of the first episode."""
    env.set_seed(seed)
    with torch.no_grad():
        rollout = env.rollout(max_steps, policy, break_when_any_done=False)  # [E, max_steps]
    reward = rollout.get(("next", GROUP, "reward")).mean(-2).squeeze(-1)  # [E, T] team reward
    done = rollout.get(("next", "done")).squeeze(-1).long()
    first_episode = (done.cumsum(-1) - done) == 0  # steps up to and including the first done
    return float((reward * first_episode).sum(-1).mean())


def _loss(learner: str, qnet: QValueActor, n_agents: int, n_obs: int, n_actions: int, gamma: float):
    state = (n_agents, n_obs)  # the stacked observations stand in for the state
    if learner in ("qplex_qmixerloss", "qplex"):
        mixer = QPLEXMixer(state, 32, n_agents, n_actions)
    elif learner in ("qmix_qmixerloss", "qmix"):
        mixer = QMixer(state, 32, n_agents)
    else:
        mixer = TorchRLQMixer(state, 32, n_agents, device="cpu")
    if learner in ("qplex", "qmix"):
        loss: LossModule = ValueFactorisationLoss(qnet, mixer, gamma=gamma, reward_reduction="mean")
        loss.set_keys(state=OBS)
        return loss
    loss = QMixerLoss(qnet, mixer_module(mixer, GROUP, state_key=OBS), action_space="categorical")
    loss.set_keys(action=(GROUP, "action"))
    loss.make_value_estimator(ValueEstimators.TD0, gamma=gamma)
    return loss


def train_on_vmas(
    learner: str = "qplex",
    frames: int = 48_000,
    seed: int = 0,
    *,
    num_envs: int = 32,
    steps_per_batch: int = 25,
    max_steps: int = 50,
    updates_per_batch: int = 8,
    batch_transitions: int = 512,
    lr: float = 1e-3,
    gamma: float = 0.9,
    eps_end: float = 0.05,
    target_update_interval: int = 50,
    eval_envs: int = 64,
    eval_seed: int = 1_000,
    **scenario_kwargs: Any,
) -> dict[str, Any]:
    """Train one learner on VMAS navigation; return its greedy return before and after.

    The greedy return is :func:`greedy_return` on ``eval_envs`` episodes from ``eval_seed`` (the same
    episodes before and after). ``batch_transitions`` is the sample size in transitions (QMixerLoss) or
    in piece steps (our loss: ``batch_transitions // steps_per_batch`` pieces of ``steps_per_batch + 1``
    rows). Epsilon goes from 1 to ``eps_end`` over the first half of ``frames``.
    """
    if learner not in LEARNERS:
        raise ValueError(f"learner must be one of {', '.join(LEARNERS)}, got {learner!r}")
    start = time.perf_counter()
    torch.manual_seed(seed)
    env = make_vmas_env(num_envs, max_steps, seed, **scenario_kwargs)
    eval_env = make_vmas_env(eval_envs, max_steps, eval_seed, **scenario_kwargs)
    action_spec = env.full_action_spec[GROUP, "action"]
    n_agents, n_actions = action_spec.shape[-1], int(action_spec.space.n)
    n_obs = env.observation_spec[OBS].shape[-1]

    net = MultiAgentMLP(
        n_obs, n_actions, n_agents, centralised=False, share_params=True, depth=2, num_cells=64
    )
    qnet = QValueActor(
        net,
        in_keys=[OBS],
        spec=env.full_action_spec,
        action_value_key=(GROUP, "action_value"),
        action_key=(GROUP, "action"),
        chosen_action_value_key=(GROUP, "chosen_action_value"),
    )
    explore = EGreedyModule(
        action_spec, annealing_num_steps=frames // 2, eps_end=eps_end, action_key=(GROUP, "action")
    )
    policy = TensorDictSequential(qnet, explore)
    loss = _loss(learner, qnet, n_agents, n_obs, n_actions, gamma)
    ours = isinstance(loss, ValueFactorisationLoss)
    optimizer = torch.optim.Adam(loss.parameters(), lr=lr)
    target_updater = HardUpdate(loss, value_network_update_interval=target_update_interval)
    sample = batch_transitions // steps_per_batch if ours else batch_transitions
    replay = ReplayBuffer(storage=LazyTensorStorage(100_000), sampler=RandomSampler(), batch_size=sample)

    untrained = greedy_return(eval_env, qnet, max_steps, eval_seed)
    collector = Collector(
        env,
        policy,
        frames_per_batch=num_envs * steps_per_batch,
        total_frames=frames,
        auto_register_policy_transforms=False,
    )

    def to_replay(batch: TensorDictBase) -> TensorDictBase:
        if ours:  # episode pieces; our loss reduces the per-agent rewards itself
            return episodes_from_rollout(
                batch, step_keys=[OBS], reward_key=(GROUP, "reward"), whole_episodes=False
            )
        # QMixerLoss: single transitions with a team reward (BenchMARL's process_batch)
        batch.set(("next", "reward"), batch.get(("next", GROUP, "reward")).mean(-2))
        return batch.reshape(-1)

    updates, pieces = 0, 0
    try:
        for batch in collector:
            explore.step(batch.numel())
            items = to_replay(batch.exclude(("collector",)))
            pieces += items.shape[0] if ours else 0
            replay.extend(items)
            for _ in range(updates_per_batch):
                out = loss(replay.sample())
                optimizer.zero_grad()
                out["loss"].backward()
                nn.utils.clip_grad_norm_(loss.parameters(), 10.0)
                optimizer.step()
                target_updater.step()
                updates += 1
    finally:
        collector.shutdown()
    trained = greedy_return(eval_env, qnet, max_steps, eval_seed)
    return {
        "learner": learner,
        "untrained_return": untrained,
        "trained_return": trained,
        "updates": updates,
        "frames": frames,
        "episode_pieces": pieces,
        "seconds": time.perf_counter() - start,
    }
