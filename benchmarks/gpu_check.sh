#!/usr/bin/env bash
# The GPU path, proven on a device machine (issue 16 item 5), as one prepared call of about 7 minutes:
#     device run: command "bash benchmarks/gpu_check.sh", carry [".whl"], timeout_s 590
# The device image has Python 3.12 with torch (CUDA), numpy, numba, pyyaml and tqdm, but no Ray, gymnasium or
# wandb, and nothing can be downloaded there. Ray's wheel (79 MB) is larger than one call may carry, so .whl/
# holds a slimmed copy (benchmarks/gpu_wheels.sh makes it: the wheel without Java, RLlib, Serve, Data, Tune,
# Train and the dashboard's web client, tar.xz, 28 MB) and the small wheels Ray and gymnasium need.
#   1. benchmarks.gpu_learner: the learner alone on the GPU at paper sizes, fp32 vs bf16 (agent-steps/s it can
#      take in, peak GPU memory), se3_graphormer and se3_kattention;
#   2. the paper config (se3_graphormer, mix, 8 drones) for a few minutes: learner on the GPU (runner.precision=
#      auto: fp32 there, see swarm_appo.precision), one Ray rollout worker per remaining CPU core; agent-steps/s,
#      learner share, policy lag, system/gpu_* metrics, a checkpoint reloaded onto the CPU (map_location);
#   3. only if 2 failed: the same serially (rollout worker in the learner's process, no Ray).
#   nvidia-smi samples utilisation and memory every second throughout.
# Results land in $OUT (the device tool brings back at most 8 files): env.txt, smi.csv, learner.log, train.log,
# train_metrics.jsonl, summary.txt. Paste summary.txt and learner.log's table into benchmarks/RESULTS.md.
# Checked without a GPU (same steps on the CPU, shorter):
#     DEVICE=cpu TRAIN_S=40 LEARNER_S=2 WORKERS=1 bash benchmarks/gpu_check.sh
# runner.compile (torch.compile of the learner's forward, against the launch-bound GPU learner), e.g.:
#     ENCODERS=se3_graphormer PRECISIONS=fp32 LEARNER_COMPILE=off,default,reduce-overhead \
#     TRAIN_COMPILE=reduce-overhead TRAIN_S=150 bash benchmarks/gpu_check.sh
set -u
OUT=${OUT:-gpu_check_out}
mkdir -p "$OUT"
PY=${PYTHON:-python3}
DEVICE=${DEVICE:-cuda} TRAIN_S=${TRAIN_S:-180} LEARNER_S=${LEARNER_S:-10} WORKERS=${WORKERS:-0}
ENCODERS=${ENCODERS:-se3_graphormer,se3_kattention} PRECISIONS=${PRECISIONS:-fp32,bf16}
LEARNER_COMPILE=${LEARNER_COMPILE:-off} TRAIN_COMPILE=${TRAIN_COMPILE:-off}
LEARNER_TIMEOUT=${LEARNER_TIMEOUT:-170}  # each compiled row adds its compilation (about a minute)
RUNS=$(mktemp -d)

source benchmarks/gpu_setup.sh

{ date -u; nvidia-smi; lscpu | grep -E "Model name|^CPU\(s\)|^Flags" | cut -c1-200; free -g; df -h /dev/shm /tmp
  git log -1 --format="commit %h %s" 2>/dev/null
  $PY -c "import torch, numba, numpy, ray; print('torch', torch.__version__, 'cuda', torch.version.cuda,
torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '-',
'bf16', torch.cuda.is_available() and torch.cuda.is_bf16_supported(),
'numba', numba.__version__, 'numpy', numpy.__version__, 'ray', ray.__version__)"; } > "$OUT/env.txt" 2>&1
tail -2 "$OUT/env.txt"
nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used,power.draw --format=csv -l 1 > "$OUT/smi.csv" 2>&1 &
SMI=$!

echo "== 1. learner alone (paper sizes, fp32 vs bf16) $(date -u +%T)"
# runner.envs_per_worker=4: the batch (4096 agent steps, one fragment) is collected on one CPU core 4x sooner
timeout $LEARNER_TIMEOUT $PY -m benchmarks.gpu_learner --device $DEVICE --seconds $LEARNER_S --encoders $ENCODERS \
    --precisions $PRECISIONS --compile $LEARNER_COMPILE --no-append runner.envs_per_worker=4 \
    > "$OUT/learner.log" 2>&1
