"""The batched MCRS-LCR simulator in pure torch: every tensor is ``[num_envs, ...]``, with no loop over envs
or UAVs.

This is the only implementation of the dynamics; the TorchRL and PettingZoo environments are adapters over
it, and :mod:`mcrs.env.outputs` builds what a reset or step returns. Cell ``(x, y)`` has flat index ``x *
height + y``. Count channel 0 holds positive readings ("F", target), channel 1 negative ones ("E").

The variants beyond the paper are off by default, and the code then follows the paper exactly:
``comm_delay`` and ``comm_budget`` (:mod:`mcrs.env.messages`), ``target_motion=random_walk``
(:mod:`mcrs.env.targets`), ``evidence_decay`` (:mod:`mcrs.env.evidence`) and ``far_view``
(:mod:`mcrs.env.far_view`). With moving targets or fading evidence, discoveries are judged at the targets'
current cells.
"""

from __future__ import annotations

import torch

from mcrs.env.belief import belief_masses
from mcrs.env.checks import check_action, scene_cells
from mcrs.env.config import EnvConfig
from mcrs.env.evidence import EvidenceDecay
from mcrs.env.far_view import FarView
from mcrs.env.fusion import apply_new_detections, fuse_known, neighbours_within, reachable_within
from mcrs.env.geometry import Geometry
from mcrs.env.messages import MessageChannel
from mcrs.env.metrics import METRICS  # noqa: F401 (read from here by mcrs.experiment, mcrs-eval and the lab)
from mcrs.env.outputs import CoreOutputs, StepResult  # StepResult: read from here by the adapters
from mcrs.env.shield import RightOfWay, safe_move_table, shielded_mask
from mcrs.env.targets import TargetWalk

# Paper eq. 1: action -> (dx, dy). 0 left, 1 right, 2 down, 3 up, 4 lower-left, 5 lower-right,
# 6 upper-right, 7 upper-left.
MOVES = ((-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, -1), (1, 1), (-1, 1))
N_ACTIONS = len(MOVES)
# Observation order D_s of the 8 surrounding cells (paper eq. 19).
SURROUNDING = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


def counts_dtype(config: EnvConfig) -> torch.dtype:
    """The dtype of the detection counts: int16 while every count fits (N (T + 1) < 2**15), else int32."""
    return torch.int16 if config.n_uavs * (config.max_steps + 1) < 2**15 else torch.int32


