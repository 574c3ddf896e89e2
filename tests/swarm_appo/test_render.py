"""python -m swarm_appo.render: a trained (here untrained) checkpoint flown and drawn, PNG and GIF."""
from __future__ import annotations

import pytest

from swarm_appo import render
from swarm_appo.testing import untrained_checkpoint


def test_render_writes_a_png_and_a_gif_of_the_checkpoint(tmp_path, capsys):
    run = untrained_checkpoint(tmp_path, "q", ["env.num_agents=3", "model.encoder_kwargs.hidden=8"])
    png, gif = render.main(["--checkpoint", str(run), "--steps", "20", "--frame-every", "10", "--num-agents", "4"])
    assert png.endswith("static_same_goal_n4_seed0.png") and gif.endswith(".gif")
    assert open(png, "rb").read(8) == b"\x89PNG\r\n\x1a\n" and open(gif, "rb").read(4) == b"GIF8"
    assert str(run / "render") in png  # next to the run
    out = capsys.readouterr().out
    assert "static_same_goal, 4 drones" in out and "success" in out
    again = render.main(["--checkpoint", str(run), "--steps", "5", "--frame-every", "5"])
    assert str(run / "render_2") in again[0]  # an earlier render is kept


@pytest.mark.parametrize("argv, message", [
    (["--scenario", "o_random"], "trained without the obstacle field"),
    (["--scenario", "nope"], "unknown --scenario 'nope'"),
    (["--steps", "0"], "--steps must be >= 1"),
])
def test_render_refuses_bad_input_with_one_line(tmp_path, capsys, argv, message):
    run = untrained_checkpoint(tmp_path, "q", ["env.num_agents=2", "model.encoder_kwargs.hidden=8"])
    with pytest.raises(SystemExit) as exc:
        render.main(["--checkpoint", str(run), *argv])
    assert exc.value.code == 2 and message in capsys.readouterr().err


def test_render_of_a_missing_checkpoint_is_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit):
        render.main(["--checkpoint", str(tmp_path / "nothing")])
    assert "does not exist" in capsys.readouterr().err
