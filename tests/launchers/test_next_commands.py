"""The commands a finished run suggests ("next:") exist: each names a module with a command line and options it
accepts, so a user can paste them."""
import importlib
import shlex
from pathlib import Path

from launchers.common import print_result
from swarm_appo.trainer import RunResult


def test_every_suggested_command_parses(capsys, tmp_path):
    run = tmp_path / "runs" / "demo"
    print_result(RunResult(run_dir=run, agent_steps=10, policy_version=1, checkpoint=run / "checkpoints" / "c.pt",
                           worker_restarts=0))
    lines = capsys.readouterr().out.split("next:\n")[1].splitlines()
    commands = [shlex.split(line.split("#")[0]) for line in lines if line.strip()]
    modules = [c[2] for c in commands]
    assert "swarm_appo.select_checkpoint" in modules and "swarm_appo.evaluate" in modules
    for argv in commands:
        assert argv[:2] == ["python", "-m"], argv
        module = importlib.import_module(argv[2])
        if argv[2] == "launchers.local":
            continue  # its parser is checked by tests/launchers/test_local.py (--resume of a run)
        parser = module.build_parser() if hasattr(module, "build_parser") else None
        if parser is not None:
            parser.parse_args(argv[3:])  # SystemExit (exit code 2) on an unknown option
        else:
            assert callable(module.main), argv[2]
    assert any(str(Path(run)) in line for line in lines)
