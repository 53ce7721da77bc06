"""Running a benchmark command in-process and reading the figures it writes (the harness's JSON)."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any


def run_json(main: Callable[[Sequence[str]], int], path: Path, argv: Sequence[str]) -> dict[str, Any]:
    """``main(argv + --json path)``, which must succeed, and the report it wrote."""
    assert main([*argv, "--json", str(path)]) == 0
    return json.loads(path.read_text())
