"""The algorithm registry (mcrs/experiment/training/algorithms.py) and EMU's incentive strategies
(mcrs/objectives/incentive.py): every preset has its algorithm, the parts are chosen once and shared, an
algorithm of one's own registers and trains, and the memory and the curiosity reach the batch one way."""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from torch import nn
from torchrl.modules.models.multiagent import VDNMixer

from mcrs.env.config import scenario
from mcrs.experiment.config import ConfigError, compose, validate
from mcrs.experiment.run.checkpoint import CheckpointError, save_atomic
from mcrs.experiment.training.algorithms import (
    ALGORITHMS,
    BUILT_IN,
    Algorithm,
    UnregisteredAlgorithm,
    algorithm_for,
    register_algorithm,
)
from mcrs.experiment.training.callbacks import Callback
from mcrs.experiment.training.learner import Learner
from mcrs.experiment.training.trainer import Experiment
from mcrs.models.mixers import make_mixer
from mcrs.objectives import ValueFactorisationLoss
from mcrs.objectives.incentive import EvaluationThreshold, FixedThreshold, Incentive, make_incentive
from mcrs.train import CONFIG_DIR, option_errors
from tests.train_helpers import TINY, TINY_MEMORY

CPU = torch.device("cpu")


def test_every_algo_preset_is_a_built_in_algorithm() -> None:
    names = {OmegaConf.load(p).name for p in (Path(CONFIG_DIR) / "algo").glob("*.yaml")}
    assert names == set(BUILT_IN)
    assert all(ALGORITHMS[name] is Algorithm for name in BUILT_IN)
    # A label nobody registered is the built-in algorithm too: its parts follow the knobs.
    assert type(algorithm_for(compose("algo=qmix", "algo.name=my_label").algo)) is Algorithm


