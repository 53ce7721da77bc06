"""State embeddings phi (spec "Embeddings phi", paper eq. 31 and figure 3f).

Checked: the key shapes for every kind, map and leading batch shape; that the CNN reads the env's map image
(the first 2 * cells state values, x-major) and its last layer covers the whole remaining map; that the fast
inference path (chunks, channels-last, the last conv as a matrix product) computes the plain convolutions;
the random projection's distribution and fixedness; that training reduces eq. 31 and pulls states with
similar returns together; argument checks and determinism from the seed.
"""

from __future__ import annotations

import copy

import pytest
import torch
from torch.nn import functional as F

from mcrs.env.config import scenario
from mcrs.env.core import MCRSCore
from mcrs.models.embedding_training import EmbeddingTrainer, embedding_loss
from mcrs.models.embeddings import (
    EMBEDDINGS,
    CNNEmbedding,
    RandomProjection,
    default_cnn_kernels,
    make_embedding,
)

MAPS = ["map10", "map15", "map20"]


def _dims(name: str) -> tuple[int, tuple[int, int]]:
    cfg = scenario(name)
    return cfg.state_dim, (cfg.width, cfg.height)


def _reference_cnn(emb: CNNEmbedding, state: torch.Tensor) -> torch.Tensor:
    """The CNN branch written plainly: NCHW convolutions (the last one a real conv) on the env's state_map."""
    width, height = emb.map_shape
    h = state[:, : 2 * width * height].reshape(-1, 2, width, height)
    for conv in emb.convs:
        h = F.relu(conv(h))
    assert h.shape[-2:] == (1, 1)
    return h.flatten(1)


# ------------------------------------------------------------------------------------------------ shapes
@pytest.mark.parametrize("kind", EMBEDDINGS)
@pytest.mark.parametrize("name", MAPS)
def test_keys_have_key_dim_for_every_kind_and_map(kind: str, name: str) -> None:
    state_dim, map_shape = _dims(name)
    emb = make_embedding(kind, state_dim, map_shape, key_dim=4)
    assert (emb.state_dim, emb.key_dim, emb.trainable) == (state_dim, 4, kind != "random")
    state, time = torch.rand(7, state_dim), torch.rand(7)
    assert emb(state, time).shape == (7, 4)
    # Any leading shape; the same keys as the flat batch.
    keys = emb(state[:6].view(2, 3, state_dim), time[:6].view(2, 3))
    assert keys.shape == (2, 3, 4)
    torch.testing.assert_close(keys.view(6, 4), emb(state[:6], time[:6]))
    assert emb(state[0], time[0]).shape == (4,)


@pytest.mark.parametrize("kind", ["fc", "cnn"])
def test_decoder_reconstructs_state_and_return_shapes(kind: str) -> None:
    state_dim, map_shape = _dims("map10")
    emb = make_embedding(kind, state_dim, map_shape, key_dim=3, hidden_dim=16)
    state, time = torch.rand(2, 5, state_dim), torch.rand(2, 5)
    keys = emb(state, time)
    state_hat, return_hat = emb.reconstruct(keys, time)
    assert state_hat.shape == (2, 5, state_dim) and return_hat.shape == (2, 5)
    # A scalar time broadcasts over the batch.
    torch.testing.assert_close(emb(state, 0.5), emb(state, torch.full((2, 5), 0.5)))


@pytest.mark.parametrize("kind", ["fc", "cnn"])
def test_trainable_embeddings_use_the_time(kind: str) -> None:
    state_dim, map_shape = _dims("map10")
    emb = make_embedding(kind, state_dim, map_shape)
    state = torch.rand(4, state_dim)
    assert not torch.allclose(emb(state, torch.zeros(4)), emb(state, torch.ones(4)))


