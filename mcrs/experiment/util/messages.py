"""One-line messages: Hydra's composing errors as one line naming the key, group or override and what is
allowed, the closest names first::

    env.comm_rage: unknown key; the keys of env (closest first): comm_range, comm_budget, comm_delay, ...
    algo=qmx: no such option of algo; allowed (closest first): qmix, cnn_semu, emc, ...

Used by the config, the training loop and the command lines, so it imports none of them.
"""

from __future__ import annotations

import difflib
from collections.abc import Sequence

from hydra.errors import MissingConfigException, OverrideParseException
from omegaconf import DictConfig
from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException, ValidationError

#: OmegaConf's "Value 'abc' of type 'str' could not be converted to Float", said as what is wanted.
TYPE_NAMES = {
    "Float": "a number",
    "Integer": "an integer",
    "Boolean": "true or false",
    "Bool": "true or false",
    "String": "a string",
}
CLOSE = 0.6  # difflib ratio from which a key or option counts as a likely meant one
GRAMMAR = "https://hydra.cc/docs/advanced/override_grammar/basic/"


def ranked(name: str, allowed: Sequence[str]) -> list[str]:
    """``allowed`` with the close matches of ``name`` first, best first, ignoring case."""
    score = {a: _similarity(name, a) for a in allowed}
    close = sorted(
        (a for a in allowed if score[a] >= CLOSE), key=lambda a: -score[a]
    )  # stable: ties keep order
    return close + [a for a in allowed if a not in close]


def _similarity(name: str, other: str) -> float:
    return difflib.SequenceMatcher(None, name.lower(), other.lower()).ratio()


def listing(name: str, allowed: Sequence[str]) -> str:
    """``" (closest first): comm_range, comm_budget, ..."``, or ``": a, b"`` when no name is close."""
    order = ranked(name, allowed)
    close = _similarity(name, order[0]) >= CLOSE if order else False
    return f"{' (closest first)' if close else ''}: {', '.join(order)}"


def describe(error: BaseException) -> str:
    """One line for an error Hydra or OmegaConf raised while composing a config."""
    cause = error.__cause__
    if isinstance(error, OverrideParseException):
        reason = _lines(error.message)[0] if _lines(error.message) else "not an override"
        return f"cannot read the override {error.override!r}: {reason} (the syntax: {GRAMMAR})"
    if isinstance(error, MissingConfigException) and error.missing_cfg_file and error.options:
        group, _, option = str(error.missing_cfg_file).rpartition("/")
        return f"{group}={option}: no such option of {group}; allowed{listing(option, sorted(error.options))}"
    if isinstance(cause, (ConfigKeyError, ConfigAttributeError)) and getattr(cause, "full_key", None):
        return _unknown_key(str(cause.full_key), cause)
    if isinstance(cause, ValidationError) and getattr(cause, "full_key", None):
        return _bad_value(str(error), cause)
    if isinstance(error, (ConfigKeyError, ConfigAttributeError)) and getattr(error, "full_key", None):
        return _unknown_key(str(error.full_key), error)
    lines = _lines(str(error)) + (_lines(str(cause)) if cause is not None else [])
    return "; ".join(lines) or type(error).__name__


#: The env's runtime fields (``EnvConfig.num_envs``, ``device``): not scenario keys, set by each command.
RUNTIME_KEYS = {
    "env.num_envs": "train.num_envs (mcrs-train) or episodes (mcrs-eval)",
    "env.device": "device",
}


def _unknown_key(full_key: str, error: OmegaConfBaseException) -> str:
    if full_key in RUNTIME_KEYS:
        return (
            f"{full_key}: not a scenario key (how the env runs, not the task): set {RUNTIME_KEYS[full_key]}"
        )
    parent, _, key = full_key.rpartition(".")
    node = getattr(error, "parent_node", None)
    keys = [str(k) for k in node if str(k) != "hydra"] if isinstance(node, DictConfig) else []
    if full_key.startswith("algo.options."):  # an algorithm's own settings: no schema lists them
        given = f"; the keys given: {', '.join(keys)}" if keys else ""
        return f"{full_key}: not in the config; add an algorithm's own setting with a '+': +{full_key}=<value>{given}"
    if not keys:
        return f"{full_key}: unknown key"
    where = f"the keys of {parent}" if parent else "the top-level keys"
    sections = (
        [k for k in keys if isinstance(node.get(k), DictConfig) and key in node.get(k)] if not parent else []
    )
    hint = f" (did you mean {' or '.join(f'{k}.{key}' for k in sections)}?)" if sections else ""
    return f"{full_key}: unknown key{hint}; {where}{listing(key, keys)}"


def _bad_value(message: str, cause: ValidationError) -> str:
    """``algo.mixer=qtran: allowed values are qmix, vdn, qplex`` or ``train.lr=abc: must be a number``."""
    prefix = "Error merging override "
    override = message.split("\n")[0][len(prefix) :] if message.startswith(prefix) else str(cause.full_key)
    reason = _lines(str(cause))[0]
    if "expected one of [" in reason:
        allowed = reason.split("expected one of [", 1)[1].rstrip("]").split(", ")
        value = override.split("=", 1)[-1]
        return f"{override}: allowed values{listing(value, allowed)}"
    for kind, wanted in TYPE_NAMES.items():
        if reason.endswith(f"could not be converted to {kind}") or f"is not a valid {kind.lower()}" in reason:
            return f"{override}: must be {wanted}"
    return f"{override}: {reason}"


def _lines(text: str) -> list[str]:
    """The lines of Hydra's report that say what is wrong, without its hints, search path or internals."""
    noise = ("Set the environment variable", "Config search path", "provider=", "See https://",
             "To append to your config", "full_key:", "reference_type=", "object_type=")  # fmt: skip
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("In '") and "': " in line:
            line = line.split("': ", 1)[1]  # "In 'config': Could not find ...": the provenance goes
        if line and not line.startswith(noise):
            out.append(line)
    return out
