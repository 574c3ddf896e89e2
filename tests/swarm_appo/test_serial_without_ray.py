"""An in-process run (``runner.serial=true``) needs torch, numpy and numba only: no Ray, no wandb (with
``wandb.mode=disabled``), no gymnasium. That is what a bare GPU machine with a torch image offers, and what the
device check in benchmarks/gpu_check.sh relies on."""
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BLOCKED = ("ray", "wandb", "gymnasium", "pettingzoo")

# A child interpreter in which importing any of BLOCKED fails, as if it were not installed.
PRELUDE = f"""
import runpy, sys
class _NotInstalled:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in {BLOCKED!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}} (blocked by the test)")
        return None
sys.meta_path.insert(0, _NotInstalled())
"""


def run_child(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", PRELUDE + code], capture_output=True, text=True, cwd=ROOT,
                          timeout=600)


def test_the_blocker_blocks():
    """The control: under the prelude the Ray sampler cannot be imported (so the test below can fail)."""
    out = run_child("import swarm_appo.ray_sampling")
    assert out.returncode != 0 and "No module named 'ray'" in out.stderr


def test_a_serial_run_trains_and_evaluates_without_ray_wandb_or_gymnasium(tmp_path):
    code = ("sys.argv = ['launchers.local', 'runner.serial=true', 'runner.num_workers=1', "
            "'runner.envs_per_worker=2', 'runner.total_agent_steps=4000', 'algo.rollout=32', "
            "'algo.batch_size=512', 'wandb.mode=disabled', 'runner.final_eval_episodes=1', "
            f"'runner.run_dir={tmp_path}', 'runner.name=bare', '--no-progress']\n"
            "try:\n    runpy.run_module('launchers.local', run_name='__main__')\n"
            f"finally:\n    print('LOADED', *[m in sys.modules for m in {BLOCKED!r}])\n")
    out = run_child(code)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split("LOADED")[-1].split() == ["False"] * len(BLOCKED)
    run = tmp_path / "bare"
    assert sorted(p.name for p in (run / "checkpoints").glob("ckpt_*.pt"))
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert records and records[-1]["global_step"] >= 4000
    assert not (run / "wandb").exists()
