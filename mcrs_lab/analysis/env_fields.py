"""``--set FIELD=VALUE`` for the lab's commands that build an environment themselves (the bound, the ledger)."""

from __future__ import annotations

from typing import Any

import yaml

from mcrs.env.config import EnvConfig, scenario


def scenario_with(prog: str, env: str, items: list[str], **fixed: Any) -> EnvConfig:
    """The preset ``env`` with each ``FIELD=VALUE`` of ``items`` (values read as YAML scalars) and ``fixed``;
    a malformed item or a refused value stops the command in one line naming it."""
    overrides: dict[str, Any] = {}
    for item in items:
        field, sep, text = item.partition("=")
        if not sep or not field:
            raise SystemExit(f"{prog}: error: --set {item!r}: must be FIELD=VALUE, e.g. p_false_alarm=0.1")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError:
            raise SystemExit(f"{prog}: error: --set {item!r}: {text!r} is not a value") from None
        if not isinstance(value, (str, int, float, bool)) and value is not None:
            raise SystemExit(f"{prog}: error: --set {item!r}: {text!r} is not a scalar")
        overrides[field] = value
    try:
        return scenario(env, **{**overrides, **fixed})
    except ValueError as error:
        raise SystemExit(f"{prog}: error: {' '.join(str(error).split())}") from None
