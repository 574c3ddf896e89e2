"""bf16 tanh on the CPU: torch's own kernel against ``encoders.common.Tanh`` (fp32 in L2-sized chunks, rounded once),
for the tanh alone at the encoders' shapes and for whole bf16 learner calls, side by side in one process (issue 16).

    python -m benchmarks.bf16_tanh [--encoders kattention,se3_kattention,se3_graphormer,deepsets] [--rounds 3]
                                   [--config configs/paper.yaml] [key=value ...]

The learner rows build one bf16 learner per variant on the same batch (``benchmarks.gpu_learner``), the only
difference being the tanh modules (``nn.Tanh`` swapped in for the native row), then time their calls alternately,
``--rounds`` each, and report the best; one learner thread, as a 2-core run's learner has. The two variants give
bit-identical outputs and gradients (tests/encoders/test_activations.py).
"""
from __future__ import annotations

import argparse
import datetime
from typing import Optional, Sequence

import torch
from torch import nn

from benchmarks.common import best_time, load_average, publish, section_header
from encoders.common import Tanh

SHAPES = [(4096 * 6, 256), (4096, 512), (4096, 256), (4096 * 7, 64)]  # per-neighbour, join, self, small preset


def op_rows():
    """Forward + backward of one tanh on a bf16 tensor of each shape, native vs ours (ms, best of 20)."""
    ours = Tanh()
    rows = []
    for shape in SHAPES:
        x = torch.randn(*shape).bfloat16().requires_grad_()
        g = torch.randn(*shape).bfloat16()
        native = 1e3 * best_time(lambda: torch.autograd.grad(torch.tanh(x), x, g), 20)
        fast = 1e3 * best_time(lambda: torch.autograd.grad(ours(x), x, g), 20)
        rows.append(f"| tanh {list(shape)} bf16, forward + backward | {native:.2f} ms | {fast:.2f} ms | "
                    f"{native / fast:.2f}x |")
        print(rows[-1], flush=True)
    return rows


def with_native_tanh(model: nn.Module) -> int:
    """Swap every ``encoders.common.Tanh`` in ``model`` for ``nn.Tanh`` (in place); returns how many."""
    swaps = [(parent, name) for parent in model.modules() for name, child in parent.named_children()
             if isinstance(child, Tanh)]
    for parent, name in swaps:
        setattr(parent, name, nn.Tanh())
    return len(swaps)


def learner_rows(configs, rounds: int):
    """``configs``: encoder name -> its loaded config."""
    from benchmarks.gpu_learner import collect_batch, make_learner, timed_call

    rows = []
    device = torch.device("cpu")
    for name, cfg in configs.items():
        batch = collect_batch(cfg)
        torch.set_num_threads(1)
        native, ours = make_learner(cfg, device, "bf16"), make_learner(cfg, device, "bf16")
        swapped = with_native_tanh(native.model)
        times = {"native": [], "ours": []}
        for learner in (native, ours):
            timed_call(learner, batch, device)  # warm-up
        for _ in range(rounds):
            times["native"].append(timed_call(native, batch, device))
            times["ours"].append(timed_call(ours, batch, device))
        steps = sum(f["num_agent_steps"] for f in batch)
        n_s, o_s = steps / min(times["native"]), steps / min(times["ours"])
        rows.append(f"| {name} learner call, bf16, {cfg.algo.num_epochs} epoch(s), {swapped} tanh layers | "
                    f"{n_s:,.0f} agent-steps/s | {o_s:,.0f} agent-steps/s | {o_s / n_s:.2f}x |")
        print(rows[-1], flush=True)
    return rows


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--encoders", default="kattention,se3_kattention,se3_graphormer,deepsets")
    p.add_argument("--config", default="configs/paper.yaml")
    p.add_argument("--rounds", type=int, default=3, help="timed calls per variant, alternating")
    p.add_argument("--no-append", action="store_true", help="print only; do not append to RESULTS.md")
    p.add_argument("overrides", nargs="*", help="config overrides, e.g. algo.num_epochs=1")
    args = p.parse_args(argv)
    if args.rounds < 1:
        raise SystemExit(f"--rounds must be >= 1, got {args.rounds}")
    from swarm_appo.config import ConfigError, load_config

    configs = {}  # every config checked before anything is timed
    for name in (e.strip() for e in args.encoders.split(",") if e.strip()):
        try:
            configs[name] = load_config(args.config, [f"model.encoder={name}", "model.symmetry=null",
                                                      *args.overrides])
        except ConfigError as exc:
            raise SystemExit(f"config error: {exc}")
    torch.set_num_threads(1)
    started, load_before = datetime.datetime.now().isoformat(timespec="seconds"), load_average()
    lines = ["| what | torch's bf16 tanh | encoders.common.Tanh | ours / native |", "|---|---:|---:|---:|"]
    lines += op_rows()
    lines += learner_rows(configs, args.rounds)
    publish("\n".join([
        *section_header("bf16_tanh", started, argv, ["encoders", "swarm_appo", "benchmarks"], load_before),
        f"- torch {torch.__version__}, 1 thread; config: `{args.config}`"
        f"{' with ' + ' '.join(args.overrides) if args.overrides else ''}; ops: best of 20; "
        f"learner calls: best of {args.rounds}, the two variants alternating",
        "",
        *lines,
    ]), append=not args.no_append)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
