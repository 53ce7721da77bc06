"""Our mixers and loss as drop-in TorchRL components (issue 17), on TorchRL's own modules and loss.

QPLEX inside TorchRL's unchanged ``QMixerLoss`` must mix the *taken* actions: the loss re-runs the value
network on a copy of the batch, whose ``("agents", "action")`` then holds the greedy action.
``ValueFactorisationLoss`` must take a ``QValueActor`` over ``MultiAgentMLP``, optional masks, per-agent
rewards and episodes that end early.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torch.nn import functional as F
from torchrl.data import Categorical, Composite
from torchrl.modules import MultiAgentMLP, QValueActor, QValueModule, SafeSequential
from torchrl.modules.models.multiagent import QMixer as TorchRLQMixer
from torchrl.modules.models.multiagent import VDNMixer
from torchrl.objectives import ValueEstimators
from torchrl.objectives.multiagent import QMixerLoss

from mcrs.experiment.training.replay import episodes_from_rollout
from mcrs.models.acting import AgentStep
from mcrs.models.agent import RecurrentAgent
from mcrs.models.mixers import DMAQMixer, QPLEXMixer, mixer_module
from mcrs.objectives import ValueFactorisationLoss

pytestmark = pytest.mark.filterwarnings("ignore:No target network updater")

N, A, OBS, B = 3, 5, 4, 64
STATE_SHAPE = (N, OBS)  # no global state: the stacked observations, as BenchMARL does on VMAS
REWARD = 100.0  # with gamma 0 the target is the reward, so td_error = (REWARD - Q_tot)^2 gives Q_tot back


def _scramble(module: nn.Module, seed: int) -> None:
    """Large random weights, so that QPLEX's advantage weights lambda_i(s, a) depend on the actions."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=g))


def _qnet(mask: bool) -> SafeSequential:
    net = TensorDictModule(
        nn.Linear(OBS, A), in_keys=[("agents", "observation")], out_keys=[("agents", "action_value")]
    )
    return SafeSequential(
        net,
        QValueModule(
            action_value_key=("agents", "action_value"),
            action_mask_key=("agents", "action_mask") if mask else None,
            out_keys=[("agents", "action"), ("agents", "action_value"), ("agents", "chosen_action_value")],
            action_space="categorical",
        ),
    )


def _transitions(qnet: SafeSequential, seed: int) -> tuple[TensorDict, torch.Tensor, torch.Tensor]:
    """A batch of transitions whose taken actions are random allowed ones, never the greedy ones."""
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(B, N, A, generator=g) > 0.3
    mask[..., 0] = True
    obs = torch.randn(B, N, OBS, generator=g)
    with torch.no_grad():
        q = qnet[0](TensorDict({("agents", "observation"): obs}, [B]))["agents", "action_value"]
    q = q.masked_fill(~mask, torch.finfo(q.dtype).min)
    greedy = q.argmax(-1)
    scores = torch.rand(B, N, A, generator=g).masked_fill(~mask, -1.0)
    scores.scatter_(-1, greedy.unsqueeze(-1), -0.5)  # the greedy action is never taken (when avoidable)
    taken = scores.argmax(-1)
    assert (taken != greedy).float().mean() > 0.9
    agents = {"observation": obs, "action_mask": mask, "action": taken}
    next_agents = {
        "observation": torch.randn(B, N, OBS, generator=g),
        "action_mask": torch.ones(B, N, A, dtype=torch.bool),
    }
    td = TensorDict(
        {
            "agents": TensorDict(agents, [B, N]),
            "next": TensorDict(
                {
                    "agents": TensorDict(next_agents, [B, N]),
                    "reward": torch.full((B, 1), REWARD),
                    "done": torch.zeros(B, 1, dtype=torch.bool),
                    "terminated": torch.zeros(B, 1, dtype=torch.bool),
                },
                [B],
            ),
        },
        [B],
    )
    return td, q, taken