class MCRSCore(CoreOutputs):
    """Holds the state of ``num_envs`` independent episodes and advances them together."""

    def __init__(self, config: EnvConfig, device: torch.device | str | None = None) -> None:
        self.config = config
        self.device = torch.device(device if device is not None else config.device)
        cfg = config
        self.num_envs, self.n_uavs, self.n_cells = cfg.num_envs, cfg.n_uavs, cfg.n_cells
        self.rounds = cfg.rounds_per_step
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(0)

        dev, E, N, C = self.device, cfg.num_envs, cfg.n_uavs, cfg.n_cells
        self._moves = torch.tensor(MOVES, dtype=torch.int64, device=dev)
        self._grid_max = torch.tensor([cfg.width - 1, cfg.height - 1], dtype=torch.int64, device=dev)
        self._pos_scale = self._grid_max.clamp(min=1).to(torch.float32)
        # Per-cell lookup tables, so that masks and neighbourhoods are one gather per step.
        xy = torch.stack(torch.meshgrid(torch.arange(cfg.width), torch.arange(cfg.height), indexing="ij"), -1)
        xy = xy.reshape(C, 1, 2).to(dev)
        after_move = xy + self._moves  # [C, 8, 2]
        self._mask_of_cell = ((after_move >= 0) & (after_move <= self._grid_max)).all(-1)  # [C, 8]
        around = xy + torch.tensor(SURROUNDING, dtype=torch.int64, device=dev)  # [C, 8, 2] in D_s order
        self._around_on_grid = ((around >= 0) & (around <= self._grid_max)).all(-1).to(torch.float32)
        around = torch.minimum(around.clamp(min=0), self._grid_max)
        around_cell = around[..., 0] * cfg.height + around[..., 1]
        self._around_cell = around_cell  # [C, 8] flat cells in D_s order (clamped: read with _around_on_grid)
        # Flat count indices of the 8 surrounding cells: 8 positive, then 8 negative (contiguous planes).
        self._around_counts = torch.cat([around_cell * 2, around_cell * 2 + 1], dim=-1)  # [C, 16]
        # Flat (i, j) indices of the ordered pairs j != i, row by row: "every other UAV in index order".
        pairs = torch.arange(N * N, device=dev).view(N, N)
        self._other_pairs = pairs[~torch.eye(N, dtype=torch.bool, device=dev)]
        self._pair_upper = torch.triu(torch.ones(N, N, dtype=torch.bool, device=dev), diagonal=1)  # i < j
        self._earlier = self._pair_upper.transpose(0, 1).contiguous()  # [i, j]: j < i
        self._env_index = torch.arange(E, device=dev)
        count_dtype = counts_dtype(cfg)
        log_dtype = torch.int16 if 2 * C < 2**15 else torch.int32

        # Episode state: everything a step needs, about 24 kB per map20 environment (state_nbytes()).
        self.uav_pos = torch.zeros(E, N, 2, dtype=torch.int64, device=dev)
        self.no_fly_pos = torch.zeros(E, cfg.n_no_fly, 2, dtype=torch.int64, device=dev)
        self.target_pos = torch.zeros(E, cfg.n_targets, 2, dtype=torch.int64, device=dev)
        self.is_target = torch.zeros(E, C, dtype=torch.bool, device=dev)
        self.is_no_fly = torch.zeros(E, C, dtype=torch.bool, device=dev)
        # The paper's reading (config.py): zones known and empty in every map; zones hidden in the surround.
        self.known_zones = cfg.no_fly_prior == "known"
        self.hide_zones = cfg.no_fly_view == "blocked" or self.known_zones
        self.pay_beliefs = cfg.discovery_rule == "belief"
        self.step_count = torch.zeros(E, dtype=torch.int64, device=dev)
        self.reading = torch.zeros(E, N, dtype=torch.bool, device=dev)  # last reading, True = "F"
        # Detection log: log[e, s, q] = cell * 2 + channel of UAV q's reading at step s (s = 0 at reset).
        self.log = torch.zeros(E, cfg.max_steps + 1, N, dtype=log_dtype, device=dev)
        # known[e, i, q]: how many of q's detections UAV i has heard of (fast form of eq. 11).
        known_dtype = torch.int16 if cfg.max_steps < 2**15 - 1 else torch.int64
        self.known = torch.zeros(E, N, N, dtype=known_dtype, device=dev)
        # UAV i's fused (max-plus-sum) counts, and the global counts of every detection.
        self.counts = torch.zeros(E, N, 2 * C, dtype=count_dtype, device=dev)
        self.global_counts = torch.zeros(E, 2 * C, dtype=count_dtype, device=dev)
        # The global belief, kept current incrementally: only the cells sensed in a step change.
        self.global_belief = torch.zeros(E, 2, C, dtype=torch.float32, device=dev)  # m(U), m(F)
        self.discovered = torch.zeros(E, C, dtype=torch.bool, device=dev)  # D_find: global m(F) ever >= tau
        self.total_uncertainty = torch.zeros(E, dtype=torch.float32, device=dev)
        self.cells_sensed = torch.zeros(E, dtype=torch.float32, device=dev)
        self.targets_found = torch.zeros(E, dtype=torch.float32, device=dev)
        self.false_discoveries = torch.zeros(E, dtype=torch.float32, device=dev)
        self.episode_reward = torch.zeros(E, dtype=torch.float32, device=dev)
        self.collisions = torch.zeros(E, dtype=torch.float32, device=dev)
        self.no_fly_violations = torch.zeros(E, dtype=torch.float32, device=dev)
        # The variants beyond the paper exist only while they are on.
        paper_comms = cfg.comm_delay == 0 and cfg.comm_budget is None
        self.channel = None if paper_comms else MessageChannel(cfg, known_dtype, dev)
        self.decay = EvidenceDecay(cfg, dev) if cfg.evidence_decay > 0 else None
        if self.decay is not None:  # UAV counts hold sums of keep^-s (mcrs/env/evidence.py)
            self.counts = self.counts.to(torch.float64)
            self.global_counts = self.global_counts.to(torch.float32)  # the global counts now, aged in place
        self.walk = TargetWalk(cfg, self._moves, dev) if cfg.target_motion == "random_walk" else None
        self.dynamic = cfg.dynamic
        # dynamic: the targets found (current cell's m(F) >= tau) at least once in the episode.
        self.found_once = (
            torch.zeros(E, cfg.n_targets, dtype=torch.bool, device=dev) if self.dynamic else None
        )
        # no_fly_shield: per env, the moves from each cell that r3 would not charge (config.violates).
        self._safe_moves = (
            safe_move_table(self.no_fly_pos, self._moves, self._mask_of_cell, cfg)
            if cfg.no_fly_shield
            else None
        )
        # uav_shield: the table of which moves may meet (mcrs/env/shield.py).
        self._right_of_way = RightOfWay(self._moves, cfg) if cfg.uav_shield else None
        # far_view: the 8 window means of own m(U) appended to the observation (mcrs/env/far_view.py).
        self.far_view = FarView(cfg, self._moves) if cfg.far_view > 0 else None
        self._mask = self._action_mask()  # the action mask of the current positions

    # ------------------------------------------------------------------ public API
    def seed(self, seed: int) -> None:
        self.generator.manual_seed(int(seed))

    def state_nbytes(self) -> int:
        """Bytes of episode state held for all environments (the memory goal counts these)."""
        return sum(t.element_size() * t.numel() for t in self._state_tensors())

    def reset(self, mask: torch.Tensor | None = None) -> StepResult:
        """Start new episodes where ``mask`` (``[E]`` bool) is True, or everywhere when it is None."""
        if mask is None:
            envs = torch.arange(self.num_envs, device=self.device)
        else:
            envs = mask.reshape(self.num_envs).nonzero().squeeze(-1)
        if envs.numel():
            self._reset_envs(envs)
        zero = torch.zeros(self.num_envs, 4, device=self.device)
        return self._result(zero)

    def reset_to(
        self, uav_positions: torch.Tensor, no_fly_positions: torch.Tensor, target_positions: torch.Tensor
    ) -> StepResult:
        """Start every environment from a given scene, e.g. to replay or test one. Cells are ``(x, y)`` with
        shapes ``[E, N, 2]``, ``[E, n_no_fly, 2]`` and ``[E, n_targets, 2]``; the leading E may be omitted.
        The scene must obey the reset rules: distinct cells, and no UAV or target on a no-fly cell."""
        E = self.num_envs
        starts, no_fly, targets = scene_cells(
            self.config, E, self.device, uav_positions, no_fly_positions, target_positions
        )
        self._start_episodes(torch.arange(E, device=self.device), no_fly, targets, starts)
        return self._result(torch.zeros(E, 4, device=self.device))

    def step(self, action: torch.Tensor) -> StepResult:
        """Advance every environment by one step with ``action`` ``[E, N]`` (integers in 0..7)."""
        cfg = self.config
        action = check_action(action, self.config, self._mask, self.uav_pos)
        finished = self.step_count >= cfg.max_steps
        if finished.any():
            raise RuntimeError(
                f"environment(s) {finished.nonzero().squeeze(-1).tolist()[:10]} reached the time limit "
                f"max_steps={cfg.max_steps}: reset them before stepping (TorchRL: step_and_maybe_reset)"
            )
        # 0. Targets move (random_walk only; its draws come first, then the readings').
        if self.walk is not None:
            self.target_pos = self.walk.step(self.target_pos, self.is_target, self.generator)
        # 1. Move.
        target = self.uav_pos + self._moves[action]
        if cfg.invalid_action == "clip":
            target = torch.minimum(target.clamp(min=0), self._grid_max)
        self.uav_pos = target
        self.step_count += 1

        # 2. Sense: each UAV reads its own cell and logs the reading.
        cell = self._uav_cells()
        flat = self._sense(cell)
        self.log[self._env_index, self.step_count] = flat.to(self.log.dtype)

        # 3. Communicate: own detection first, then the synchronous exchange rounds.
        known_before = self.known.clone()
        self.known.diagonal(dim1=1, dim2=2).copy_((self.step_count + 1).unsqueeze(-1).expand(-1, self.n_uavs))
        geometry = self._geometry()
        neighbours = neighbours_within(geometry.uav_squared, cfg.comm_range)
        if self.channel is None:
            self.known = fuse_known(self.known, reachable_within(neighbours, self.rounds))
        else:
            self.known = self.channel.communicate(self.known, neighbours, self.step_count)
        weight = None if self.decay is None else self.decay.step_weight
        apply_new_detections(self.counts, known_before, self.known, self.log, weight)

        # 4. Global belief, rewards and metrics.
        if self.dynamic:
            uncertainty_drop, discoveries = self._update_global_belief_dynamic(cell, flat)
        else:
            uncertainty_drop, discoveries = self._update_global_belief(cell, flat)
        r_uncertainty = cfg.w_uncertainty * uncertainty_drop
        r_discovery = cfg.w_discovery * discoveries
        no_fly_events, collision_events = self._safety_events(geometry)
        r_no_fly = -cfg.w_no_fly * no_fly_events
        r_collision = -cfg.w_collision * collision_events
        terms = torch.stack([r_uncertainty, r_discovery, r_no_fly, r_collision], dim=-1)
        self.episode_reward += terms.sum(-1)
        self.collisions += collision_events
        self.no_fly_violations += no_fly_events
        return self._result(terms, geometry, neighbours)

    def counts_now(self) -> torch.Tensor:
        """``[E, N, 2 C]``: each UAV's fused counts at the current step (float32 when they decay)."""
        return self.counts if self.decay is None else self.decay.now(self.counts, self.step_count)

    # ------------------------------------------------------------------ internals
    def _state_tensors(self) -> list[torch.Tensor]:
        variants = [] if self.channel is None else self.channel.tensors()
        variants += [] if self.walk is None else self.walk.tensors()
        variants += [] if self.found_once is None else [self.found_once]
        return [
            self.uav_pos, self.no_fly_pos, self.target_pos, self.is_target, self.is_no_fly, self.step_count, self.reading,
            self.log, self.known, self.counts, self.global_counts, self.global_belief, self.discovered,
            self.total_uncertainty, self.cells_sensed, self.targets_found, self.false_discoveries,
            self.episode_reward, self.collisions, self.no_fly_violations, *variants,
        ]  # fmt: skip

    def _update_global_belief_dynamic(
        self, cell: torch.Tensor, flat: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Update the global belief with moving targets or fading evidence; return (drop of sum m(U),
        discoveries).

        A target counts as found while the global m(F) of its current cell is >= tau. With
        ``discovery_rule`` ``target``, r2 pays each target once per episode; with ``belief`` it pays each
        cell the first time its m(F) reaches tau. Fading evidence changes every cell, so the whole map is
        then recomputed."""
        cfg = self.config
        discovered_before = self.discovered.clone()
        if self.decay is None:
            drop, _ = self._update_global_belief(cell, flat)
        else:
            # One global map, read every step: aged in place (float32), cheaper than scaled storage here.
            counts = self.global_counts.mul_(self.decay.keep)
            counts.scatter_add_(1, flat, torch.ones_like(flat, dtype=counts.dtype))
            # Config validation keeps keep^max_steps a normal float32: a sensed cell's count stays > 0.
            self.cells_sensed = ((counts[:, 0::2] + counts[:, 1::2]) > 0).sum(-1).to(torch.float32)
            _, full, unknown = belief_masses(counts[:, 0::2], counts[:, 1::2], cfg.m_f, cfg.m_e)
            if self.known_zones:
                unknown, full = (
                    unknown.masked_fill(self.is_no_fly, 0.0),
                    full.masked_fill(self.is_no_fly, 0.0),
                )
            self.global_belief[:, 0], self.global_belief[:, 1] = unknown, full
            total = unknown.sum(-1)
            drop, self.total_uncertainty = self.total_uncertainty - total, total
        reached = self.global_belief[:, 1] >= cfg.target_threshold
        found = reached.gather(1, self.target_pos[..., 0] * cfg.height + self.target_pos[..., 1])
        self.targets_found = found.sum(-1).to(torch.float32)
        self.false_discoveries = (reached & ~self.is_target).sum(-1).to(torch.float32)
        new_targets = (found & ~self.found_once).sum(-1).to(torch.float32)
        self.found_once |= found
        self.discovered = discovered_before | reached
        if self.pay_beliefs:
            return drop, (reached & ~discovered_before).sum(-1).to(torch.float32)
        return drop, new_targets

    def _sense(self, cell: torch.Tensor) -> torch.Tensor:
        """Draw each UAV's reading of its ``cell`` ``[E, N]``; return the flat ``cell * 2 + channel``."""
        cfg = self.config
        p_positive = torch.where(self.is_target.gather(1, cell), cfg.p_detect, cfg.p_false_alarm)
        self.reading = torch.rand(cell.shape, generator=self.generator, device=self.device) < p_positive
        return cell * 2 + (~self.reading).long()

    def _reset_envs(self, envs: torch.Tensor) -> None:
        cfg, dev, M, N, C = self.config, self.device, envs.numel(), self.n_uavs, self.n_cells
        # No-fly and target cells are those of the largest random keys: a uniform draw without
        # replacement, cheaper with topk than with a full permutation.
        keys = torch.rand(M, C, generator=self.generator, device=dev)
        chosen = keys.topk(cfg.n_no_fly + cfg.n_targets, dim=1).indices
        no_fly, targets = chosen[:, : cfg.n_no_fly], chosen[:, cfg.n_no_fly :]
        # UAV starts: distinct cells outside no-fly zones (a UAV may start on a target).
        keys = torch.rand(M, C, generator=self.generator, device=dev)
        keys.scatter_(1, no_fly, -1.0)
        starts = keys.topk(N, dim=1).indices
        self._start_episodes(envs, no_fly, targets, starts)

    def _start_episodes(
        self, envs: torch.Tensor, no_fly: torch.Tensor, targets: torch.Tensor, starts: torch.Tensor
    ) -> None:
        """Begin episodes in ``envs`` from flat cells of no-fly zones, targets and UAV starts."""
        cfg, dev, M, N, C = self.config, self.device, envs.numel(), self.n_uavs, self.n_cells
        self.no_fly_pos[envs] = self._cell_to_xy(no_fly)
        if self._safe_moves is not None:
            self._safe_moves[envs] = safe_move_table(
                self.no_fly_pos[envs], self._moves, self._mask_of_cell, cfg
            )
        self.target_pos[envs] = self._cell_to_xy(targets)
        if self.walk is not None:
            self.walk.start(envs, no_fly)
        if self.channel is not None:
            self.channel.clear(envs)
        self.uav_pos[envs] = self._cell_to_xy(starts)
        is_target = torch.zeros(M, C, dtype=torch.bool, device=dev)
        is_target.scatter_(1, targets, True)
        self.is_target[envs] = is_target
        is_no_fly = torch.zeros(M, C, dtype=torch.bool, device=dev)
        is_no_fly.scatter_(1, no_fly, True)
        self.is_no_fly[envs] = is_no_fly
        self.step_count[envs] = 0
        self.episode_reward[envs] = 0.0
        self.collisions[envs] = 0.0
        self.no_fly_violations[envs] = 0.0

        # Every UAV senses its start cell (no reward); no exchange happens at reset.
        positive = torch.rand(M, N, generator=self.generator, device=dev) < torch.where(
            is_target.gather(1, starts), cfg.p_detect, cfg.p_false_alarm
        )
        flat = starts * 2 + (~positive).long()
        self.reading[envs] = positive
        log = torch.zeros(M, cfg.max_steps + 1, N, dtype=self.log.dtype, device=dev)
        log[:, 0] = flat.to(log.dtype)
        self.log[envs] = log
        self.known[envs] = torch.eye(N, dtype=self.known.dtype, device=dev).expand(M, N, N)
        counts = torch.zeros(M, N, 2 * C, dtype=self.counts.dtype, device=dev)
        counts.scatter_(2, flat.unsqueeze(-1), 1)
        self.counts[envs] = counts
        global_counts = torch.zeros(M, 2 * C, dtype=self.global_counts.dtype, device=dev)
        global_counts.scatter_add_(1, flat, torch.ones_like(flat, dtype=global_counts.dtype))
        self.global_counts[envs] = global_counts
        _, full, unknown = belief_masses(global_counts[:, 0::2], global_counts[:, 1::2], cfg.m_f, cfg.m_e)
        if self.known_zones:  # known and empty from reset: no uncertainty, never a discovery
            unknown, full = unknown.masked_fill(is_no_fly, 0.0), full.masked_fill(is_no_fly, 0.0)
        self.global_belief[envs] = torch.stack([unknown, full], dim=1)
        self.total_uncertainty[envs] = unknown.sum(-1)
        discovered = full >= cfg.target_threshold  # only when tau <= m_f: counted, never rewarded
        self.discovered[envs] = discovered
        self.cells_sensed[envs] = (global_counts.view(M, C, 2).sum(-1) > 0).sum(-1).to(torch.float32)
        self.targets_found[envs] = (discovered & is_target).sum(-1).to(torch.float32)
        self.false_discoveries[envs] = (discovered & ~is_target).sum(-1).to(torch.float32)
        if self.dynamic:
            # Found at reset (only when tau <= m_f): counted in the metrics, never rewarded.
            found = discovered.gather(1, targets)
            self.found_once[envs] = found
            self.targets_found[envs] = found.sum(-1).to(torch.float32)

    def _cell_to_xy(self, cell: torch.Tensor) -> torch.Tensor:
        return torch.stack([cell // self.config.height, cell % self.config.height], dim=-1)

    def _update_global_belief(
        self, cell: torch.Tensor, flat: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Add this step's readings to the global map; return (drop of sum m(U), discoveries r2 pays). Only
        the sensed cells change, so the work is O(E N). When several UAVs share a cell, the lowest index
        stands for it, so nothing is counted twice. A known no-fly cell keeps m(U) = m(F) = 0."""
        cfg = self.config
        same_cell = cell.unsqueeze(-1) == cell.unsqueeze(-2)  # [E, i, j]
        first = ~(same_cell & self._earlier).any(-1)  # no j < i on the same cell
        pair_index = torch.stack([cell * 2, cell * 2 + 1], dim=-1).view(self.num_envs, -1)
        before = self.global_counts.gather(1, pair_index).view(self.num_envs, self.n_uavs, 2)
        self.global_counts.scatter_add_(1, flat, torch.ones_like(flat, dtype=self.global_counts.dtype))
        after = self.global_counts.gather(1, pair_index).view(self.num_envs, self.n_uavs, 2)
        _, full, unknown = belief_masses(after[..., 0], after[..., 1], cfg.m_f, cfg.m_e)
        if self.known_zones:
            in_zone = self.is_no_fly.gather(1, cell)
            unknown, full = unknown.masked_fill(in_zone, 0.0), full.masked_fill(in_zone, 0.0)
        old_unknown = self.global_belief[:, 0].gather(1, cell)
        self.global_belief[:, 0].scatter_(1, cell, unknown)
        self.global_belief[:, 1].scatter_(1, cell, full)
        drop = ((old_unknown - unknown) * first).sum(-1)
        self.total_uncertainty -= drop
        self.cells_sensed += (first & (before.sum(-1) == 0)).sum(-1)
        # UAVs on one cell write identical values (same counts), so duplicate indices are harmless here.
        was_discovered = self.discovered.gather(1, cell)
        reached = full >= cfg.target_threshold
        self.discovered.scatter_(1, cell, reached | was_discovered)
        newly = first & reached & ~was_discovered
        on_target = self.is_target.gather(1, cell)
        new_targets = (newly & on_target).sum(-1).to(torch.float32)
        self.targets_found += new_targets
        self.false_discoveries += (newly & ~on_target).sum(-1)
        if self.pay_beliefs:  # eq. 24: every cell reaching tau is taken for a target
            return drop, newly.sum(-1).to(torch.float32)
        return drop, new_targets

    def _geometry(self) -> Geometry:
        return Geometry.of(self.uav_pos, self.no_fly_pos)

    def _safety_events(self, geometry: Geometry) -> tuple[torch.Tensor, torch.Tensor]:
        """Count, per environment, UAV-zone pairs closer than d1 and UAV pairs closer than d2 (within, for
        ``safety_rule=near``)."""
        cfg = self.config
        no_fly = cfg.violates(geometry.no_fly_squared, cfg.no_fly_safety).sum((-1, -2)).to(torch.float32)
        close = cfg.violates(geometry.uav_squared, cfg.uav_safety) & self._pair_upper
        return no_fly, close.sum((-1, -2)).to(torch.float32)

    def _uav_cells(self) -> torch.Tensor:
        return self.uav_pos[..., 0] * self.config.height + self.uav_pos[..., 1]

    def _action_mask(
        self, cell: torch.Tensor | None = None, geometry: Geometry | None = None
    ) -> torch.Tensor:
        """Return the ``[E, N, 8]`` mask: on-grid moves, less those the shields forbid (mcrs/env/shield.py)."""
        cell = self._uav_cells() if cell is None else cell
        on_grid = self._mask_of_cell[cell]
        mask = on_grid if self._safe_moves is None else shielded_mask(self._safe_moves, cell, on_grid)
        if self._right_of_way is not None:
            geometry = self._geometry() if geometry is None else geometry
            mask = self._right_of_way.mask(mask, on_grid, self.uav_pos, geometry.uav_squared, self._earlier)
        return mask