# ---------------------------------------------------------------------------------------------------- CNN
@pytest.mark.parametrize(
    ("map_shape", "last_kernel"),
    [((10, 10), (3, 3)), ((15, 15), (4, 4)), ((20, 20), (5, 5)), ((12, 7), (3, 2)), ((9, 16), (3, 4))],
)
def test_cnn_last_layer_covers_the_whole_remaining_map(map_shape, last_kernel) -> None:
    assert default_cnn_kernels(map_shape) == [(3, 3), (3, 3), last_kernel]
    state_dim = 2 * map_shape[0] * map_shape[1] + 6
    emb = CNNEmbedding(state_dim, map_shape)
    assert emb.convs[-1].kernel_size == last_kernel and emb.convs[-1].stride == (1, 1)
    assert [c.stride for c in emb.convs[:-1]] == [(2, 2), (2, 2)]
    h = torch.rand(3, 2, *map_shape)
    for conv in emb.convs:
        h = conv(h)
    assert h.shape == (3, 32, 1, 1)
    # Every map cell reaches the output: the receptive field of the single output position is the whole map.
    image = torch.rand(1, 2, *map_shape, requires_grad=True)
    h = image
    for conv in emb.convs:
        h = conv(h)
    h.sum().backward()
    assert (image.grad != 0).all()


def test_paper_figure_3f_kernels_for_20x20() -> None:
    state_dim, map_shape = _dims("map20")
    emb = make_embedding("cnn", state_dim, map_shape)
    assert [c.kernel_size for c in emb.convs] == [(3, 3), (3, 3), (5, 5)]
    assert [c.out_channels for c in emb.convs] == [8, 16, 32]


@pytest.mark.parametrize("name", MAPS)
def test_cnn_reads_the_env_state_map(name: str) -> None:
    """The CNN's input is the env's ``state_map`` (first 2 * cells values, x-major), the rest goes to the FC."""
    core = MCRSCore(scenario(name, num_envs=3))
    result = core.reset()
    generator = torch.Generator().manual_seed(0)
    for _ in range(4):  # a few allowed random moves, so the maps are no longer uniform
        scores = torch.rand(result.action_mask.shape, generator=generator).masked_fill(
            ~result.action_mask, -1
        )
        result = core.step(scores.argmax(-1))
    state = result.state
    emb = make_embedding("cnn", state.shape[-1], (core.config.width, core.config.height), seed=3)
    h = result.state_map
    for conv in emb.convs:
        h = F.relu(conv(h))
    torch.testing.assert_close(emb.map_features(state), h.flatten(1))


def test_cnn_splits_map_and_positions() -> None:
    state_dim, map_shape = _dims("map10")
    cells = map_shape[0] * map_shape[1]
    emb = make_embedding("cnn", state_dim, map_shape, seed=1)
    state = torch.rand(4, state_dim, requires_grad=True)
    # The conv branch depends on the map part only ...
    emb.map_features(state).sum().backward()
    assert (state.grad[:, : 2 * cells] != 0).any() and (state.grad[:, 2 * cells :] == 0).all()
    # ... and the position part changes the keys only through the FC branch.
    moved = state.detach().clone()
    moved[:, 2 * cells] += 0.5
    torch.testing.assert_close(emb.map_features(moved), emb.map_features(state.detach()))
    assert not torch.allclose(emb(moved, torch.zeros(4)), emb(state.detach(), torch.zeros(4)))
    # The key depends on the map (through the conv) and the positions (through the FC): both gradients flow.
    state.grad = None
    emb(state, torch.zeros(4)).square().sum().backward()
    assert (state.grad[:, : 2 * cells] != 0).any() and (state.grad[:, 2 * cells :] != 0).any()


@pytest.mark.parametrize("map_shape", [(10, 10), (20, 20), (12, 7)])
def test_cnn_fast_path_computes_the_plain_convolutions(map_shape) -> None:
    """Channels-last layout and the last conv as a matrix product give the plain NCHW convolutions."""
    state_dim = 2 * map_shape[0] * map_shape[1] + 8
    emb = CNNEmbedding(state_dim, map_shape, channels=(4, 6, 5))
    state = torch.rand(9, state_dim)
    torch.testing.assert_close(emb.map_features(state), _reference_cnn(emb, state))


