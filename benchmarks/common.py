"""What every benchmark shares: the machine and commit it ran on, timing, the matmul roofline, RESULTS.md."""
from __future__ import annotations

import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Callable, List, Optional, Sequence, TypeVar

T = TypeVar("T")

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "RESULTS.md"


MATMUL_FLAGS = ("amx_bf16", "amx_tile", "avx512_bf16", "avx512f", "avx2")  # what bounds the GEMM rate


def machine(extra: str = "") -> str:
    """CPU model, its matrix-multiply flags (bf16/AMX), cores, OS (and whatever the caller adds)."""
    fields = {}  # the first core's "model name" and "flags"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            fields.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    model = fields.get("model name") or platform.processor() or "unknown cpu"
    flags = set(fields.get("flags", "").split())
    present = [f for f in MATMUL_FLAGS if f in flags]
    text = (f"{model} (flags: {' '.join(present) or 'none of ' + '/'.join(MATMUL_FLAGS)}), {os.cpu_count()} cores, "
            f"Python {platform.python_version()}, {platform.system()} {platform.machine()}")
    return f"{text}, {extra}" if extra else text


def commit(paths: Sequence[str] = ()) -> str:
    """Short HEAD sha, marked when the measured code (``paths``) has uncommitted changes."""
    try:
        sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                             text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", *paths], cwd=ROOT, capture_output=True,
                               text=True).stdout.strip() if paths else ""
        return sha + (f" ({', '.join(paths)} modified)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def load_average() -> str:
    try:
        return " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def steady_window(items: Sequence[T], time_of: Callable[[T], float], warmup_fraction: float = 0.3) -> List[T]:
    """The items (in time order) after the warm-up: ``warmup_fraction`` of the span from the first to the last;
    at least the last two."""
    t0, t1 = time_of(items[0]), time_of(items[-1])
    steady = [x for x in items if time_of(x) >= t0 + warmup_fraction * (t1 - t0)]
    return steady if len(steady) >= 2 else list(items[-2:])


def best_time(fn: Callable[[], object], repeats: int) -> float:
    """Best wall time of ``repeats`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def gemm_rate(precision: str = "fp32", repeats: int = 3, size: int = 1024) -> float:
    """FLOP/s of a size^3 matmul in ``precision`` ("fp32", or "bf16": bf16 operands, as autocast runs a
    Linear) with the current torch thread setting."""
    import torch

    dtype = {"fp32": torch.float32, "bf16": torch.bfloat16}[precision]
    a, b = torch.randn(size, size, dtype=dtype), torch.randn(size, size, dtype=dtype)

    def ten():
        for _ in range(10):
            a @ b
    return 10 * 2 * size ** 3 / best_time(ten, repeats)


def append_results(section: str) -> None:
    """Append one section (Markdown) to benchmarks/RESULTS.md."""
    with RESULTS.open("a") as fh:
        fh.write("\n" + section.rstrip() + "\n")
    print(f"appended to {RESULTS}")


def section_header(name: str, started: str, argv: Optional[Sequence[str]], measured: Sequence[str],
                   load_before: str) -> List[str]:
    """The first lines of a RESULTS.md section: title, the command as typed, the commit (marked when the
    ``measured`` packages have uncommitted changes), the machine and the load averages before and now."""
    import sys

    args = " ".join(argv if argv is not None else sys.argv[1:])
    return [f"## {name} — {started}", "",
            f"- command: `{f'python -m benchmarks.{name} {args}'.strip()}`",
            f"- commit: {commit(list(measured))}",
            f"- machine: {machine()}; load average before: {load_before}, after: {load_average()}"]


def publish(section: str, append: bool) -> None:
    """Print a section and, unless told not to, append it to RESULTS.md."""
    print(section)
    if append:
        append_results(section)