@pytest.mark.parametrize(
    ("algo", "incentive", "callbacks"),
    [
        ("qmix", Incentive, []),
        ("emc", Incentive, ["curiosity", "memory"]),
        ("emu", FixedThreshold, ["memory"]),
        ("emu_change", EvaluationThreshold, ["memory"]),
    ],
)
def test_the_parts_are_chosen_once_and_shared(algo: str, incentive: type, callbacks: list[str]) -> None:
    config = compose(f"algo={algo}", *TINY, *TINY_MEMORY)
    env_config = validate(config)
    algorithm = algorithm_for(config.algo)
    torch.manual_seed(0)
    learner = algorithm.learner(config.model, config.train, env_config, CPU)
    built = algorithm.callbacks(config, env_config, learner, CPU)
    assert type(algorithm.incentive) is incentive and [cb.name for cb in built] == callbacks
    assert learner.loss.incentive is algorithm.incentive  # one object for the loss and the memory
    memory = [cb for cb in built if cb.name == "memory"]
    assert all(cb.incentive is algorithm.incentive for cb in memory)
    # The learner is the one a plain Learner(config.algo, ...) builds: same mixer, same initial weights.
    torch.manual_seed(0)
    plain = type(learner)(config.algo, config.model, config.train, env_config, CPU)
    for a, b in zip(learner.loss.state_dict().values(), plain.loss.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    assert type(plain.loss.incentive) is incentive


def test_incentive_strategies() -> None:
    returns = torch.tensor([10.0, 365.0, 400.0])
    assert Incentive().desirable(returns, 5.0) is None
    assert FixedThreshold(365).desirable(returns, None).tolist() == [False, True, True]
    change = EvaluationThreshold()
    assert change.desirable(returns, None).tolist() == [False, False, False]  # before the first evaluation
    assert change.desirable(returns, 380.0).tolist() == [False, False, True]
    memory_return = torch.tensor([[[4.0], [-3.0], [8.0]]])
    hit = torch.tensor([[[1.0], [1.0], [0.0]]])
    next_value = torch.zeros(1, 3, 1)
    ratio = {"memory_ratio": torch.tensor([[[0.5], [1.0], [1.0]]])}
    assert Incentive().reward(None, None, next_value, 0.5, ratio.__getitem__) is None
    fixed = FixedThreshold(0).reward(memory_return, hit, next_value, 0.5, ratio.__getitem__)
    assert fixed[0, :, 0].tolist() == [1.0, 0.0, 0.0]  # 0.5 * 0.5 * max(4 - 0, 0); H below Q; a miss
    assert change.reward(memory_return, hit, next_value, 0.5, ratio.__getitem__)[0, :, 0].tolist() == [
        2,
        0,
        0,
    ]
    assert make_incentive("fixed", 370.0).threshold == 370.0 and make_incentive(change) is change
    with pytest.raises(ValueError, match="incentive must be one of none, fixed, change, got 'always'"):
        make_incentive("always")


def test_register_refuses_a_taken_name_and_a_non_algorithm() -> None:
    with pytest.raises(ValueError, match="'qmix' is already registered"):
        register_algorithm("qmix", type("Other", (Algorithm,), {}))
    register_algorithm("qmix", Algorithm)  # the class it has: nothing changes
    assert ALGORITHMS["qmix"] is Algorithm
    with pytest.raises(TypeError, match="expected an Algorithm subclass"):
        register_algorithm("not_one", object)  # type: ignore[arg-type]
    assert "not_one" not in ALGORITHMS
    with pytest.raises(
        TypeError, match=r'the first argument is the algo.name .* @register_algorithm\("my_algo"\)'
    ):
        register_algorithm(type("NoName", (Algorithm,), {}))  # type: ignore[arg-type]  # @register_algorithm


def test_a_class_defined_again_replaces_its_registration() -> None:
    """A notebook cell run twice defines a new class of the same module and name: it replaces the old one."""
    try:
        first = register_algorithm("cell_algo")(type("CellAlgo", (Algorithm,), {}))
        again = register_algorithm("cell_algo")(type("CellAlgo", (Algorithm,), {}))
        assert first is not again and ALGORITHMS["cell_algo"] is again
    finally:
        ALGORITHMS.pop("cell_algo", None)


class HalfBonus(Callback):
    """Writes a constant intrinsic reward, the key the loss reads, as EMC's curiosity does."""

    name = "half_bonus"

    def on_train_batch(self, batch, env_steps: int) -> dict[str, float]:
        batch.set("intrinsic_reward", torch.full_like(batch.get("reward"), 0.5))
        return {}


class BonusVDN(Algorithm):
    """An algorithm of one's own: VDN's mixer whatever algo.mixer says, plus a constant bonus."""

    def mixer(self, task):
        return make_mixer("vdn", task.n_agents, task.state_shape, task.n_actions)

    def callbacks(self, config, env_config, learner, device):
        return [*super().callbacks(config, env_config, learner, device), HalfBonus()]


@pytest.mark.slow
def test_a_registered_algorithm_trains(tmp_path: Path) -> None:
    register_algorithm("bonus_vdn", BonusVDN)
    try:
        config = compose("algo=qmix", *TINY, "algo.name=bonus_vdn", "train.total_env_steps=80")
        experiment = Experiment(config, tmp_path)
        assert isinstance(experiment.algorithm, BonusVDN) and isinstance(experiment.learner.mixer, VDNMixer)
        assert [cb.name for cb in experiment.callbacks] == ["half_bonus"]
        experiment.run()
    finally:
        ALGORITHMS.pop("bonus_vdn")
    with open(tmp_path / "logs" / "scalars" / "train" / "intrinsic_mean.csv") as f:
        rows = [float(value) for _, value in csv.reader(f)]
    assert rows and all(v == pytest.approx(0.5) for v in rows)


@pytest.mark.slow
def test_a_registered_algorithm_resumes_only_where_it_is_registered(tmp_path: Path, capsys) -> None:
    config = compose("algo=qmix", *TINY, "algo.name=bonus_vdn", "train.total_env_steps=80")
    longer = compose("algo=qmix", *TINY, "algo.name=bonus_vdn", "train.total_env_steps=120")
    register_algorithm("bonus_vdn", BonusVDN)
    try:
        Experiment(config, tmp_path).run()
    finally:
        ALGORITHMS.pop("bonus_vdn")
    # Without its registration the run would resume as the built-in algorithm, its bonus silently gone.
    with pytest.raises(CheckpointError) as refused:
        Experiment(longer, tmp_path, resume=True)
    assert (
        f"algorithm.class: '{BonusVDN.__module__}.BonusVDN' in the checkpoint, "
        "'mcrs.experiment.algorithms.Algorithm' in this run: "
        in str(refused.value)  # the flat name (history.py)
    )
    assert "register_algorithm" in str(refused.value)
    register_algorithm("bonus_vdn", BonusVDN)
    try:
        Experiment(longer, tmp_path, resume=True).run()
    finally:
        ALGORITHMS.pop("bonus_vdn")
    with open(tmp_path / "logs" / "scalars" / "train" / "intrinsic_mean.csv") as f:
        steps = [int(float(step)) for step, _ in csv.reader(f)]
    assert steps[-1] > 80  # the bonus went on after the resume


def test_an_unregistered_name_is_said_to_be_the_built_in_algorithm(tmp_path: Path, caplog) -> None:
    """In the run's log, and to a Python user as a warning (mcrs-train says it as a note: line)."""
    said = "algo.name=qmxi is not a registered algorithm: trained as the built-in Algorithm(qmxi"
    with (
        caplog.at_level("INFO", logger="mcrs.run"),
        pytest.warns(UnregisteredAlgorithm, match=re.escape(said)),
    ):
        Experiment(compose("algo=qmix", *TINY, "algo.name=qmxi"), tmp_path).close()
    assert said in caplog.text


@pytest.mark.slow
def test_the_memory_writes_its_keys_in_on_train_batch(tmp_path: Path) -> None:
    """No replay transform: a sampled batch has no memory keys until the memory's on_train_batch."""
    config = compose("algo=emu", *TINY, *TINY_MEMORY, "train.total_env_steps=40")
    experiment = Experiment(config, tmp_path)
    experiment.run()
    batch = experiment.replay.sample()
    keys = ("memory_return", "memory_hit", "memory_ratio")
    assert all(batch.get(key, None) is None for key in keys)
    assert experiment.callback("memory").on_train_batch(batch, 40) == {}
    assert all(batch.get(key, None) is not None for key in keys)
    assert set(experiment.learner.loss.in_keys) >= set(keys)


PLUGIN = """
from dataclasses import dataclass
from typing import Literal

from omegaconf import MISSING

from mcrs.experiment.training.algorithms import Algorithm
from mcrs.models.mixers import make_mixer


class PluginVDN(Algorithm):
    def mixer(self, task):
        return make_mixer("vdn", task.n_agents, task.state_shape, task.n_actions)


class PluginNeeds(Algorithm):
    @dataclass
    class Options:
        clip: float = MISSING  # no default: every run must set it


class PluginLiteral(Algorithm):
    @dataclass
    class Options:
        mode: Literal["a", "b"] = "a"  # a type OmegaConf cannot check


NOT_AN_ALGORITHM = 3
"""


def _install_plugin(root: Path, entries: str) -> None:
    """A package installed as pip would leave it: its module and its dist-info with entry points."""
    (root / "mcrs_test_plugin.py").write_text(PLUGIN)
    info = root / "mcrs_test_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: mcrs-test-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[mcrs.algorithms]\n{entries}")