@pytest.mark.parametrize("kind", EMBEDDINGS)
def test_chunked_inference_equals_the_autograd_pass(kind: str) -> None:
    state_dim, map_shape = _dims("map15")
    emb = make_embedding(kind, state_dim, map_shape, seed=2)
    emb.inference_chunk = 64  # several chunks and a partial last one
    state, time = torch.rand(3, 100, state_dim), torch.rand(3, 100)
    expected = emb(state, time)  # grad enabled: one pass
    with torch.inference_mode():
        chunked = emb(state, time)
    with torch.no_grad():
        chunked_no_grad = emb(state, time)
    torch.testing.assert_close(chunked, expected)
    torch.testing.assert_close(chunked_no_grad, expected)


# ------------------------------------------------------------------------------------------- random (EMC)
def test_random_projection_is_fixed_gaussian_with_variance_one_over_key_dim() -> None:
    state_dim, map_shape = _dims("map20")
    emb = make_embedding("random", state_dim, map_shape, key_dim=4, seed=5)
    assert isinstance(emb, RandomProjection) and not emb.trainable
    assert list(emb.parameters()) == []
    assert "projection" in emb.state_dict()
    p = emb.projection
    assert p.shape == (state_dim, 4)
    assert abs(p.mean().item()) < 0.05
    assert p.std().item() == pytest.approx(0.5, rel=0.05)  # N(0, 1/key_dim): std 1/sqrt(4)
    wide = RandomProjection(state_dim, key_dim=16, seed=5)
    assert wide.projection.std().item() == pytest.approx(0.25, rel=0.05)
    state = torch.rand(3, state_dim)
    torch.testing.assert_close(emb(state, torch.rand(3)), state @ p)
    torch.testing.assert_close(emb(state, torch.zeros(3)), emb(state))  # time is ignored


def test_random_projection_seeded_and_survives_state_dict() -> None:
    state_dim = 226
    global_rng = torch.random.get_rng_state()
    a = make_embedding("random", state_dim, seed=7)
    b = make_embedding("random", state_dim, seed=7)
    c = make_embedding("random", state_dim, seed=8)
    assert torch.equal(torch.random.get_rng_state(), global_rng)
    assert torch.equal(a.projection, b.projection)
    assert not torch.allclose(a.projection, c.projection)
    c.load_state_dict(a.state_dict())
    state = torch.rand(5, state_dim)
    torch.testing.assert_close(c(state), a(state))


def test_random_projection_is_not_trained() -> None:
    emb = make_embedding("random", 226)
    with pytest.raises(TypeError, match="not trainable"):
        EmbeddingTrainer(emb)
    with pytest.raises(TypeError, match="not trainable"):
        embedding_loss(emb, torch.rand(2, 226), torch.rand(2), torch.rand(2))
    with pytest.raises(TypeError, match="no decoder"):
        emb.reconstruct(torch.rand(2, 4), torch.rand(2))


# ------------------------------------------------------------------------------------------- determinism
@pytest.mark.parametrize("kind", ["fc", "cnn"])
def test_parameters_drawn_from_the_seed_without_touching_the_global_rng(kind: str) -> None:
    state_dim, map_shape = _dims("map10")
    torch.manual_seed(123)
    before = torch.random.get_rng_state()
    a = make_embedding(kind, state_dim, map_shape, seed=4)
    assert torch.equal(torch.random.get_rng_state(), before)
    b = make_embedding(kind, state_dim, map_shape, seed=4)
    c = make_embedding(kind, state_dim, map_shape, seed=5)
    for (name, pa), pb, pc in zip(
        a.state_dict().items(), b.state_dict().values(), c.state_dict().values(), strict=True
    ):
        assert torch.equal(pa, pb), name
        assert not torch.equal(pa, pc), name