echo "rc=$?" >> "$OUT/learner.log"; tail -6 "$OUT/learner.log"

train() {  # $1: run name, then overrides
    local name=$1; shift
    echo "== $name $(date -u +%T)" >> "$OUT/train.log"
    timeout $((TRAIN_S + 180)) $PY -m launchers.local --config configs/paper.yaml runner.device=$DEVICE \
        runner.precision=auto runner.compile=$TRAIN_COMPILE runner.time_limit_s=$TRAIN_S runner.checkpoint_every_s=60 \
        runner.final_eval_episodes=2 wandb.mode=disabled runner.run_dir="$RUNS" runner.name=$name "$@" \
        --no-progress >> "$OUT/train.log" 2>&1
    local rc=$?
    echo "rc=$rc" >> "$OUT/train.log"
    cp "$RUNS/$name/metrics.jsonl" "$OUT/${name}_metrics.jsonl" 2>/dev/null
    return $rc
}
echo "== 2. paper config, Ray rollout workers on the CPUs, learner on the GPU $(date -u +%T)"
train paper_gpu_ray runner.num_workers=$WORKERS; RAY_RC=$?
if [ $RAY_RC -ne 0 ]; then
    echo "== 3. Ray run failed (rc $RAY_RC): the same serially $(date -u +%T)"
    TRAIN_S=$((TRAIN_S * 2 / 3)) train paper_gpu_serial runner.serial=true runner.num_workers=1
fi
kill $SMI 2>/dev/null

for run in "$RUNS"/paper_gpu_*; do
$PY - "$run" "$OUT/smi.csv" <<'PYEOF'
import json, statistics, sys
from pathlib import Path
run, smi = Path(sys.argv[1]), Path(sys.argv[2])
print(f"--- {run.name}")
recs = [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()] if (run / "metrics.jsonl").exists() else []
late = [r for r in recs if "perf/agent_steps_per_s" in r]
late = late[len(late) // 3:]  # past the start-up
def med(k):
    v = [r[k] for r in late if k in r]
    return f"{statistics.median(v):,.3f}" if v else "-"
print("training records:", len(recs), "last global_step:", recs[-1].get("global_step") if recs else "-")
for k in ("perf/agent_steps_per_s", "perf/learner_samples_per_s", "perf/learner_share", "perf/inference_share",
          "perf/env_share", "perf/startup_s", "lag/min", "lag/mean", "lag/max", "system/gpu_mem_mb",
          "system/gpu_max_mem_mb", "system/gpu_util", "system/max_rss_mb"):
    print(f"median over the last 2/3 of records, {k}: {med(k)}")
evals = {k: v for r in recs for k, v in r.items() if k.startswith(("eval/", "eval_random/"))}
print("final evaluation:", {k: round(v, 3) for k, v in sorted(evals.items()) if isinstance(v, (int, float))})
rows = [l.split(", ") for l in smi.read_text().splitlines()[1:] if l.count(",") >= 3]
util = [float(r[1].split()[0]) for r in rows if r[1].split()[0].replace(".", "").isdigit()]
mem = [float(r[2].split()[0]) for r in rows if r[2].split()[0].isdigit()]
if util:
    print(f"nvidia-smi over the whole script, {len(util)} s: utilisation mean {statistics.mean(util):.1f} %, "
          f"max {max(util):.0f} %; memory used max {max(mem):,.0f} MiB")
ckpts = sorted((run / "checkpoints").glob("ckpt_*.pt"))
print("checkpoints:", [c.name for c in ckpts])
if ckpts:
    from swarm_appo.checkpoint import load_checkpoint
    state = load_checkpoint(ckpts[-1], map_location="cpu")
    devs = {t.device.type for t in state["learner"]["model"].values() if hasattr(t, "device")}
    print("last checkpoint loads on the CPU; its model tensors are on:", devs)
PYEOF
done > "$OUT/summary.txt" 2>&1
cat "$OUT/summary.txt"; grep -E "^\|" "$OUT/learner.log"; tail -25 "$OUT/train.log"
