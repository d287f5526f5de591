#!/usr/bin/env bash
# The GPU figures of docs/performance.md in one command, about 8 minutes on an H100/H200:
#   bash experiments/gpu_check.sh [OUT]        (default: $OUT, else outputs/gpu_check)
# Prints, and writes to OUT/<step>.txt: the environment; bf16 correctness (one training step in
# bf16-mixed and float32 from the same weights); the training step of the paper and paper_plus
# presets at batch 2 in bf16-mixed (channels-last, with and without torch.compile, with
# activation checkpointing for the paper preset's memory); inference latency at batch 1 and 8
# (eager, compiled, ONNX Runtime) of the paper's net and of the light one; and a 200-step training of experiment=paper_plus on a small
# rendered 480 px dataset with its loss curve. OUT/summary.txt lists each step's exit status and
# seconds. Without CUDA it runs the same steps at a tiny size (32 px, a few steps, nothing
# compiled: inductor takes minutes on this CPU) and says so.
# PYTHON names the interpreter (default: .venv/bin/python, else python).
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:-${OUT:-outputs/gpu_check}}
mkdir -p "$out"
py=${PYTHON:-$([ -x .venv/bin/python ] && echo .venv/bin/python || echo python)}
summary="$out/summary.txt"
: > "$summary"

if "$py" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)"; then
  tiny=false device=cuda
  presets=(paper paper_plus) size=() infer_size=() steps=(--steps 20 --warmup 5) batches=(1 8)
  scenes=8 resolution=480 train_steps=200 limit=240 trainer=gpu
else
  tiny=true device=cpu
  presets=(quickstart) size=(--resolution 32) infer_size=(--set data.resolution=32)
  steps=(--steps 2 --warmup 1) batches=(1 2)
  scenes=4 resolution=32 train_steps=3 limit=300 trainer=cpu
  echo "no CUDA device: every step at a tiny size on the CPU (32 px, a few steps); no GPU figure" \
    | tee "$out/tiny.txt"
fi

# step NAME COMMAND...: run it under the time limit, its output to the terminal and NAME.txt
step() {
  local name=$1; shift
  echo "== $name: $*"
  local t0=$SECONDS
  timeout "$limit" "$@" 2>&1 | tee "$out/$name.txt"
  local rc=${PIPESTATUS[0]}
  echo "$name rc=$rc $((SECONDS - t0)) s" | tee -a "$summary"
}

step environment "$py" -c "
import platform, subprocess, torch
print('date', __import__('datetime').datetime.now().isoformat(timespec='seconds'))
print('host', platform.node(), platform.platform())
print('torch', torch.__version__, 'cuda', torch.version.cuda, 'cudnn', torch.backends.cudnn.version())
if torch.cuda.is_available():
    p = torch.cuda.get_device_properties(0)
    print('gpu', p.name, f'{p.total_memory / 2**30:.1f} GiB', 'bf16', torch.cuda.is_bf16_supported())
    print(subprocess.run(['nvidia-smi', '--query-gpu=name,driver_version,memory.total',
                          '--format=csv'], capture_output=True, text=True).stdout)
else:
    print('no CUDA device;', torch.get_num_threads(), 'CPU threads')
"

step bf16 "$py" experiments/bf16_check.py --preset "${presets[-1]}" --device "$device" \
  --batch 2 "${size[@]}"

for preset in "${presets[@]}"; do
  common=(--preset "$preset" --batch 2 --device "$device" --precision bf16-mixed
          --channels-last "${size[@]}" "${steps[@]}")
  [ "$device" = cuda ] && common+=(--cudnn-benchmark)
  step "train_${preset}" "$py" experiments/bench_train.py "${common[@]}"
  if [ "$tiny" = false ]; then  # inductor takes minutes on the CPU (and fails on bf16 there)
    step "train_${preset}_compiled" "$py" experiments/bench_train.py "${common[@]}" --compile \
      --compile-mode default
  fi
  if [ "$preset" = paper ]; then  # 113.7 M parameters: the memory target needs checkpointing?
    step "train_${preset}_checkpointing" "$py" experiments/bench_train.py "${common[@]}" \
      --checkpointing
  fi
done

infer_precision=$([ "$device" = cuda ] && echo bf16 || echo 32)
runtimes=(eager)
[ "$tiny" = false ] && runtimes+=(compiled)
# ONNX Runtime where it runs on this device
"$py" -c "import sys, onnxruntime as o; sys.exit('$device' == 'cuda' and
  'CUDAExecutionProvider' not in o.get_available_providers())" && runtimes+=(onnx)
step infer "$py" experiments/bench_infer.py --preset "${presets[0]}" --device "$device" \
  --precision "$infer_precision" --batches "${batches[@]}" --runtimes "${runtimes[@]}" \
  --repeats "$([ "$tiny" = true ] && echo 2 || echo 20)" "${infer_size[@]}"
# the light net for in-line inspection (docs/deploy.md), with the phase head, at 480 px
step infer_lite "$py" experiments/bench_infer.py --preset mini --model odmvnet_lite \
  --device "$device" --precision "$infer_precision" --batches "${batches[@]}" \
  --runtimes "${runtimes[@]}" --repeats "$([ "$tiny" = true ] && echo 2 || echo 20)" \
  --set head=phase "data.resolution=$resolution"

data="$out/data-${resolution}px"
step render "$py" -m odmv.simulate out="$data" scenes="$scenes" resolution="$resolution" \
  images=training seed=5 splits="{train: 0.5, val: 0.25, test: 0.25}" progress=false
step train_steps "$py" -m odmv.train experiment=paper_plus trainer="$trainer" data=exr \
  root="$data" data.resolution="$resolution" +trainer.max_steps="$train_steps" \
  trainer.max_epochs=-1 trainer.log_every_n_steps=1 trainer.enable_progress_bar=false \
  trainer.enable_model_summary=false data.progress=false data.num_workers=2 \
  "paths.output_dir=$out/train_steps" test=false log_images=0 \
  $([ "$tiny" = true ] && echo "model.net.base_width=4 model.net.blocks=1")
step loss_curve "$py" -c "
import csv, sys
rows = [r for r in csv.DictReader(open('$out/train_steps/csv/metrics.csv')) if r.get('train/loss')]
if not rows:
    sys.exit('no train/loss in the CSV log')
every = max(1, len(rows) // 20)
for r in rows[::every] + ([rows[-1]] if (len(rows) - 1) % every else []):
    print(f\"step {int(r['step']):4d}  loss {float(r['train/loss']):.4f}\")
"
echo "== done: $summary"
cat "$summary"
! grep -qv " rc=0 " "$summary"
