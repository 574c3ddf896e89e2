"""Numeric precision of the network's matrix multiplies: fp32, or bf16 mixed precision (``torch.autocast``).

Under bf16 the weights and the optimizer state stay fp32 (autocast casts the inputs of each matmul, and
its gradients come back in fp32); the policy's mean and value leave the model in fp32
(``ActorCritic.forward``), so log-probs, importance ratios, V-trace and the loss reductions are fp32; the
canonicalization of the observations and the typed readout of the symmetric encoders run in fp32 too
(``encoders.frames.full_precision``), so their inputs are exactly canonical. Inside the Graphormer's layers
the rotations of the hidden features and the pair products read bf16 operands, cast once per layer
(``encoders.graphormer``): their values are rounded to bf16 by the next matmul anyway.

``runner.precision: auto`` resolves on the learner's device:

- CUDA: fp32. At the shipped batch sizes a CUDA learner is bound by kernel launches, not arithmetic, and
  autocast's casts are more launches: on an H200 at the paper's config (se3_graphormer, batch 4096) bf16 was
  0.79x fp32 for the learner alone and 0.92x end to end with 15 Ray rollout workers; at batch 16384 it was
  1.20x (benchmarks/RESULTS.md, "gpu_check"). Ask for ``bf16`` with large batches;
- CPU: bf16 when the CPU multiplies bf16 natively (AMX or AVX-512 BF16: Intel Sapphire Rapids and later,
  AMD Zen 4 and later) *and* the model has the paper's widths (``model.size: paper``); fp32 otherwise.
  On the 2-core AMX Xeon of benchmarks/RESULTS.md ("bf16"), one learner step at batch 2048 was 1.6-2.5x
  faster in bf16 at paper sizes, but 0.9-1.3x for the 64-wide ``size: small`` models (their matmuls are
  too small to pay for the casts); a rollout worker's 128-drone forward was 0.6-0.75x at small sizes and
  0.9-1.3x at paper sizes.

``runner.inference_precision`` follows the same rule, resolved by each rollout worker on its own CPU.
"""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Tuple

import torch

from swarm_appo.config import PRECISIONS
BF16_CPU_FLAGS = ("amx_bf16", "avx512_bf16")  # native bf16 dot products (AMX tiles, AVX-512 BF16)


def cpu_flags() -> frozenset:
    """The CPU feature flags of /proc/cpuinfo (empty where it does not exist, e.g. macOS)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "flags":
                return frozenset(value.split())
    except OSError:
        pass
    return frozenset()


def native_bf16(device: torch.device) -> Tuple[bool, str]:
    """Whether ``device`` multiplies bf16 natively, and the evidence in words."""
    if device.type == "cuda":
        ok = torch.cuda.is_bf16_supported()
        return ok, f"{torch.cuda.get_device_name(device)} {'supports' if ok else 'lacks'} bf16"
    flags = [f for f in BF16_CPU_FLAGS if f in cpu_flags()]
    if flags:
        return True, f"CPU flags {' '.join(flags)}"
    return False, f"CPU without {' or '.join(BF16_CPU_FLAGS)}"


def resolve_precision(precision: str, device: torch.device, model_size: str = "paper") -> Tuple[str, str]:
    """``(fp32 | bf16, why)`` for ``runner.precision`` on the learner's ``device`` (see the module docstring)."""
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}; valid: {list(PRECISIONS)}")
    if precision != "auto":
        return precision, "set by runner.precision"
    ok, evidence = native_bf16(device)
    if not ok:
        return "fp32", f"auto: {evidence}"
    if device.type == "cuda":
        return "fp32", (f"auto: {evidence}, but a CUDA learner at these batch sizes is launch-bound and bf16's "
                        "casts made it slower (set runner.precision=bf16 for batches of 16k agent steps and more)")
    if device.type == "cpu" and model_size != "paper":
        return "fp32", f"auto: {evidence}, but model.size={model_size} (too narrow for bf16 to pay on a CPU)"
    return "bf16", f"auto: {evidence}"


def autocast(precision: str, device: torch.device):
    """The context the network's forward (and backward) runs in: autocast to bf16, or nothing for fp32."""
    if precision == "bf16":
        return torch.autocast(device.type, dtype=torch.bfloat16)
    if precision == "fp32":
        return contextlib.nullcontext()
    raise ValueError(f"precision must be resolved to fp32 or bf16, got {precision!r}")
