"""The scenario configuration: one validated dataclass, loaded from the packaged Hydra presets.

The YAML files under ``conf/env/`` (paper tables 2 and 3) are the only source of the preset values, so
Python users, tests and benchmarks see what the ``mcrs-*`` commands see."""

from __future__ import annotations

import difflib
import math
from dataclasses import asdict, dataclass, field, fields, is_dataclass, make_dataclass, replace
from importlib import resources
from typing import Any, Optional, get_type_hints

from omegaconf import DictConfig, OmegaConf

SCENARIOS = ("map10", "map15", "map20")
#: Variants beyond the paper (its section 7's future work): map20 with a communication delay, with a
#: bandwidth limit, and with moving targets and fading evidence.
VARIANT_PRESETS = ("map20_delay", "map20_bandwidth", "map20_dynamic")
PRESETS = SCENARIOS + VARIANT_PRESETS
#: Fields of how the env runs, set by the command that runs it and never by the scenario presets.
RUNTIME_FIELDS = ("num_envs", "device")
INVALID_ACTION_MODES = ("raise", "clip")
TARGET_MOTIONS = ("static", "random_walk")
#: How r3 and r4 read the safe distances d1 and d2 (docs/ENVIRONMENT.md, "Reward"). ``enter``, the
#: paper's reward text (section 4.3), charges distances < d. ``near``, a reading of constraints (16)-(17),
#: charges distances <= d, so a zone's four neighbours and side-by-side UAVs too.
SAFETY_RULES = ("enter", "near")
#: What a UAV's surround shows in a direction it cannot move to (docs/ENVIRONMENT.md, "Observation").
#: ``blocked``, the paper (section 4.2), zeroes m(U) and m(F) off the grid and on no-fly cells. ``belief``
#: zeroes them off the grid only and shows a no-fly cell's belief.
NO_FLY_VIEWS = ("blocked", "belief")
#: What every belief map holds for a no-fly cell. ``known``, the paper (section 3.1, figure 4), holds it
#: as known and empty from reset, m(U) = m(F) = 0. ``unknown`` starts it at m(U) = 1 like any cell, so that
#: entering it pays r1.
NO_FLY_PRIORS = ("known", "unknown")
#: Which cells r2 pays (docs/ENVIRONMENT.md, "Discoveries"). ``belief`` (eq. 24) pays every cell whose
#: global m(F) first reaches tau, target or not. ``target`` pays only cells that hold a target.
DISCOVERY_RULES = ("belief", "target")
#: The order of the relative-position slots, on which the paper is silent. ``index`` keeps index order.
#: ``nearest`` sorts the UAVs and the zones each by distance, entities beyond sight last, ties by index.
RELATIVE_ORDERS = ("index", "nearest")
#: Values the observation gains with ``far_view`` > 0: one window mean of own m(U) per move.
N_FAR_VIEW = 8
#: The value a saved scenario that predates each field was run with (applied by mcrs/experiment/run/history.py).
LEGACY_SCENARIO_VALUES = {
    "safety_rule": "near",
    "no_fly_view": "belief",
    "no_fly_prior": "unknown",
    "discovery_rule": "target",
}
#: evidence_decay's bound on max_steps * -ln(1 - decay): (1 - decay)^max_steps stays a normal float32.
MAX_DECAY_EXPONENT = 80.0


class FieldsOnly:
    """A mutable config dataclass that refuses attributes that are not its fields. A misspelt field such as
    ``config.train.total_env_step = 3200`` raises an error naming the closest fields instead of setting an
    attribute the run never reads."""

    __slots__ = ()

    def __setattr__(self, name: str, value: Any) -> None:
        known = getattr(self, "__dataclass_fields__", None)
        if known is not None and name not in known and not name.startswith("_"):
            close = difflib.get_close_matches(name, list(known), n=3, cutoff=0.6)
            hint = f"closest: {', '.join(close)}" if close else f"its fields: {', '.join(known)}"
            raise AttributeError(f"{type(self).__name__} has no field {name!r} ({hint})")
        super().__setattr__(name, value)