# ------------------------------------------------------------------------------------------------- checks
@pytest.mark.parametrize(
    ("kwargs", "argument"),
    [
        ({"kind": "mlp"}, "kind"),
        ({"kind": "cnn", "map_shape": None}, "map_shape"),
        ({"kind": "cnn", "map_shape": (11, 11)}, "map_shape"),  # 242 > 226 values
        ({"kind": "cnn", "map_shape": (0, 10)}, "map_shape"),
        ({"kind": "cnn", "map_shape": (10,)}, "map_shape"),
        ({"kind": "cnn", "cnn_channels": ()}, "channels"),
        ({"kind": "cnn", "cnn_channels": (8, 0, 4)}, "channels"),
        ({"kind": "fc", "key_dim": 0}, "key_dim"),
        ({"kind": "fc", "hidden_dim": -1}, "hidden_dim"),
        ({"kind": "random", "state_dim": 0}, "state_dim"),
        ({"kind": "random", "seed": 1.5}, "seed"),
    ],
)
def test_bad_arguments_are_refused_by_name(kwargs: dict, argument: str) -> None:
    args = {"kind": "cnn", "state_dim": 226, "map_shape": (10, 10), **kwargs}
    with pytest.raises(ValueError, match=argument):
        make_embedding(**args)


def test_unknown_kind_lists_the_allowed_values() -> None:
    with pytest.raises(ValueError, match=r"kind.*'random', 'fc', 'cnn'"):
        make_embedding("mlp", 226)


def test_cnn_kernels_must_reduce_the_map_to_one_position() -> None:
    with pytest.raises(ValueError, match=r"kernels.*not 1x1"):
        CNNEmbedding(226, (10, 10), kernels=[3, 3, 2])
    with pytest.raises(ValueError, match=r"kernels.*no output position"):
        CNNEmbedding(226, (10, 10), kernels=[3, 3, 5])
    with pytest.raises(ValueError, match="kernels"):
        CNNEmbedding(226, (10, 10), kernels=[3, 3])
    emb = CNNEmbedding(226, (10, 10), kernels=[3, 3, (3, 3)])
    assert emb.convs[-1].kernel_size == (3, 3)


@pytest.mark.parametrize("kind", EMBEDDINGS)
def test_state_and_time_shapes_checked_at_forward(kind: str) -> None:
    emb = make_embedding(kind, 226, (10, 10))
    with pytest.raises(ValueError, match=r"state.*226"):
        emb(torch.rand(3, 502), torch.rand(3))
    if kind != "random":
        with pytest.raises(ValueError, match="time"):
            emb(torch.rand(3, 226), torch.rand(4))


def test_trainer_arguments_checked() -> None:
    emb = make_embedding("fc", 226)
    for kwargs, argument in [
        ({"lr": 0.0}, "lr"),
        ({"batch_size": 0}, "batch_size"),
        ({"samples": -5}, "samples"),
        ({"samples": 100, "batch_size": 128}, "samples"),
        ({"state_weight": -1.0}, "state_weight"),
    ]:
        with pytest.raises(ValueError, match=argument):
            EmbeddingTrainer(emb, **kwargs)
    trainer = EmbeddingTrainer(emb, batch_size=8, samples=16)
    with pytest.raises(ValueError, match="sample"):
        trainer.fit(lambda n: (torch.rand(n, 226), torch.rand(n, 1), torch.rand(n)))


