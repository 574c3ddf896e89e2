"""Pictures: the 3-D trajectory PNG, the top/side GIF, and the one-command renderer."""
import numpy as np
import pytest
from PIL import Image

from quad_env import EnvConfig
from quad_env.render import main, record_episode, save_animation_gif


def test_render_command_writes_a_png_and_an_animated_gif(tmp_path, capsys):
    png, gif = main(["--scenario", "ep_lissajous3D", "--out", str(tmp_path), "--steps", "12", "--num-agents", "3",
                     "--policy", "random", "--frame-every", "4"])
    out = capsys.readouterr().out
    assert png in out and gif in out and "success" in out
    with open(png, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    with Image.open(gif) as im:
        assert im.format == "GIF" and im.n_frames == 4  # steps 0, 4, 8, 12
    with pytest.raises(SystemExit):
        main(["--scenario", "nope", "--out", str(tmp_path)])


def test_recorded_episode_marks_every_collision_and_takes_a_policy_callable(tmp_path):
    cfg = EnvConfig(num_agents=32, scenario="static_same_goal", num_neighbors=2)
    seen = []

    def policy(obs, state):  # the hook a trained policy uses
        seen.append(obs.shape)
        return np.full((32, 4), -1.0, np.float32)  # motors off: the swarm falls

    ep = record_episode(cfg, policy, steps=6, seed=1)
    assert seen == [(32, cfg.num_neighbors * 21 + 18 + cfg.num_neighbors)] * 6
    assert ep.pos.shape == (7, 32, 3) and ep.goal.shape == (7, 32, 3)
    assert np.all(np.diff(ep.pos[:, :, 2], axis=0) <= 1e-12)  # falling
    ep = record_episode(cfg, "controller", steps=150, seed=0)  # a crowded swarm converging on one goal
    assert len(ep.collisions) == ep.stats["collisions"] >= 1  # one mark per new contact
    assert np.all(ep.collisions[:, 0] >= 1) and np.all(ep.collisions[:, 0] <= 150)
    for t, x, y, z in ep.collisions:  # marks lie between two drones that touch at that step
        d = np.linalg.norm(ep.pos[int(t)] - [x, y, z], axis=1)
        assert np.sort(d)[1] <= 0.092 / 2 + 1e-9
    gif = save_animation_gif(ep, str(tmp_path / "a.gif"), frame_every=50)
    with Image.open(gif) as im:
        assert im.n_frames == 4
