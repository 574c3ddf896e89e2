#!/usr/bin/env bash
# The GPU path, proven on a device machine (issue 16 item 5), as one prepared call of about 7 minutes:
#     device run: command "bash benchmarks/gpu_check.sh", timeout_s 570
# The device image has Python 3.12 with torch (CUDA), numpy, numba, pyyaml and tqdm, but no Ray, wandb or
# gymnasium, and Ray's wheel (78 MB) is larger than what one call may carry. So this check runs what needs
# none of them (tests/swarm_appo/test_serial_without_ray.py keeps that true):
#   1. benchmarks.gpu_learner: the learner alone on the GPU at paper sizes, fp32 vs bf16 (agent-steps/s it can
#      take in, peak GPU memory);
#   2. the paper config (se3_graphormer, mix, 8 drones) trained serially for a few minutes: learner on the GPU
#      (runner.precision=auto: bf16 there), rollout workers in the same process on the CPU; agent-steps/s,
#      learner share, system/gpu_* metrics, a checkpoint reloaded onto the CPU (map_location);
#   nvidia-smi samples utilisation and memory every second throughout.
# Results land in $OUT (the device tool brings back at most 8 files): env.txt, smi.csv, learner.log, train.log,
# train_metrics.jsonl, summary.txt. Paste summary.txt and learner.log's table into benchmarks/RESULTS.md.
# Checked without a GPU (same steps on the CPU, shorter): DEVICE=cpu TRAIN_S=30 LEARNER_S=2 bash benchmarks/gpu_check.sh
set -u
OUT=${OUT:-gpu_check_out}
mkdir -p "$OUT"
PY=${PYTHON:-python3}
DEVICE=${DEVICE:-cuda} TRAIN_S=${TRAIN_S:-150} LEARNER_S=${LEARNER_S:-15}
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD
RUNS=$(mktemp -d)

{ date -u; nvidia-smi; lscpu | grep -E "Model name|^CPU\(s\)"; git log -1 --format="commit %h %s" 2>/dev/null
  $PY -c "import torch, numba, numpy; print('torch', torch.__version__, 'cuda', torch.version.cuda,
torch.cuda.is_available(), torch.cuda.get_device_name(0), 'bf16', torch.cuda.is_bf16_supported(),
'numba', numba.__version__, 'numpy', numpy.__version__)"; } > "$OUT/env.txt" 2>&1
nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used,power.draw --format=csv -l 1 > "$OUT/smi.csv" 2>&1 &
SMI=$!

echo "== 1. learner alone (paper sizes, fp32 vs bf16)"
timeout 200 $PY -m benchmarks.gpu_learner --device $DEVICE --seconds $LEARNER_S --no-append > "$OUT/learner.log" 2>&1
echo "rc=$?" >> "$OUT/learner.log"

echo "== 2. paper config, serial, learner on the GPU"
timeout 300 $PY -m launchers.local --config configs/paper.yaml runner.serial=true runner.num_workers=1 \
    runner.device=$DEVICE runner.precision=auto runner.time_limit_s=$TRAIN_S runner.checkpoint_every_s=60 \
    runner.final_eval_episodes=2 wandb.mode=disabled runner.run_dir="$RUNS" runner.name=paper_gpu \
    --no-progress > "$OUT/train.log" 2>&1
echo "rc=$?" >> "$OUT/train.log"
cp "$RUNS/paper_gpu/metrics.jsonl" "$OUT/train_metrics.jsonl" 2>/dev/null
kill $SMI 2>/dev/null

$PY - "$RUNS/paper_gpu" "$OUT/smi.csv" > "$OUT/summary.txt" 2>&1 <<'PYEOF'
import json, statistics, sys
from pathlib import Path
run, smi = Path(sys.argv[1]), Path(sys.argv[2])
recs = [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()] if (run / "metrics.jsonl").exists() else []
late = [r for r in recs if "perf/agent_steps_per_s" in r][len(recs) // 3:]  # past the start-up
def med(k):
    v = [r[k] for r in late if k in r]
    return f"{statistics.median(v):,.3f}" if v else "-"
print("training records:", len(recs), "last global_step:", recs[-1]["global_step"] if recs else "-")
for k in ("perf/agent_steps_per_s", "perf/learner_samples_per_s", "perf/learner_share", "perf/inference_share",
          "perf/env_share", "system/gpu_mem_mb", "system/gpu_max_mem_mb", "system/gpu_util", "system/max_rss_mb"):
    print(f"median over the last 2/3 of records, {k}: {med(k)}")
rows = [l.split(", ") for l in smi.read_text().splitlines()[1:] if l.count(",") >= 3]
util = [float(r[1].split()[0]) for r in rows if r[1].split()[0].replace(".", "").isdigit()]
mem = [float(r[2].split()[0]) for r in rows if r[2].split()[0].isdigit()]
if util:
    print(f"nvidia-smi over {len(util)} s: utilisation mean {statistics.mean(util):.1f} %, max {max(util):.0f} %; "
          f"memory used max {max(mem):,.0f} MiB")
ckpts = sorted((run / "checkpoints").glob("ckpt_*.pt"))
print("checkpoints:", [c.name for c in ckpts])
if ckpts:
    import torch
    state = torch.load(ckpts[-1], map_location="cpu", weights_only=False)
    devs = {t.device.type for t in state["learner"]["model"].values() if hasattr(t, "device")}
    print("last checkpoint loads on the CPU; its model tensors are on:", devs)
PYEOF
cat "$OUT/summary.txt"; tail -5 "$OUT/learner.log"; tail -12 "$OUT/train.log"