# ----------------------------------------------------------------------------------------------- training
def test_embedding_loss_is_eq_31_with_per_value_means() -> None:
    """Both terms are means over their values (EMU's MSELoss): the state term is not a sum over D."""
    emb = make_embedding("fc", 30, hidden_dim=8)
    state, time, returns = torch.rand(6, 30), torch.rand(6), torch.randn(6)
    loss, stats = embedding_loss(emb, state, time, returns, state_weight=0.25)
    state_hat, return_hat = emb.reconstruct(emb(state, time), time)
    loss_return = ((returns - return_hat) ** 2).mean()
    loss_state = ((state - state_hat) ** 2).mean()
    torch.testing.assert_close(loss, loss_return + 0.25 * loss_state)
    assert stats["loss_return"] == pytest.approx(loss_return.item(), rel=1e-5)
    assert stats["loss_state"] == pytest.approx(loss_state.item(), rel=1e-5)
    assert stats["loss_state_weighted"] == pytest.approx(0.25 * loss_state.item(), rel=1e-5)


@pytest.mark.parametrize(
    ("kind", "name"), [("fc", "map10"), ("cnn", "map10"), ("cnn", "map15"), ("cnn", "map20")]
)
def test_the_return_term_outweighs_the_weighted_state_term_on_real_states(kind: str, name: str) -> None:
    """Eq. 31 with lambda_1 = 0.1 on real rollouts of each map: in every fit (fresh and trained) the
    return term carries at least the weight of lambda_1 times the reconstruction term."""
    from mcrs_benchmarks.memory import rollout

    from mcrs.env.config import scenario

    config = scenario(name)
    state, _, reward = rollout(config, 8, seed=0)
    returns = reward.flip(1).cumsum(1).flip(1)  # undiscounted returns-to-go: real scale and spread
    T = state.shape[1]
    time = (torch.arange(T, dtype=torch.float32) / T).expand(state.shape[0], T)
    data = (state.flatten(0, 1), time.flatten(), returns.flatten())
    emb = make_embedding(kind, config.state_dim, (config.width, config.height), hidden_dim=32, seed=0)
    trainer = EmbeddingTrainer(emb, batch_size=100, samples=800, state_weight=0.1)
    for _ in range(3):
        stats = trainer.fit(lambda n: data, generator=torch.Generator().manual_seed(0))
        assert stats["loss_return"] >= stats["loss_state_weighted"] > 0


def test_embedding_gradients_are_clipped() -> None:
    """The optimiser sees gradients of norm at most grad_clip (Adam's step size hides the clip in the
    parameters, so the test looks at the gradients the optimiser is given)."""
    emb = make_embedding("fc", 30, hidden_dim=8, seed=0)
    state, time, returns = torch.rand(64, 30), torch.rand(64), torch.randn(64)
    trainer = EmbeddingTrainer(emb, batch_size=64, samples=64, grad_clip=0.01)
    seen: list[float] = []
    original = trainer.optimizer.step

    def step(*args, **kwargs):
        norms = [p.grad.norm() for p in emb.parameters() if p.grad is not None]
        seen.append(float(torch.linalg.vector_norm(torch.stack(norms))))
        return original(*args, **kwargs)

    trainer.optimizer.step = step
    trainer.fit(lambda n: (state, time, returns))
    assert seen and seen[0] == pytest.approx(0.01, rel=1e-4)
    with pytest.raises(ValueError, match="grad_clip must be positive"):
        EmbeddingTrainer(emb, grad_clip=0.0)


