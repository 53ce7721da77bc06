"""The config's choices are written once (:mod:`mcrs.choices`): the schema's enums and the modules that
implement them read the same lists, every choice builds, and a name outside the list is refused."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from tensordict import TensorDict

from mcrs import choices
from mcrs.experiment import config, schema

#: The config's choice lists, each with its enum in the schema.
ENUMS = {
    "MIXERS": schema.Mixer,
    "EMBEDDINGS": schema.Embedding,
    "DELTA_RULES": schema.DeltaRule,
    "SHAPES": schema.Neighbourhood,
    "TIME_LIMITS": schema.TimeLimit,
    "INCENTIVES": schema.Incentive,
    "OPTIMIZERS": schema.Optimizer,
    "COLLECTORS": schema.Collector,
    "MODEL_NAMES": schema.ModelName,
    "LOGGER_BACKENDS": schema.LoggerBackend,
    "WANDB_MODES": schema.WandbMode,
}


def test_every_list_has_its_enum_and_the_old_names_are_the_same_objects() -> None:
    """The enums' members are the lists' values, and where users import a list today they get the one
    object of mcrs.choices, not a copy."""
    from mcrs import models
    from mcrs.experiment.training import replay
    from mcrs.memory import delta, index
    from mcrs.models import embeddings, mixers
    from mcrs.objectives import incentive
    from mcrs.objectives.value_factorisation import ValueFactorisationLoss

    assert sorted(ENUMS) == sorted(choices.__all__)
    for name, enum in ENUMS.items():
        assert tuple(member.value for member in enum) == getattr(choices, name), name
    for name in ("MIXERS", "EMBEDDINGS", "DELTA_RULES", "SHAPES", "TIME_LIMITS", "INCENTIVES"):
        assert getattr(config, name) is getattr(choices, name), name
    same = [
        (models.MIXERS, mixers.MIXERS, choices.MIXERS),
        (models.EMBEDDINGS, embeddings.EMBEDDINGS, choices.EMBEDDINGS),
        (delta.DELTA_RULES, choices.DELTA_RULES),
        (index.SHAPES, choices.SHAPES),
        (replay.TIME_LIMITS, choices.TIME_LIMITS),
        (incentive.INCENTIVES, ValueFactorisationLoss.INCENTIVES, choices.INCENTIVES),
    ]
    for objects in same:
        assert all(o is objects[-1] for o in objects), objects


def test_the_choices_load_nothing_but_the_standard_library() -> None:
    code = "import sys, mcrs.choices; print(sorted(m for m in sys.modules if m.startswith(('mcrs', 'torch', 'omegaconf', 'hydra'))))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "['mcrs', 'mcrs.choices']"


def test_every_mixer_builds_and_no_other() -> None:
    from mcrs.models.mixers import make_mixer

    built = {name: make_mixer(name, n_agents=2, state_shape=(6,), n_actions=3) for name in choices.MIXERS}
    assert len({type(mixer) for mixer in built.values()}) == len(choices.MIXERS)
    with pytest.raises(ValueError, match=r"unknown mixer 'qtran'; allowed: qmix, vdn, qplex"):
        make_mixer("qtran", n_agents=2, state_shape=(6,), n_actions=3)


def test_every_embedding_builds_and_no_other() -> None:
    from mcrs.env import scenario
    from mcrs.models.embeddings import make_embedding

    env = scenario("map10")
    built = {
        kind: make_embedding(kind, env.state_dim, (env.width, env.height)) for kind in choices.EMBEDDINGS
    }
    assert len({type(embedding) for embedding in built.values()}) == len(choices.EMBEDDINGS)
    with pytest.raises(ValueError, match=r"kind must be one of \('random', 'fc', 'cnn'\), got 'lstm'"):
        make_embedding("lstm", env.state_dim)


def test_every_delta_rule_and_neighbourhood_builds_and_no_other() -> None:
    from mcrs.memory.delta import match_tolerance
    from mcrs.memory.index import GridIndex

    for rule in choices.DELTA_RULES:
        for shape in choices.SHAPES:
            tolerance = match_tolerance(1.3e-3, rule, shape, key_dim=4)
            assert GridIndex(4, tolerance, capacity=8, shape=shape).shape == shape
    with pytest.raises(ValueError, match="delta rule must be one of volume, literal, got 'area'"):
        match_tolerance(1.3e-3, "area", "box", key_dim=4)
    with pytest.raises(ValueError, match="shape must be one of ball, box, got 'cube'"):
        GridIndex(4, 0.1, capacity=8, shape="cube")


def test_every_time_limit_is_taken_and_no_other() -> None:
    """A choice passes the time-limit check and reaches the batch's (test_replay.py builds both)."""
    from mcrs.experiment.training.replay import episodes_from_rollout

    flat = TensorDict({}, batch_size=[3])
    for time_limit in choices.TIME_LIMITS:
        with pytest.raises(ValueError, match="expected a collector batch"):
            episodes_from_rollout(flat, time_limit=time_limit)
    with pytest.raises(ValueError, match=r"time_limit='never': must be one of \['terminal', 'bootstrap'\]"):
        episodes_from_rollout(flat, time_limit="never")


def test_every_incentive_builds_and_no_other() -> None:
    from mcrs.objectives.incentive import INCENTIVE_TYPES, make_incentive

    assert tuple(INCENTIVE_TYPES) == choices.INCENTIVES
    assert [make_incentive(name).name for name in choices.INCENTIVES] == list(choices.INCENTIVES)
    with pytest.raises(ValueError, match="incentive must be one of none, fixed, change, got 'always'"):
        make_incentive("always")


def test_every_optimizer_builds_its_own() -> None:
    from mcrs.experiment.training.learner import make_optimizer

    params = [torch.nn.Parameter(torch.zeros(2))]
    built = {
        name: type(make_optimizer(params, config.TrainConfig(optimizer=name))) for name in choices.OPTIMIZERS
    }
    assert built == {"rmsprop": torch.optim.RMSprop, "adam": torch.optim.Adam}


def test_a_logger_outside_the_choices_is_refused_naming_them(tmp_path) -> None:
    from mcrs.experiment.run.logging import make_logger

    with pytest.raises(
        ValueError, match=r"logger\.backend='mlflow': allowed values are csv, wandb, tensorboard"
    ):
        make_logger("mlflow", tmp_path, {})
    with pytest.raises(ValueError, match=r"logger\.wandb_mode='shared': allowed values are offline, online"):
        make_logger("wandb", tmp_path, {}, mode="shared")