@pytest.mark.parametrize("mask", [False, True])
def test_qplex_inside_torchrl_qmixerloss_mixes_the_taken_actions(mask: bool) -> None:
    """Fails if QPLEX inside QMixerLoss is given the greedy actions (what the loss's copy holds)."""
    torch.manual_seed(0)
    qnet = _qnet(mask)
    mixer = QPLEXMixer(state_shape=STATE_SHAPE, mixing_embed_dim=16, n_agents=N, n_actions=A, device="cpu")
    _scramble(mixer, seed=1)
    loss = QMixerLoss(
        qnet, mixer_module(mixer, state_key=("agents", "observation")), action_space="categorical"
    )
    loss.make_value_estimator(ValueEstimators.TD0, gamma=0.0)
    td, q, taken = _transitions(qnet, seed=2)
    if not mask:
        q = qnet[0](td.clone())["agents", "action_value"].detach()
    out = loss(td)
    out["loss"].backward()
    q_tot = REWARD - td.get("td_error").squeeze(-1).sqrt()  # [B]: what the loss mixed

    def explicit(actions: torch.Tensor) -> torch.Tensor:
        chosen = q.gather(-1, actions.unsqueeze(-1))
        one_hot = F.one_hot(actions, A).float()
        with torch.no_grad():
            return DMAQMixer.forward(
                mixer, chosen, td["agents", "observation"], one_hot, q.max(-1, keepdim=True).values
            ).squeeze(-1)

    with_taken, with_greedy = explicit(taken), explicit(q.argmax(-1))
    torch.testing.assert_close(q_tot, with_taken, rtol=1e-5, atol=1e-3)
    # The greedy joint action would change Q_tot through lambda_i(s, a): the test can tell them apart.
    assert (with_taken - with_greedy).abs().mean() > 1.0
    assert all(p.grad is not None for p in mixer.parameters())

    # What the loss's copy holds at ("agents", "action"): the greedy actions, which is why QPLEXMixer does
    # not read it (the glue that one-hot encodes it is silently wrong).
    copy = qnet(td.clone(False))
    assert torch.equal(copy["agents", "action"], q.argmax(-1))
    assert not torch.equal(copy["agents", "action"], taken)


def test_qplex_mixer_has_qmixer_constructor_plus_n_actions() -> None:
    kwargs = {"state_shape": (6,), "mixing_embed_dim": 8, "n_agents": N, "device": "cpu"}
    TorchRLQMixer(**kwargs)
    mixer = QPLEXMixer(**kwargs, n_actions=A)
    assert (mixer.n_agents, mixer.n_actions, mixer.state_shape) == (N, A, (6,))
    assert QPLEXMixer((6,), 8, N, A, "cpu").state_dict().keys() == mixer.state_dict().keys()
    with pytest.raises(ValueError, match="n_actions"):
        QPLEXMixer((6,), 8, N, "cpu")  # QMixer's positional call, n_actions forgotten
    with pytest.raises(ValueError, match="takes 3 inputs"):
        mixer(torch.zeros(2, N, 1), torch.zeros(2, 6))
    with pytest.raises(ValueError, match="not in action_value"):  # values from another network
        mixer(torch.zeros(2, N, 1), torch.zeros(2, 6), torch.ones(2, N, A))


def test_mixer_module_names_the_missing_key_and_its_origin() -> None:
    module = mixer_module(QPLEXMixer((6,), 8, N, A))
    td = TensorDict(
        {("agents", "chosen_action_value"): torch.zeros(2, N, 1), "state": torch.zeros(2, 6)}, [2]
    )
    with pytest.raises(KeyError, match=r"action_value.*QValueModule"):
        module(td)
    module = mixer_module(TorchRLQMixer((6,), 8, N, "cpu"))
    with pytest.raises(KeyError, match=r"'state'.*stacked observations"):
        module(TensorDict({("agents", "chosen_action_value"): torch.zeros(2, N, 1)}, [2]))


# ---------------------------------------------------------------------------------------------- our loss
T = 5


