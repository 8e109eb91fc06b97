#!/usr/bin/env bash
# Render a training set with Mitsuba's cuda_ad_rgb variant and train the offline networks on one CUDA GPU, in
# a fixed time.
#
# usage: [NETS="rae flnr kpn"] [INIT_<NET>=CKPT] [LR=0.001] [CLIP=0] \
#          models/train/accelerator.sh OUT RENDER_SECONDS TRAIN_MINUTES [WORKERS]
#
# 1. Renders, for at most RENDER_SECONDS, WORKERS `python -m models.data dataset` processes side by side on
#    the one GPU: worker 0 renders make data's training seeds (2-5), worker k > 0 the seeds 7 + 4(k-1) ..
#    10 + 4(k-1), every library scene at each seed in turn (128x128, 8 frames, 2/4/8 spp, 1024-spp
#    references). Seeds 0 (benchmark), 1 (hard cases) and 6 (validation) are never trained on. A sequence
#    cut off by the time limit has no sequence.json and is not used. The validation set (seed 6, one
#    sequence per scene, as make data's) renders beside them.
# 2. Trains one run per network in $NETS (default: all of them), side by side on the one GPU (the CPU
#    threads shared out), TRAIN_MINUTES each: OUT/rae (with the hidden-state warp, as the shipped weights),
#    OUT/flnr, OUT/kpn (dual motion); with INIT_<NET> set (INIT_rae=CKPT), a fine-tune of that checkpoint
#    (`--init`). Peak learning rate LR; CLIP: --clip-grad (0: none); TONE_EPS: --tone-eps (unset: the loss's default).
#    `python -m export NET OUT/NET/best.pt OUT/NET.onnx` exports each.
#
# Needs: a CUDA GPU, torch with CUDA, mitsuba (cuda_ad_rgb), OpenEXR, numba, tqdm, matplotlib (or DEVICE=cpu
# and MCDENOISE_MI_VARIANT=llvm_ad_rgb or scalar_rgb, slowly).
# Logs: OUT/logs/. Time it took on an H100: models/weights/rae.json (`machine`, `training_seconds`).
# Exit status: 1 if any network's training or export failed (its log says why), else 0.
set -u
trap 'kill $(jobs -p) 2>/dev/null' INT TERM  # an interrupted run leaves no renderer or trainer on the GPU
out=${1:?OUT}
render_s=${2:?RENDER_SECONDS}
train_min=${3:?TRAIN_MINUTES}
workers=${4:-8}
py=${PYTHON:-python3}
device=${DEVICE:-cuda}  # DEVICE=cpu: the same steps without a GPU (slow; for trying the script)
export MCDENOISE_MI_VARIANT=${MCDENOISE_MI_VARIANT:-cuda_ad_rgb}
mkdir -p "$out/logs"

timeout "$render_s" $py -m models.data dataset --out "$out/data/val" --sequences-per-scene 1 --first-seed 6 \
  >"$out/logs/render_val.log" 2>&1 &
for k in $(seq 0 $((workers - 1))); do
  first=$((k == 0 ? 2 : 7 + 4 * (k - 1)))
  timeout "$render_s" $py -m models.data dataset --out "$out/data/train" --sequences-per-scene 4 \
    --first-seed "$first" >"$out/logs/render_$k.log" 2>&1 &
done
wait
echo "rendered: $(ls "$out"/data/train/*/sequence.json 2>/dev/null | wc -l) training and" \
  "$(ls "$out"/data/val/*/sequence.json 2>/dev/null | wc -l) validation sequences in ${render_s} s or less"

nets=(${NETS:-rae flnr kpn})
threads=$(( $(nproc) / ${#nets[@]} > 0 ? $(nproc) / ${#nets[@]} : 1 ))
common=(--data "$out/data/train" --val "$out/data/val" --device "$device" --steps 1000000 --minutes "$train_min"
        --batch 16 --lr "${LR:-0.001}" --warmup 200 --seed 0 --val-every 250 --log-every 50 --checkpoint-every 250
        --ema 0.999 --threads "$threads" --clip-grad "${CLIP:-0}" ${TONE_EPS:+--tone-eps "$TONE_EPS"})
# kpn: its occlusion loss term joins at a share of --steps (1e6 here, never reached in TRAIN_MINUTES): step 1000
declare -A extra=([rae]="--warp" [flnr]="" [kpn]="--motion dual --occlusion-from 0.001")
pids=()
for net in "${nets[@]}"; do
  init=()
  start="INIT_$net"
  if [ -n "${!start:-}" ]; then init=(--init "${!start}"); fi
  (
    # shellcheck disable=SC2086  # the extra options are words
    $py -m models.train "$net" "${common[@]}" ${extra[$net]} "${init[@]}" --out "$out/$net" \
      >"$out/logs/train_$net.log" 2>&1 &&
      $py -m export "$net" "$out/$net/best.pt" "$out/$net.onnx" >>"$out/logs/train_$net.log" 2>&1
  ) &
  pids+=($!)
done
status=0
for pid in "${pids[@]}"; do
  wait "$pid" || status=1
done
exit $status