def _synthetic_sampler(state_dim: int, cells: int, seed: int):
    """States with a random fraction of found targets on the map; the return grows with it (up to 400)."""
    g = torch.Generator().manual_seed(seed)

    def sample(n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        level = torch.rand(n, 1, generator=g)
        state = (torch.rand(n, state_dim, generator=g) < 0.5).float() * 0.5
        state[:, cells : 2 * cells] = (torch.rand(n, cells, generator=g) < level).float()  # m(F)
        time = torch.rand(n, generator=g)
        returns = 400.0 * state[:, cells : 2 * cells].mean(-1)
        return state, time, returns

    return sample


@pytest.mark.parametrize("kind", ["fc", "cnn"])
def test_training_reduces_the_loss_and_groups_states_by_return(kind: str) -> None:
    map_shape = (6, 6)
    cells = map_shape[0] * map_shape[1]
    state_dim = 2 * cells + 8
    emb = make_embedding(kind, state_dim, map_shape, hidden_dim=32, seed=0)
    trainer = EmbeddingTrainer(emb, lr=3e-3, batch_size=128, samples=128 * 25)
    sample = _synthetic_sampler(state_dim, cells, seed=1)
    test_state, test_time, test_returns = _synthetic_sampler(state_dim, cells, seed=2)(400)

    def grouping() -> float:
        """Mean key distance of pairs with close returns over that of pairs with far returns."""
        with torch.no_grad():
            keys = emb(test_state, test_time)
        dist = torch.cdist(keys, keys)
        gap = (test_returns[:, None] - test_returns[None, :]).abs()
        return (dist[gap < 20].mean() / dist[gap > 200].mean()).item()

    first = trainer.fit(sample, generator=torch.Generator().manual_seed(0))
    for _ in range(7):
        last = trainer.fit(sample, generator=torch.Generator().manual_seed(0))
    assert first["steps"] == last["steps"] == 25
    assert last["loss"] < 0.5 * first["loss"]
    assert last["loss_return"] < 0.2  # standardised returns: variance 1 before training
    assert first["return_mean"] == pytest.approx(200.0, rel=0.1)
    assert grouping() < 0.25


def test_trainer_accepts_samples_made_under_inference_mode() -> None:
    """The memory decodes its states without autograd; training on them must still work."""
    emb = make_embedding("cnn", 80, (6, 6), hidden_dim=8)
    with torch.inference_mode():
        data = _synthetic_sampler(80, 36, seed=0)(64)
    before = [p.clone() for p in emb.parameters()]
    stats = EmbeddingTrainer(emb, batch_size=32, samples=64).fit(lambda n: data)
    assert stats["steps"] == 2
    assert all(not torch.equal(a, b) for a, b in zip(before, emb.parameters(), strict=True))


def test_trainer_is_deterministic_and_checkpoints_the_optimizer() -> None:
    state_dim, map_shape = 2 * 36 + 8, (6, 6)

    def run(emb, trainer, seed):
        return trainer.fit(
            _synthetic_sampler(state_dim, 36, seed), generator=torch.Generator().manual_seed(seed)
        )

    a = make_embedding("cnn", state_dim, map_shape, hidden_dim=16, seed=3)
    b = make_embedding("cnn", state_dim, map_shape, hidden_dim=16, seed=3)
    ta = EmbeddingTrainer(a, batch_size=32, samples=128)
    tb = EmbeddingTrainer(b, batch_size=32, samples=128)
    assert run(a, ta, 1) == run(b, tb, 1)
    for pa, pb in zip(a.parameters(), b.parameters(), strict=True):
        assert torch.equal(pa, pb)

    # Resume from a checkpoint: same result as going on.
    c = copy.deepcopy(a)
    tc = EmbeddingTrainer(c, batch_size=32, samples=128)
    tc.load_state_dict(copy.deepcopy(ta.state_dict()))
    assert run(a, ta, 2) == run(c, tc, 2)
    for pa, pc in zip(a.parameters(), c.parameters(), strict=True):
        assert torch.equal(pa, pc)
    # Without the optimizer's moments the step differs (the checkpoint carries them).
    d = copy.deepcopy(b)
    fresh = EmbeddingTrainer(d, batch_size=32, samples=128)
    run(d, fresh, 2)
    assert any(not torch.equal(pa, pd) for pa, pd in zip(a.parameters(), d.parameters(), strict=True))


def test_embedding_modules_copy_like_any_module() -> None:
    """The memory keeps a module on the learner's device and may copy it: the keys must come along."""
    for kind in EMBEDDINGS:
        emb = make_embedding(kind, 226, (10, 10))
        clone = copy.deepcopy(emb)
        state, time = torch.rand(2, 226), torch.rand(2)
        torch.testing.assert_close(clone(state, time), emb(state, time))