def _torchrl_agent() -> QValueActor:
    """A QValueActor over a parameter-shared MultiAgentMLP, as TorchRL's and BenchMARL's QMIX build it."""
    net = MultiAgentMLP(OBS, A, N, centralised=False, share_params=True, depth=1, num_cells=16)
    spec = Composite(agents=Composite(action=Categorical(A, shape=(N,)), shape=(N,)))
    return QValueActor(
        net,
        in_keys=[("agents", "observation")],
        spec=spec,
        action_value_key=("agents", "action_value"),
        action_key=("agents", "action"),
        chosen_action_value_key=("agents", "chosen_action_value"),
    )


def _collector_batch() -> TensorDict:
    """``[2, T]`` as a collector writes it: row 0 holds an episode terminated at t=1 and one truncated at
    t=4; row 1 one episode that ends at t=4. Observation values encode (row, step): 10 e + t (+0.5 next)."""
    E = 2
    obs = (10 * torch.arange(E).view(E, 1) + torch.arange(T)).float().view(E, T, 1, 1).expand(E, T, N, OBS)
    done = torch.zeros(E, T, 1, dtype=torch.bool)
    done[0, 1] = done[0, 4] = done[1, 4] = True
    terminated = torch.zeros_like(done)
    terminated[0, 1] = True
    g = torch.Generator().manual_seed(0)
    return TensorDict(
        {
            ("agents", "observation"): obs.clone(),
            ("agents", "action"): torch.randint(A, (E, T, N), generator=g),
            ("next", "agents", "observation"): obs + 0.5,
            ("next", "agents", "reward"): torch.randn(E, T, N, 1, generator=g),
            ("next", "done"): done,
            ("next", "terminated"): terminated,
        },
        [E, T],
    )


def test_episodes_that_end_early_are_split_padded_and_kept() -> None:
    batch = _collector_batch()
    kw = {"step_keys": [("agents", "observation")], "reward_key": ("agents", "reward")}
    ep = episodes_from_rollout(batch, **kw)
    assert ep.batch_size == (3, T + 1)  # three episodes, each padded to T + 1 rows
    assert ep["filled"].sum(-1).tolist() == [2, 3, 5]
    assert int(ep["filled"].sum()) == batch.numel()  # every transition kept
    first_obs = ep["agents", "observation"][:, :, 0, 0]
    torch.testing.assert_close(
        first_obs[0], torch.tensor([0, 1, 1.5, 1.5, 1.5, 1.5])
    )  # o_0, o_1, o_2 = final
    torch.testing.assert_close(first_obs[1], torch.tensor([2, 3, 4, 4.5, 4.5, 4.5]))
    torch.testing.assert_close(first_obs[2], torch.tensor([10, 11, 12, 13, 14, 14.5]))
    assert ep["terminated"][:, :, 0].tolist()[0][:2] == [False, True] and not ep["terminated"][1:].any()
    assert ep["done"][0, 1] and ep["done"][1, 2] and ep["done"][2, 4] and ep["done"][0, 2:].all()
    reward = batch["next", "agents", "reward"]
    torch.testing.assert_close(ep["reward"][1, :3], reward[0, 2:5])  # per agent, [.., N, 1]
    assert not ep["reward"][0, 2:].any() and not ep["agents", "action"][0, 2:].any()

    # A row cut by the collector: refused for whole episodes, kept as done-not-terminated otherwise.
    cut = batch[:, :4]
    with pytest.raises(ValueError, match="whole_episodes=False"):
        episodes_from_rollout(cut, **kw)
    ep = episodes_from_rollout(cut, **kw, whole_episodes=False)
    assert ep["filled"].sum(-1).tolist() == [2, 2, 4] and ep.batch_size == (3, 5)
    assert ep["done"][1, 1] and not ep["terminated"][1, 1] and ep["done"][2, 3] and not ep["terminated"][2, 3]
    torch.testing.assert_close(ep["agents", "observation"][2, 4, 0, 0], torch.tensor(13.5))  # bootstrap state