@dataclass(frozen=True)
class EnvConfig:
    """Every parameter of the MCRS-LCR environment (see docs/ENVIRONMENT.md)."""

    name: str = "map10"
    width: int = 10
    height: int = 10
    n_uavs: int = 4
    n_targets: int = 6
    n_no_fly: int = 3
    max_steps: int = 50
    comm_range: float = 5.0
    comm_rounds: Any = 1  # int >= 1 or "flood"; Any because OmegaConf has no Union of int and str
    sight_range: float = 4.0
    no_fly_safety: float = 1.0
    uav_safety: float = 1.0
    safety_rule: str = "enter"  # enter (< d, the paper's reward text) | near (<= d)
    no_fly_view: str = "blocked"  # blocked (the paper: zero in no-fly directions) | belief
    no_fly_prior: str = "known"  # known (the paper: zones known empty from reset) | unknown
    discovery_rule: str = "belief"  # belief (eq. 24: any cell reaching tau) | target (real targets only)
    relative_order: str = "index"  # index | nearest: the order of the relative-position slots
    m_f: float = 0.8
    m_e: float = 0.8
    p_detect: float = 0.8
    p_false_alarm: float = 0.2
    w_uncertainty: float = 1.0
    w_discovery: float = 1.0
    w_no_fly: float = 1.0
    w_collision: float = 1.0
    target_threshold: float = 0.95
    invalid_action: str = "raise"
    expose_beliefs: bool = False
    no_fly_shield: bool = False  # mask moves ending within d1 of a no-fly zone (mcrs/env/shield.py)
    uav_shield: bool = False  # mask moves that could meet a lower-indexed UAV in sight within d2 (shield.py)
    far_view: int = 0  # k > 0 adds 8 window means of own m(U) to the observation (outputs.py)
    # Variants beyond the paper (docs/ENVIRONMENT.md, "Delay, bandwidth and moving targets").
    comm_delay: int = 0  # steps between sending and receiving a message
    comm_budget: Optional[int] = None  # noqa: UP045 (OmegaConf needs Optional) detections per link and step; None: unlimited
    target_motion: str = "static"  # static | random_walk
    target_move_prob: float = 0.0  # random_walk: probability that a target tries a move in a step
    evidence_decay: float = 0.0  # every count is multiplied by (1 - evidence_decay) per step
    num_envs: int = 1
    device: str = "cpu"

    def __post_init__(self) -> None:
        problems = validation_errors(self)
        if problems:
            raise ValueError("invalid environment config:\n  - " + "\n  - ".join(problems))

    # Derived sizes (paper table 2): the layouts of observation and state follow from these.
    @property
    def n_cells(self) -> int:
        return self.width * self.height

    @property
    def obs_dim(self) -> int:
        far = N_FAR_VIEW if self.far_view > 0 else 0
        return 18 + 3 * (self.n_uavs - 1) + 3 * self.n_no_fly + far

    @property
    def state_dim(self) -> int:
        return 2 * self.n_cells + 2 * self.n_uavs + 2 * self.n_no_fly + 2 * self.n_targets

    def violates(self, squared: Any, distance: float) -> Any:
        """Return which squared distances break the safe ``distance`` under :attr:`safety_rule`; exact for
        integer cells."""
        limit = distance**2
        return squared < limit if self.safety_rule == "enter" else squared <= limit

    @property
    def rounds_per_step(self) -> int:
        """Exchange rounds per step; ``flood`` needs at most N - 1 rounds to cross any component."""
        if self.comm_rounds == "flood":
            return max(self.n_uavs - 1, 1)
        return int(self.comm_rounds)

    @property
    def dynamic(self) -> bool:
        """Whether targets move or evidence fades; discoveries are then judged at the targets' current cells."""
        return self.target_motion != "static" or self.evidence_decay > 0

    @classmethod
    def from_scenario(cls, scenario: Any, *, num_envs: int = 1, device: str = "cpu") -> EnvConfig:
        """Return the env config of a scenario (dataclass, mapping or OmegaConf node) run as ``num_envs``
        environments on ``device``."""
        values = asdict(scenario) if is_dataclass(scenario) else _plain(scenario)
        return from_mapping({**values, "num_envs": num_envs, "device": device})

    def scenario(self) -> dict[str, Any]:
        """Return the scenario fields, everything but :data:`RUNTIME_FIELDS`."""
        return {k: v for k, v in asdict(self).items() if k not in RUNTIME_FIELDS}

    def replace(self, **overrides: Any) -> EnvConfig:
        _check_known_fields(overrides)
        return replace(self, **overrides)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def with_legacy_values(env: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """Fill the fields a saved scenario predates with what they meant (:data:`LEGACY_SCENARIO_VALUES`).

    Returns the completed scenario and one ``"field=value"`` line per field set, so that the caller can report
    them. Fields already saved are kept."""
    missing = {k: v for k, v in LEGACY_SCENARIO_VALUES.items() if k not in env}
    return {**env, **missing}, [f"{k}={v}" for k, v in missing.items()]


def _plain(values: Any) -> dict[str, Any]:
    if isinstance(values, DictConfig):
        return OmegaConf.to_container(values, resolve=True, enum_to_str=True)
    return dict(values)


def _scenario_schema() -> type:
    """Return the scenario's fields as a mutable dataclass, the schema Hydra checks the ``env`` node with. It
    is generated from :class:`EnvConfig` so that the fields are written once."""
    hints = get_type_hints(EnvConfig)
    return make_dataclass(
        "ScenarioConfig",
        [
            (f.name, hints[f.name], field(default=f.default))
            for f in fields(EnvConfig)
            if f.name not in RUNTIME_FIELDS
        ],
        bases=(FieldsOnly,),
        namespace={
            "__doc__": "The scenario part of :class:`EnvConfig` (the ``env`` node of the configs).",
            "__module__": __name__,
        },
    )


#: The ``env`` node's schema: :class:`EnvConfig` without its runtime fields.
ScenarioConfig = _scenario_schema()


def field_names() -> list[str]:
    return [f.name for f in fields(EnvConfig)]


def _check_known_fields(names: Any) -> None:
    unknown = set(names) - set(field_names())
    if unknown:
        raise ValueError(f"unknown environment field(s) {sorted(unknown)}; allowed: {field_names()}")


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


#: A finite range or safety distance beyond this many cells is refused (inf means unlimited): any map is
#: smaller, and the squares the fusion takes stay finite.
MAX_DISTANCE = 1e9


def validation_errors(cfg: EnvConfig) -> list[str]:
    """Return every problem of a config, one message each naming the field, the value and what is allowed."""
    errors = _number_errors(cfg) + _choice_errors(cfg)
    errors += _variant_errors(cfg)
    problem = device_problem(cfg.device)
    if problem:
        errors.append(f"device={cfg.device!r}: {problem}")
    if not errors:  # the sizes are sane: do the map's cells hold the team, the targets and the zones?
        errors += _layout_errors(cfg)
    return errors


def _number_errors(cfg: EnvConfig) -> list[str]:
    """Sizes, probabilities, distances and reward weights."""
    errors: list[str] = []
    for name in ("width", "height", "n_uavs", "max_steps", "num_envs"):
        value = getattr(cfg, name)
        if not _is_int(value) or value < 1:
            errors.append(f"{name}={value!r}: must be an integer >= 1")
    for name in ("n_targets", "n_no_fly"):
        value = getattr(cfg, name)
        if not _is_int(value) or value < 0:
            errors.append(f"{name}={value!r}: must be an integer >= 0")
    for name in ("m_f", "m_e"):
        value = getattr(cfg, name)
        # m = 1 would make one reading certain and two conflicting readings undefined (D = 0).
        if not _is_number(value) or not 0.0 <= value < 1.0:
            errors.append(f"{name}={value!r}: must be a probability in [0, 1)")
    for name in ("p_detect", "p_false_alarm", "target_threshold"):
        value = getattr(cfg, name)
        if not _is_number(value) or not 0.0 <= value <= 1.0:
            errors.append(f"{name}={value!r}: must be a probability in [0, 1]")
    for name in ("comm_range", "sight_range", "no_fly_safety", "uav_safety"):
        value = getattr(cfg, name)
        if not _is_number(value) or math.isnan(value) or value < 0:
            errors.append(f"{name}={value!r}: must be a distance >= 0 (inf allowed)")
        elif MAX_DISTANCE < value < math.inf:  # squared distances of 1e308 overflow in the fusion
            errors.append(f"{name}={value!r}: must be <= {MAX_DISTANCE:g} cells or inf (unlimited)")
    if _is_number(cfg.p_detect) and _is_number(cfg.p_false_alarm) and cfg.p_detect < cfg.p_false_alarm:
        errors.append(
            f"p_detect={cfg.p_detect!r} < p_false_alarm={cfg.p_false_alarm!r}: the sensor would read "
            "backwards (a target reported less often than an empty cell)"
        )
    sight_ok = _is_number(cfg.sight_range) and 0 < cfg.sight_range < math.inf
    if not sight_ok and not any(e.startswith("sight_range") for e in errors):
        errors.append(f"sight_range={cfg.sight_range!r}: must be finite and > 0 (it normalises positions)")
    for name in ("w_uncertainty", "w_discovery", "w_no_fly", "w_collision"):
        value = getattr(cfg, name)
        if not _is_number(value) or not math.isfinite(value):
            errors.append(f"{name}={value!r}: must be a finite number")
    return errors


def _choice_errors(cfg: EnvConfig) -> list[str]:
    """The choices among named rules, the flags and the far view."""
    errors: list[str] = []
    rounds = cfg.comm_rounds
    if not (rounds == "flood" or (_is_int(rounds) and rounds >= 1)):
        errors.append(f"comm_rounds={rounds!r}: must be an integer >= 1 or 'flood'")
    if cfg.safety_rule not in SAFETY_RULES:
        errors.append(
            f"safety_rule={cfg.safety_rule!r}: must be one of {list(SAFETY_RULES)} (enter: distances < d are "
            "penalised, the paper's reward; near: distances <= d, the stricter old reading)"
        )
    choices = (
        (
            "no_fly_view",
            NO_FLY_VIEWS,
            "blocked: zero in no-fly directions, the paper; belief: the zone's belief",
        ),
        (
            "no_fly_prior",
            NO_FLY_PRIORS,
            "known: zones known and empty from reset, the paper; unknown: unread",
        ),
        (
            "discovery_rule",
            DISCOVERY_RULES,
            "belief: r2 for any cell reaching tau, eq. 24; target: real targets",
        ),
        (
            "relative_order",
            RELATIVE_ORDERS,
            "index: other UAVs and zones in index order; nearest: by distance",
        ),
    )
    for name, allowed, meaning in choices:
        if getattr(cfg, name) not in allowed:
            errors.append(f"{name}={getattr(cfg, name)!r}: must be one of {list(allowed)} ({meaning})")
    if cfg.invalid_action not in INVALID_ACTION_MODES:
        errors.append(f"invalid_action={cfg.invalid_action!r}: must be one of {list(INVALID_ACTION_MODES)}")
    for name in ("expose_beliefs", "no_fly_shield", "uav_shield"):
        if not isinstance(getattr(cfg, name), bool):
            errors.append(f"{name}={getattr(cfg, name)!r}: must be true or false")
    far = cfg.far_view
    if not _is_int(far) or far < 0:
        errors.append(f"far_view={far!r}: must be an integer >= 0 (0: the paper's 8-cell view)")
    elif _is_int(cfg.width) and _is_int(cfg.height) and far > max(cfg.width, cfg.height):
        errors.append(
            f"far_view={far}: must be <= max(width, height) = {max(cfg.width, cfg.height)} "
            "(a larger window holds no more of the map)"
        )
    return errors


def _layout_errors(cfg: EnvConfig) -> list[str]:
    """Return whether the map's cells can hold the UAVs, targets and no-fly zones."""
    errors: list[str] = []
    cells = cfg.width * cfg.height
    if cells < 2:  # every one of the 8 moves leaves the grid: no action is allowed
        errors.append(
            f"width={cfg.width}, height={cfg.height}: a 1x1 map leaves a UAV no move: at least 2 cells"
        )
    if cfg.n_targets + cfg.n_no_fly > cells:
        errors.append(
            f"n_targets + n_no_fly = {cfg.n_targets} + {cfg.n_no_fly} > {cells} cells: "
            "targets and no-fly zones need distinct cells"
        )
    if cfg.n_uavs > cells - cfg.n_no_fly:
        errors.append(
            f"n_uavs={cfg.n_uavs} > {cells - cfg.n_no_fly} free cells (cells - n_no_fly): "
            "UAVs start on distinct cells outside no-fly zones"
        )
    return errors


def _variant_errors(cfg: EnvConfig) -> list[str]:
    """Check the fields beyond the paper: delay, bandwidth, moving targets and evidence decay."""
    errors: list[str] = []
    delay = cfg.comm_delay
    if not _is_int(delay) or delay < 0:
        errors.append(f"comm_delay={delay!r}: must be an integer >= 0 (steps; 0: instantaneous, the paper)")
    elif _is_int(cfg.max_steps) and delay > cfg.max_steps:
        errors.append(
            f"comm_delay={delay}: must be <= max_steps={cfg.max_steps} (no message would ever arrive)"
        )
    budget = cfg.comm_budget
    if budget is not None and (not _is_int(budget) or budget < 1):
        errors.append(
            f"comm_budget={budget!r}: must be an integer >= 1 (detections per link and step) or null for "
            "unlimited (the paper); use comm_range=0 for no communication"
        )
    if cfg.target_motion not in TARGET_MOTIONS:
        errors.append(f"target_motion={cfg.target_motion!r}: must be one of {list(TARGET_MOTIONS)}")
    prob = cfg.target_move_prob
    if not _is_number(prob) or not 0.0 <= prob <= 1.0:
        errors.append(f"target_move_prob={prob!r}: must be a probability in [0, 1]")
    elif prob > 0 and cfg.target_motion == "static":
        errors.append(
            f"target_move_prob={prob!r}: has no effect with target_motion='static': set "
            "target_motion=random_walk, or target_move_prob=0"
        )
    decay = cfg.evidence_decay
    if not _is_number(decay) or not 0.0 <= decay < 1.0:
        errors.append(f"evidence_decay={decay!r}: must be in [0, 1) (0: counts never fade, the paper)")
    elif decay > 0 and _is_int(cfg.max_steps) and -math.log1p(-decay) * cfg.max_steps > MAX_DECAY_EXPONENT:
        largest = -math.expm1(-MAX_DECAY_EXPONENT / cfg.max_steps)
        errors.append(
            f"evidence_decay={decay!r}: with max_steps={cfg.max_steps} must be <= {largest:.6g} "
            f"(max_steps * -ln(1 - evidence_decay) <= {MAX_DECAY_EXPONENT:g}, so that counts stay finite)"
        )
    return errors


def device_problem(device: Any) -> str | None:
    """Why ``device`` cannot hold the environment here, or None when it can."""
    if device == "cpu":  # always there; a command line checks its config without loading torch
        return None
    import torch  # deferred: validating a config must not load torch

    allowed = "a torch device string such as 'cpu', 'cuda' or 'cuda:0'"
    if not isinstance(device, str):
        return f"must be {allowed}"
    try:
        parsed = torch.device(device)
    except RuntimeError:
        return f"is not a torch device: use {allowed}"
    if parsed.type == "cuda":
        if not torch.cuda.is_available():
            return "CUDA is not available on this machine: use 'cpu'"
        if parsed.index is not None and parsed.index >= torch.cuda.device_count():
            return f"there are {torch.cuda.device_count()} CUDA device(s): use cuda:0..cuda:{torch.cuda.device_count() - 1}"
    elif parsed.type == "mps" and not torch.backends.mps.is_available():
        return "MPS (Apple GPU) is not available on this machine: use 'cpu'"
    elif parsed.type not in ("cpu", "mps"):
        return f"device type {parsed.type!r} is not supported: use {allowed}"
    return None


def _preset_values(name: str) -> dict[str, Any]:
    if name not in PRESETS:
        raise ValueError(f"unknown scenario {name!r}; allowed: {list(PRESETS)}")
    text = resources.files("mcrs").joinpath(f"conf/env/{name}.yaml").read_text()
    return OmegaConf.to_container(OmegaConf.create(text))


def scenario(name: str = "map10", **overrides: Any) -> EnvConfig:
    """Return the validated config of a packaged preset (:data:`PRESETS`) with overrides."""
    return from_mapping({**_preset_values(name), **overrides})


def from_mapping(values: Any) -> EnvConfig:
    """Build a validated config from a Hydra/OmegaConf node, a :data:`ScenarioConfig` or a plain mapping."""
    values = asdict(values) if is_dataclass(values) else _plain(values)
    _check_known_fields(values)
    for name in (
        "comm_range",
        "sight_range",
        "no_fly_safety",
        "uav_safety",
        "target_move_prob",
        "evidence_decay",
    ):
        if _is_int(values.get(name)):
            values[name] = float(values[name])
    return EnvConfig(**values)
