"""Episode pictures (mcrs.viz): right file formats, figure 4's data shows what communication buys, and
the mcrs-render command (Hydra, typed schema, one-line errors)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from PIL import Image

from mcrs.env import scenario
from mcrs.render_episode import CONFIG_DIR
from mcrs.render_episode import run as render_run
from mcrs.viz import (
    episode_frames,
    plot_scene,
    plot_uncertainty_contours,
    rollout_comm_pair,
    rollout_episode,
    save_episode_gif,
    uncertainty_contour_data,
    write_episode_pictures,
)

SHORT = scenario("map10", max_steps=8)


@pytest.fixture(scope="module")
def short_episode():
    return rollout_episode(SHORT, "greedy", seed=3)


@pytest.fixture(scope="module")
def comm_pair():
    """A full map10 episode with R_c = 5 and the same seed without communication."""
    return rollout_comm_pair(scenario("map10"), "greedy", seed=0)


def _assert_image(path: Path, fmt: str) -> Image.Image:
    assert path.is_file() and path.stat().st_size > 2000
    image = Image.open(path)
    assert image.format == fmt
    assert image.size[0] > 200 and image.size[1] > 200
    return image


def test_rollout_episode_is_one_full_episode_with_beliefs(short_episode) -> None:
    cfg = SHORT
    assert short_episode.batch_size == (1, cfg.max_steps)
    assert short_episode.get(("agents", "belief_map")).shape == (1, cfg.max_steps, cfg.n_uavs, 2, 10, 10)
    assert short_episode.get(("next", "truncated"))[0, -1].all()
    frames = episode_frames(short_episode, cfg)
    assert frames.positions.shape == (cfg.max_steps + 1, cfg.n_uavs, 2)
    # Consecutive positions differ by one 8-neighbour move.
    step = np.abs(np.diff(frames.positions, axis=0)).max(-1)
    assert (step == 1).all()
    assert len(frames.no_fly) == cfg.n_no_fly and len(frames.targets) == cfg.n_targets


def test_episode_without_beliefs_is_refused() -> None:
    from mcrs.env import MCRSEnv
    from mcrs.policies import make_policy

    env = MCRSEnv(SHORT)
    td = env.rollout(3, make_policy("random", SHORT, 0), break_when_any_done=False)
    with pytest.raises(ValueError, match="expose_beliefs=True"):
        episode_frames(td, SHORT)


def test_plot_scene_writes_png(short_episode, tmp_path: Path) -> None:
    path = tmp_path / "scene.png"
    fig = plot_scene(short_episode, SHORT, path)
    image = _assert_image(path, "PNG")
    assert len(np.unique(np.asarray(image.convert("RGB")).reshape(-1, 3), axis=0)) > 20  # not blank
    assert "targets found" in fig.axes[0].get_title()


def test_plot_uncertainty_contours_writes_png(short_episode, tmp_path: Path) -> None:
    without = rollout_episode(SHORT.replace(comm_range=0.0), "greedy", seed=3)
    path = tmp_path / "contours.png"
    fig = plot_uncertainty_contours(short_episode, without, SHORT, path, uav=1, steps=(2, 8))
    _assert_image(path, "PNG")
    titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
    assert sum("with communication" in t for t in titles) == 2
    assert sum("without communication" in t for t in titles) == 2


def test_save_episode_gif_has_one_frame_per_step(short_episode, tmp_path: Path) -> None:
    path = save_episode_gif(short_episode, SHORT, tmp_path / "episode.gif", background=2)
    image = _assert_image(path, "GIF")
    assert image.n_frames == SHORT.max_steps + 1
    first, last = (np.asarray(image.convert("RGB")) for image in _frames(image, [0, SHORT.max_steps]))
    assert not np.array_equal(first, last)  # it is animated
    with pytest.raises(ValueError, match="background"):
        save_episode_gif(short_episode, SHORT, tmp_path / "bad.gif", background=99)


def test_gif_no_fly_zones_stand_out_from_the_belief_map_and_a_legend_names_every_mark(short_episode) -> None:
    """Each no-fly cell is dark and hatched over any belief colour (the red-blue map never is), and the
    legend names UAVs, targets, no-fly zones and comm links; the colour bar says which end is which."""
    from mcrs.env.render import StateDrawing

    fr = episode_frames(short_episode, SHORT)
    drawing = StateDrawing(SHORT, fr.no_fly, fr.targets)
    t = fr.steps
    found = (fr.global_maps[:, 1] >= SHORT.target_threshold).any(0)
    pixels = drawing.draw(fr.global_maps[t, 0], fr.positions[: t + 1], fr.neighbours[t], found, "last")
    pixels = pixels.astype(int)
    fig, ax = drawing.fig, drawing.ax
    height = pixels.shape[0]

    def cell(x: int, y: int) -> np.ndarray:  # the inner half of the cell's square, in pixels
        (x0, y0), (x1, y1) = ax.transData.transform([(x - 0.25, y - 0.25), (x + 0.25, y + 0.25)])
        return pixels[height - int(y1) : height - int(y0), int(x0) : int(x1)].reshape(-1, 3)

    no_fly = fr.no_fly
    assert len(no_fly)
    for x, y in no_fly:
        dark = (cell(x, y).max(axis=1) < 70).mean()
        assert dark > 0.3, f"no-fly cell ({x}, {y}): {dark:.0%} dark pixels"
    labels = " | ".join(t.get_text() for legend in fig.legends for t in legend.get_texts())
    for mark in ("UAV", "target, not yet found", "target found", "no-fly zone", "comm link"):
        assert mark in labels, labels
    bar = next(a for a in fig.axes if a is not ax)
    assert [t.get_text() for t in bar.get_yticklabels()] == ["0 known", "0.5", "1 uncertain"]


def _frames(image: Image.Image, indices: list[int]) -> list[Image.Image]:
    out = []
    for k in indices:
        image.seek(k)
        out.append(image.copy())
    return out


def test_contours_with_communication_are_less_uncertain(comm_pair) -> None:
    cfg = scenario("map10")
    with_comm, without = comm_pair
    steps = (0, 25, 50)
    for uav in range(cfg.n_uavs):
        a = uncertainty_contour_data(with_comm, cfg, uav, steps)
        b = uncertainty_contour_data(without, cfg, uav, steps)
        assert a.shape == (3, cfg.width, cfg.height)
        assert np.array_equal(a[0], b[0])  # same seed, same start; no exchange happens at reset
        assert a[2].mean() < b[2].mean()  # by the end, what the others sensed is known too
    with pytest.raises(ValueError, match="steps"):
        uncertainty_contour_data(with_comm, cfg, 0, (51,))


def test_write_episode_pictures_is_the_one_routine(tmp_path: Path) -> None:
    paths = write_episode_pictures(tmp_path / "pictures", SHORT, "lawnmower", seed=1, uav=3)
    assert [p.name for p in paths] == ["scene.png", "uncertainty_contours.png", "episode.gif"]
    _assert_image(paths[0], "PNG")
    _assert_image(paths[1], "PNG")
    assert Image.open(paths[2]).n_frames == SHORT.max_steps + 1
    assert (
        write_episode_pictures(tmp_path / "no_gif", SHORT, "random", seed=1, gif=False)[-1].suffix == ".png"
    )
    with pytest.raises(ValueError, match=r"uav=4: must be in 0\.\.3"):
        write_episode_pictures(tmp_path / "bad", SHORT, "random", seed=1, uav=4)


def _compose(overrides: list[str]):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base=None):
        return compose("render", overrides=overrides)


def test_render_config_is_typed_and_composes() -> None:
    cfg = _compose([])
    assert (cfg.policy, cfg.seed, cfg.uav, cfg.gif, cfg.env.name) == ("greedy", 0, 0, True, "map10")
    assert cfg.out.startswith("outputs/render/") and cfg.out.endswith(f"_{os.getpid()}")  # one per process
    cfg = _compose(["env=map20", "env.comm_range=3", "seed=4", "gif=false", "uav=9"])
    assert (cfg.env.name, cfg.env.comm_range, cfg.seed, cfg.gif, cfg.uav) == ("map20", 3, 4, False, 9)
    for bad in ("seed=abc", "gif=maybe", "bogus=1"):  # the schema refuses them before any work
        with pytest.raises(ConfigCompositionException):
            _compose([bad])


def test_render_run_in_process(tmp_path: Path, capsys) -> None:
    cfg = _compose(["env.max_steps=6", "policy=lawnmower", "seed=2", "gif=false"])
    paths = render_run(cfg, tmp_path)
    _assert_image(tmp_path / "scene.png", "PNG")
    _assert_image(tmp_path / "uncertainty_contours.png", "PNG")
    assert not (tmp_path / "episode.gif").exists()
    assert capsys.readouterr().out.split() == [str(p) for p in paths]
    for bad, message in [
        ("policy=bogus", "unknown policy 'bogus'"),
        ("uav=4", r"uav=4: must be in 0\.\.3"),
        ("env.comm_range=-1", "comm_range"),
    ]:
        with pytest.raises(ValueError, match=message):
            render_run(_compose(["env.max_steps=6", bad]), tmp_path / "bad")
    assert not (tmp_path / "bad").exists()  # checked before anything is drawn


def _cli(cwd: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mcrs.render_episode", *overrides],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "HYDRA_FULL_ERROR": "0"},
        cwd=cwd,
    )


@pytest.mark.slow
def test_mcrs_render_cli_writes_the_pictures_into_out_only(tmp_path: Path) -> None:
    out = tmp_path / "render"
    done = _cli(
        tmp_path, "env=map10", "policy=lawnmower", "seed=2", f"out={out}", "gif=false", "env.max_steps=6"
    )
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in out.iterdir()) == [
        "scene.png",
        "uncertainty_contours.png",
    ]  # no .hydra/, logs
    assert done.stdout.split() == [str(out / "scene.png"), str(out / "uncertainty_contours.png")]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["render"]


@pytest.mark.slow
def test_mcrs_render_cli_bad_input_is_one_line_without_traceback(tmp_path: Path) -> None:
    done = _cli(tmp_path, "uav=7", f"out={tmp_path / 'render'}")
    assert done.returncode != 0
    assert done.stderr.strip() == "mcrs-render: error: uav=7: must be in 0..3 (map10 has 4 UAVs)"
    assert not (tmp_path / "render").exists()