def test_value_factorisation_loss_takes_a_torchrl_agent_with_early_ends_and_per_agent_rewards() -> None:
    torch.manual_seed(0)
    agent = _torchrl_agent()
    loss = ValueFactorisationLoss(agent, VDNMixer(N, "cpu"), gamma=0.5)  # no state, no mask
    batch = _collector_batch()
    ep = episodes_from_rollout(batch, step_keys=[("agents", "observation")], reward_key=("agents", "reward"))
    taken = ep["agents", "action"].clone()
    out = loss(ep)
    out["loss"].backward()
    assert torch.equal(ep["agents", "action"], taken)  # the agent's greedy actions never overwrite them
    assert all(p.grad is not None for p in agent.parameters())

    # By hand: VDN's Q_tot of the taken actions, team reward = mean over agents, one-step double-Q targets.
    q = agent[0](ep.select(("agents", "observation")).clone())["agents", "action_value"].detach()
    filled = ep["filled"][:, :-1]
    q_taken = q.gather(-1, taken.unsqueeze(-1)).squeeze(-1).sum(-1)[:, :-1]
    next_q = q.max(-1).values.sum(-1)[:, 1:]  # target net == online net at the start
    team = ep["reward"][:, :-1].mean(-2).squeeze(-1)
    y = team + 0.5 * next_q * (~ep["terminated"][:, :-1, 0])
    torch.testing.assert_close(out["q_taken_mean"], q_taken[filled].mean())
    torch.testing.assert_close(out["target_mean"], y[filled].mean())

    summed = ValueFactorisationLoss(agent, VDNMixer(N, "cpu"), gamma=0.5, reward_reduction="sum")(ep)
    torch.testing.assert_close(summed["target_mean"] - out["target_mean"], ((N - 1) * team)[filled].mean())
    masked = ep.clone()
    masked.set(("agents", "action_mask"), torch.ones(*ep.batch_size, N, A, dtype=torch.bool))
    torch.testing.assert_close(loss(masked)["loss"], out["loss"])  # no mask == all allowed


def test_qplex_mixer_in_our_loss_equals_dmaq_mixer() -> None:
    torch.manual_seed(0)
    agent = _torchrl_agent()
    ep = episodes_from_rollout(
        _collector_batch(), step_keys=[("agents", "observation")], reward_key=("agents", "reward")
    )
    qplex = QPLEXMixer(STATE_SHAPE, 16, N, A)
    dmaq = DMAQMixer(STATE_SHAPE, N, A, hypernet_embed=16, adv_hypernet_embed=16)
    dmaq.load_state_dict(qplex.state_dict())
    outs = []
    for mixer in (qplex, dmaq):
        loss = ValueFactorisationLoss(agent, mixer)
        loss.set_keys(state=("agents", "observation"))
        outs.append(loss(ep)["loss"])
    torch.testing.assert_close(outs[0], outs[1])


def test_missing_keys_are_named_with_their_origin() -> None:
    ep = episodes_from_rollout(
        _collector_batch(), step_keys=[("agents", "observation")], reward_key=("agents", "reward")
    )
    loss = ValueFactorisationLoss(_torchrl_agent(), TorchRLQMixer((6,), 8, N, "cpu"))
    with pytest.raises(KeyError, match=r"state key 'state'.*stacked observations.*set_keys"):
        loss(ep)
    vdn = ValueFactorisationLoss(_torchrl_agent(), VDNMixer(N, "cpu"))
    with pytest.raises(
        KeyError, match=r"agent network reads.*lacks \[\('agents', 'observation'\)\].*step_keys"
    ):
        vdn(ep.exclude(("agents", "observation")))
    with pytest.raises(TypeError, match="agent_network must be"):
        ValueFactorisationLoss(nn.Linear(OBS, A), VDNMixer(N, "cpu"))
    with pytest.raises(ValueError, match="reward_reduction"):
        ValueFactorisationLoss(_torchrl_agent(), VDNMixer(N, "cpu"), reward_reduction="max")
    with pytest.raises(KeyError, match=r"\('agents', 'action_mask'\).*step key"):
        episodes_from_rollout(_collector_batch())

    step = AgentStep(RecurrentAgent(OBS, A, N, hidden_dim=4))
    td = TensorDict({("agents", "observation"): torch.zeros(2, N, OBS)}, [2])
    with pytest.raises(KeyError, match=r"rnn_hidden.*recurrent_primer.*step_count.*StepCounter"):
        step(td)