DECORATED_PLUGIN = """
from mcrs.experiment.training.algorithms import Algorithm, register_algorithm


@register_algorithm("plugin_decorated")  # registered on import too, as docs/API.md's example is
class PluginDecorated(Algorithm):
    pass
"""


def test_an_installed_algorithm_that_registers_itself_is_found(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Loading the entry point imports the module, whose decorator registers the class; the registry then
    gets the same class again, which is not a clash."""
    (tmp_path / "mcrs_test_decorated.py").write_text(DECORATED_PLUGIN)
    info = tmp_path / "mcrs_test_decorated-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: mcrs-test-decorated\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[mcrs.algorithms]\nplugin_decorated = mcrs_test_decorated:PluginDecorated\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        algorithm = algorithm_for(compose("algo=qmix", "algo.name=plugin_decorated").algo)
        assert type(algorithm).__name__ == "PluginDecorated"
    finally:
        ALGORITHMS.pop("plugin_decorated", None)


def test_an_installed_algorithm_is_found_by_its_name_in_any_process(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _install_plugin(
        tmp_path,
        "plugin_vdn = mcrs_test_plugin:PluginVDN\nplugin_int = mcrs_test_plugin:NOT_AN_ALGORITHM\n"
        "plugin_gone = mcrs_test_plugin_gone:Algo\nplugin_needs = mcrs_test_plugin:PluginNeeds\n"
        "plugin_literal = mcrs_test_plugin:PluginLiteral\n",
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    run = tmp_path / "run"
    try:
        config = compose("algo=qmix", *TINY, "algo.name=plugin_vdn", "train.total_env_steps=40")
        experiment = Experiment(config, run)
        assert type(experiment.algorithm).__name__ == "PluginVDN"
        assert isinstance(experiment.learner.mixer, VDNMixer)
        experiment.run()
        ALGORITHMS.pop("plugin_vdn")  # a new process: the resume finds it again by its name
        longer = compose("algo=qmix", *TINY, "algo.name=plugin_vdn", "train.total_env_steps=80")
        Experiment(longer, run, resume=True).run()
    finally:
        ALGORITHMS.pop("plugin_vdn", None)
    with pytest.raises(ConfigError, match=r"algo.name=plugin_int: the entry point .* is 3, not an Algorithm"):
        algorithm_for(compose("algo=qmix", "algo.name=plugin_int").algo)
    with pytest.raises(
        ConfigError, match=r"algo.name=plugin_gone: .* cannot be loaded: ModuleNotFoundError: No module"
    ):
        algorithm_for(compose("algo=qmix", "algo.name=plugin_gone").algo)
    assert "plugin_int" not in ALGORITHMS and "plugin_gone" not in ALGORITHMS
    # An installed algorithm's settings are checked up front even when the command sets none (a sweep's
    # jobs would each fail on a setting without a default), and an Options class OmegaConf cannot check
    # is the plugin's problem, named once.
    try:
        needs = OmegaConf.structured(compose("algo=qmix", "algo.name=plugin_needs"))
        assert option_errors(needs) == [
            "algo.options.clip: Structured config of type `Options` has missing mandatory value: clip"
        ]
        literal = OmegaConf.structured(compose("algo=qmix", "algo.name=plugin_literal"))
        (problem,) = option_errors(literal)
        assert problem.startswith(
            "algo.name=plugin_literal: the entry point 'mcrs_test_plugin:PluginLiteral'"
        )
        assert "PluginLiteral.Options: Unexpected type annotation: Literal" in problem
    finally:
        ALGORITHMS.pop("plugin_needs", None)


class ClippedTargets(ValueFactorisationLoss):
    """Another TD target (clipped), as a loss subclass: what Algorithm.loss exists for."""

    calls = 0

    def __init__(self, *args, clip: float, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.clip = clip

    def targets(self, reward, next_value, done, terminated):
        ClippedTargets.calls += 1
        return super().targets(reward, next_value, done, terminated).clamp(-self.clip, self.clip)


class ClippedQMIX(Algorithm):
    @dataclass
    class Options:  # its own settings: algo.options.clip
        clip: float = 1.0
        note: str = "clipped"

    def loss(self, agent, mixer):
        base = super().loss(agent, mixer)
        return ClippedTargets(
            agent, mixer, gamma=base.gamma, incentive=self.incentive, clip=self.options.clip
        )


def test_an_algorithms_loss_is_its_own_and_the_learner_is_built_around_it(tmp_path: Path) -> None:
    register_algorithm("clipped_qmix", ClippedQMIX)
    try:
        config = compose("algo=qmix", *TINY, "algo.name=clipped_qmix", "train.total_env_steps=40")
        experiment = Experiment(config, tmp_path)
        learner = experiment.learner
        assert type(learner.loss) is ClippedTargets and learner.target_updater.loss_module is learner.loss
        assert learner.loss.tensor_keys.state == "state"  # the task's keys are set on it
        assert learner.loss.clip == 1.0  # its Options' default
        experiment.run()
    finally:
        ALGORITHMS.pop("clipped_qmix")
    assert ClippedTargets.calls > 0
    with pytest.raises(TypeError, match="the learner's loss must be a ValueFactorisationLoss"):
        Learner(
            compose("algo=qmix").algo,
            config.model,
            config.train,
            scenario("map10"),
            CPU,
            loss=lambda a, m: nn.MSELoss(),
        )


def test_an_algorithms_own_settings_are_checked_recorded_and_fingerprinted(tmp_path: Path) -> None:
    register_algorithm("clipped_qmix", ClippedQMIX)
    base = ("algo=qmix", *TINY, "algo.name=clipped_qmix", "train.total_env_steps=40")
    try:
        config = compose(*base, "+algo.options.clip=0.5")
        experiment = Experiment(config, tmp_path)
        assert experiment.algorithm.options == ClippedQMIX.Options(clip=0.5)
        assert experiment.learner.loss.clip == 0.5
        assert config.algo.options == {"clip": 0.5}  # the caller's config is not changed
        experiment.run()
        # The run's config holds every setting, the defaults filled in.
        saved = OmegaConf.load(tmp_path / "config.yaml").algo.options
        assert OmegaConf.to_container(saved) == {"clip": 0.5, "note": "clipped"}
        longer = ("train.total_env_steps=80", "+algo.options.clip=0.25")
        with pytest.raises(
            CheckpointError, match=r"algo.options.clip: 0.5 in the checkpoint, 0.25 in this run"
        ):
            Experiment(compose(*base, *longer), tmp_path, resume=True)
        problems = [
            ("+algo.options.clp=2", "algo.options.clp: not a setting of ClippedQMIX (algo.name=clipped_qmix); "
             "its settings (closest first): clip, note"),
            ("+algo.options.clip=wide", "algo.options.clip='wide': Value 'wide' of type 'str' could not be "
             "converted to Float"),
        ]  # fmt: skip
        for override, message in problems:
            with pytest.raises(ConfigError) as refused:
                Experiment(compose(*base, override), tmp_path / "refused")
            assert str(refused.value) == message
            # mcrs-train and a sweep's up-front check say the same before a job starts
            assert option_errors(OmegaConf.structured(compose(*base, override))) == [message]
        assert not (tmp_path / "refused").exists()  # refused before anything is written
    finally:
        ALGORITHMS.pop("clipped_qmix")
    with pytest.raises(
        ConfigError, match=r"^algo.options.clip: Algorithm \(algo.name=qmix\) takes no options$"
    ):
        algorithm_for(compose("algo=qmix", "+algo.options.clip=2").algo)
    with pytest.raises(ConfigError, match=r"takes no options \(algo.name=qmxi is not a registered algorithm"):
        algorithm_for(compose("algo=qmix", "algo.name=qmxi", "+algo.options.clip=2").algo)
    # Without the '+', Hydra's own refusal says how to add one.
    with pytest.raises(ConfigError, match=r"with a '\+': \+algo.options.clip=<value>"):
        compose("algo=qmix", "algo.options.clip=2")
    with pytest.raises(TypeError, match=r"Options must be a dataclass class"):
        register_algorithm("bad_options", type("BadOptions", (Algorithm,), {"Options": dict}))
    with_path = type(
        "WithPath",
        (Algorithm,),
        {"Options": dataclass(type("Options", (), {"__annotations__": {"out": Path}, "out": Path("x")}))},
    )
    with pytest.raises(TypeError, match=r"WithPath.Options.out: a PosixPath is not a plain config value"):
        register_algorithm("with_path", with_path)
    assert "bad_options" not in ALGORITHMS and "with_path" not in ALGORITHMS


def test_a_resume_that_sets_a_setting_the_runs_config_predates_is_refused(tmp_path: Path) -> None:
    """A run saved before ``algo.options`` existed: the command's ``+algo.options.<key>`` is a contradiction
    of the run's config, not an override silently dropped."""
    from mcrs.train import resume_config

    Experiment(compose("algo=qmix", *TINY, "train.total_env_steps=40"), tmp_path).run()
    saved = OmegaConf.load(tmp_path / "config.yaml")
    del saved.algo["options"]  # as runs before this field wrote it
    OmegaConf.save(saved, tmp_path / "config.yaml")
    overrides = [f"resume={tmp_path}", "+algo.options.bonus=0.9"]
    with pytest.raises(
        ConfigError, match=r"contradicts the run's config:\n  - algo.options: the run has '<missing>'"
    ):
        resume_config(OmegaConf.structured(compose(*overrides)), overrides)


def test_a_setting_added_to_an_algorithm_after_its_checkpoint_is_said_on_resume(
    tmp_path: Path, caplog
) -> None:
    register_algorithm("clipped_qmix", ClippedQMIX)
    try:
        config = compose("algo=qmix", *TINY, "algo.name=clipped_qmix", "train.total_env_steps=40")
        Experiment(config, tmp_path).run()
        path = tmp_path / "checkpoints" / "last.pt"
        state = torch.load(path, weights_only=False)
        del state["fingerprint"]["algo.options.note"]  # as the class was when the checkpoint was written
        whole = {k: v for k, v in state.items() if k not in ("format", "version", "checksum")}
        save_atomic(whole, path)  # a whole file, its checksum its own
        longer = compose("algo=qmix", *TINY, "algo.name=clipped_qmix", "train.total_env_steps=80")
        with caplog.at_level("INFO", logger="mcrs.run"):
            Experiment(longer, tmp_path, resume=True).close()
        assert (
            "the checkpoint predates these settings of its algorithm: resumed with algo.options.note='clipped'"
            in caplog.text
        )
    finally:
        ALGORITHMS.pop("clipped_qmix")


def test_a_package_ships_its_algorithms_preset_with_its_settings(tmp_path: Path) -> None:
    """Hydra's search path finds a package's ``algo/`` preset (``hydra.searchpath=[pkg://...]`` or a
    SearchPathPlugin): the preset holds the settings' keys, so the command line sets them without '+'."""
    (tmp_path / "algo").mkdir()
    (tmp_path / "algo" / "clipped.yaml").write_text(
        "defaults:\n  - qmix\n  - _self_\nname: clipped_qmix\noptions:\n  clip: 0.5\n"
    )
    register_algorithm("clipped_qmix", ClippedQMIX)
    try:
        search = f"hydra.searchpath=[file://{tmp_path}]"
        config = compose(search, "algo=clipped", *TINY, "train.total_env_steps=40", "algo.options.clip=0.25")
        assert str(config.algo.mixer) == "qmix" and config.algo.options == {"clip": 0.25}
        experiment = Experiment(config, tmp_path / "run")
        assert experiment.learner.loss.clip == 0.25 and experiment.algorithm.options.note == "clipped"
        experiment.close()
        with pytest.raises(ConfigError, match=r"algo.options.clp: not a setting of ClippedQMIX"):
            Experiment(compose(search, "algo=clipped", *TINY, "+algo.options.clp=1"), tmp_path / "bad")
    finally:
        ALGORITHMS.pop("clipped_qmix")
