"""Fly an exported agent (``mcrs-export``) in the PettingZoo environment, each UAV deciding on its own.

    .venv/bin/mcrs-export outputs/map10/qmix/<run> agent.pt2
    .venv/bin/python examples/deploy_exported.py agent.pt2 [--episodes 3] [--seed 0]

The policy is the ``.pt2`` file alone (``torch.export.load``: a file you made or trust, since loading a
program runs code stored in it): no mcrs model, config or checkpoint code.
Each UAV calls it as an onboard computer would, with its own row of the inputs only (zeros in the others)
and its own hidden state; the simulator (mcrs's PettingZoo environment, built from the file's description)
stands in for the world. For each step the example also makes one call for the whole team and checks
that every UAV chose the same move alone, which is what the exported program promises.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

from mcrs.env.config import from_mapping
from mcrs.env.pettingzoo_env import MCRSParallelEnv
from mcrs.policies.export import ExportError, read_description


class OnboardAgent:
    """One UAV's copy of the exported program: its own row, its own memory."""

    def __init__(self, step: torch.nn.Module, index: int, meta: dict) -> None:
        self.step, self.index = step, index
        n_agents, obs_dim, hidden_dim = meta["n_agents"], meta["obs_dim"], meta["hidden_dim"]
        self.observation = torch.zeros(1, n_agents, obs_dim)
        self.mask = torch.zeros(1, n_agents, meta["n_actions"], dtype=torch.bool)
        self.mask[..., 0] = True  # the other rows must not be empty of moves
        self.last_action = torch.full((1, n_agents), -1)
        self.hidden = torch.zeros(1, n_agents, hidden_dim)

    def act(self, observation: np.ndarray, action_mask: np.ndarray) -> int:
        i = self.index
        self.observation[0, i] = torch.from_numpy(observation)
        self.mask[0, i] = torch.from_numpy(action_mask.astype(bool))
        action, hidden = self.step(self.observation, self.mask, self.last_action, self.hidden)
        self.hidden[0, i] = hidden[0, i]
        self.last_action[0, i] = action[0, i]
        return int(action[0, i])


def fly(path: str, episodes: int, seed: int) -> list[float]:
    """Each episode's team reward; raises AssertionError if a UAV alone chose other than the team call."""
    meta = read_description(path)
    step = torch.export.load(path).module()
    env = MCRSParallelEnv(from_mapping(meta["env"]))
    n, hidden_dim = meta["n_agents"], meta["hidden_dim"]
    rewards = []
    for episode in range(episodes):
        observations, _ = env.reset(seed=seed + episode)
        uavs = [OnboardAgent(step, i, meta) for i in range(n)]
        team_hidden, team_last = torch.zeros(1, n, hidden_dim), torch.full((1, n), -1)
        total = 0.0
        while env.agents:
            names = env.possible_agents
            actions = {a: uav.act(observations[a]["observation"], observations[a]["action_mask"])
                       for a, uav in zip(names, uavs, strict=True)}  # fmt: skip
            team_obs = torch.from_numpy(np.stack([observations[a]["observation"] for a in names]))[None]
            team_mask = torch.from_numpy(np.stack([observations[a]["action_mask"] for a in names]) > 0)[None]
            team_action, team_hidden = step(team_obs, team_mask, team_last, team_hidden)
            team_last = team_action
            assert team_action[0].tolist() == [actions[a] for a in names], "a UAV alone chose another move"
            observations, reward, _, _, _ = env.step(actions)
            total += reward[names[0]]
        rewards.append(total)
        print(f"episode {episode} (seed {seed + episode}): team reward {total:.2f}, every UAV decided alone")
    return rewards


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("agent", help="an mcrs-export file (.pt2)")
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes={args.episodes}: must be >= 1")
    try:
        rewards = fly(args.agent, args.episodes, args.seed)
    except ExportError as error:
        print(f"deploy_exported: error: {error}", file=sys.stderr)
        return 1
    print(f"mean team reward over {len(rewards)} episodes: {sum(rewards) / len(rewards):.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
