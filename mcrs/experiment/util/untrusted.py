"""Names, paths and files that come from outside the program, checked before anything is read or written.

Campaign files, records, a run's ``config.yaml`` and the command line are written by someone else, so every
tool uses the same checks:

- :func:`plain_name`: a value that becomes one path component is letters, digits and ``_ . + = -``, not
  starting with a dot, so ``..``, ``a/b`` and ``.hidden`` never become a directory.
- :func:`confined`: a path built from such values, or read from a file, must resolve under its root.
- :func:`read_yaml` refuses anchors and aliases (the "billion laughs" bomb), files over :data:`MAX_YAML_BYTES`
  and nesting over :data:`MAX_DEPTH` while scanning the events, at a cost in proportion to the file.
- :func:`check_archive` refuses a checkpoint unless it is a torch zip archive of at most :data:`MAX_MEMBERS`
  stored members in one folder, so a zip bomb is refused from its directory alone.
"""

from __future__ import annotations

import math
import os
import re
import zipfile
from pathlib import Path
from typing import Any

import yaml

#: A run's config.yaml is about 5 kB, a campaign file a few kB: 1 MiB leaves room and bounds the parse.
MAX_YAML_BYTES = 1 << 20
#: Nesting of mappings and lists: a config is 3 deep; a record's JSON about 5.
MAX_DEPTH = 32
#: A torch zip archive has a handful of members plus one per tensor storage (a full run: a few thousand).
MAX_MEMBERS = 200_000
#: Plain names: what may become one path component.
PLAIN_NAME = re.compile(r"[A-Za-z0-9_+=-][A-Za-z0-9_.+=-]{0,127}")


class UntrustedInput(ValueError):
    """A name, path or file from outside that is refused (one line, naming it and the rule)."""


# ------------------------------------------------------------------------------------------- names
def plain_name(value: Any, what: str) -> str:
    """``value`` as a plain name (one path component), or :class:`UntrustedInput` naming ``what``."""
    if not isinstance(value, (str, int)) or isinstance(value, bool) or not PLAIN_NAME.fullmatch(str(value)):
        raise UntrustedInput(
            f"{what}={value!r}: must be a plain name (letters, digits, _ . + = -, not starting with "
            "'.', at most 128 characters): it names a directory"
        )
    return str(value)


def confined(path: str | Path, root: str | Path, what: str) -> Path:
    """``path`` resolved, symbolic links followed, and refused unless it lies under ``root``."""
    root = Path(os.path.abspath(root)).resolve()
    resolved = Path(os.path.abspath(path)).resolve()
    if resolved != root and not resolved.is_relative_to(root):
        raise UntrustedInput(f"{what}={path}: resolves to {resolved}, outside {root}: refused")
    return resolved


# -------------------------------------------------------------------------------------------- YAML
def check_yaml_text(text: str, where: str, max_depth: int = MAX_DEPTH) -> None:
    """Scan ``text``'s YAML events without building objects; refuse anchors, aliases and deep nesting."""
    depth = 0
    try:
        for event in yaml.parse(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
            if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None):
                raise UntrustedInput(
                    f"{where} holds YAML anchors or aliases (&, *): refused unexpanded (write the values out)"
                )
            if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                depth += 1
                if depth > max_depth:
                    raise UntrustedInput(f"{where} is nested deeper than {max_depth} levels: refused")
            elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
                depth -= 1
    except yaml.YAMLError as error:
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise UntrustedInput(f"{where} is not a valid config (bad YAML: {first})") from None


def read_yaml_text(path: str | Path, max_bytes: int = MAX_YAML_BYTES) -> str:
    """The text of ``path``, refused before it is read past ``max_bytes`` or when not UTF-8."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = f.read(max_bytes + 1)
    except OSError as error:
        raise UntrustedInput(f"cannot read {path}: {error.strerror or error}") from None
    if len(data) > max_bytes:
        raise UntrustedInput(f"{path} is larger than {max_bytes:,} bytes: refused unread")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise UntrustedInput(f"{path} is not a valid config (not UTF-8 text)") from None


def read_yaml(
    path: str | Path, max_bytes: int = MAX_YAML_BYTES, interpolations: bool = True, resolve: bool = False
) -> Any:
    """Plain data from the YAML file ``path`` through OmegaConf's safe loader, after :func:`check_yaml_text`'s
    bounds. ``interpolations=False`` refuses ``${...}``, which a resolved file such as a run's ``config.yaml``
    never holds and which can multiply a file's size as aliases do."""
    from omegaconf import OmegaConf  # here: the other checks need only PyYAML
    from omegaconf.errors import OmegaConfBaseException

    text = read_yaml_text(path, max_bytes)
    check_yaml_text(text, str(path))
    if not interpolations and "${" in text:
        raise UntrustedInput(
            f"{path} holds an interpolation '${{...}}' (a saved config is resolved): refused"
        )
    try:
        loaded = OmegaConf.create(text) if text.strip() else OmegaConf.create({})
        return OmegaConf.to_container(loaded, resolve=resolve)
    except yaml.constructor.ConstructorError as error:
        tag = f" ({error.problem})" if error.problem else ""
        raise UntrustedInput(f"{path} is not plain YAML data{tag}: refused without running it") from None
    except (yaml.YAMLError, OmegaConfBaseException, ValueError, TypeError) as error:
        first = (str(error).strip().splitlines() or [type(error).__name__])[0]
        raise UntrustedInput(f"{path} is not a valid config ({first})") from None


# ----------------------------------------------------------------------------------------- numbers
def depth_of(value: Any, limit: int = MAX_DEPTH) -> int:
    """Nesting depth of plain data, counted without recursion so a deep file cannot exhaust the stack."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        node, level = stack.pop()
        if isinstance(node, (dict, list)):
            deepest = max(deepest, level)
            if deepest > limit:
                return deepest
            stack.extend((v, level + 1) for v in (node.values() if isinstance(node, dict) else node))
    return deepest


def finite_number(value: Any) -> bool:
    """Whether ``value`` is a finite JSON or YAML number, not a bool, NaN or inf."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


# ------------------------------------------------------------------------------------- checkpoints
def check_archive(path: str | Path) -> str | None:
    """Why the torch file ``path`` must not reach ``torch.load``, or None: it needs one top folder, stored
    members only (torch never compresses), sizes within the file, at most :data:`MAX_MEMBERS` members and no
    absolute or ``..`` names."""
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"PK\x03\x04":
        return "it is corrupt or not a torch file (not a zip archive)"
    try:
        with zipfile.ZipFile(path) as archive:
            members = archive.infolist()
    except (zipfile.BadZipFile, OSError, ValueError) as error:
        return f"it is truncated or corrupt (its zip directory cannot be read: {error})"
    if not members or len(members) > MAX_MEMBERS:
        return f"it has {len(members)} archive members (a checkpoint has 1 to {MAX_MEMBERS:,})"
    tops = {m.filename.split("/", 1)[0] for m in members}
    declared = 0
    for member in members:
        name = member.filename
        if name.startswith("/") or ".." in name.split("/"):
            return f"it has an archive member outside its folder ({name!r})"
        if member.compress_type != zipfile.ZIP_STORED:
            return f"its member {name!r} is compressed (torch stores members uncompressed; a zip bomb?)"
        declared += member.file_size
    if len(tops) != 1:
        return f"its archive members are in {len(tops)} folders (a torch file has one)"
    if declared > size:
        return f"its members declare {declared:,} bytes, more than the file's {size:,}"
    return None
