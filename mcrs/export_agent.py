"""``mcrs-export``: a trained agent as one file that runs without mcrs (a ``torch.export`` program).

    mcrs-export outputs/map10/qmix/<run> agent.pt2         the run's latest weights
    mcrs-export <run>/checkpoints/model_000500000.pt agent.pt2 --force

The program maps the team's observations, action masks, previous actions and hidden states to greedy
actions and next hidden states, as its ``extra/mcrs.json`` describes. It is checked against the checkpoint
before it replaces ``out``. See docs/TRAINING.md, "Deploying a trained agent"."""

from __future__ import annotations

import argparse
import sys

from mcrs.experiment.run.checkpoint import CheckpointError
from mcrs.policies.export import ExportError, export_agent, read_description


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mcrs-export", description=__doc__.split("\n\n")[0])
    parser.add_argument("policy", help="a run directory (its latest weights) or a checkpoint .pt file")
    parser.add_argument("out", help="the file to write (.pt2)")
    parser.add_argument("--force", action="store_true", help="replace out if it exists")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        path = export_agent(args.policy, args.out, overwrite=args.force)
        meta = read_description(path)
    except (CheckpointError, ExportError) as error:
        print(f"mcrs-export: error: {error}", file=sys.stderr)
        return 1
    except OSError as error:  # a full disk or a read-only folder while writing
        print(f"mcrs-export: error: out={args.out}: {error.strerror or error}", file=sys.stderr)
        return 1
    steps = "" if meta["env_steps"] is None else f", {meta['env_steps']:,} env steps"
    trained_on = meta["task"]["name"] if "task" in meta else meta["env"]["name"]
    print(
        f"wrote {path} ({path.stat().st_size / 1e3:.0f} kB): {meta['algo']} on {trained_on}{steps}; "
        f"{meta['n_agents']} agents, observation {meta['obs_dim']}, {meta['n_actions']} actions, hidden "
        f"{meta['hidden_dim']}\n"
        f"  step = torch.export.load({str(path)!r}).module()\n"
        "  action, hidden = step(observation, action_mask, last_action, hidden)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
