#!/usr/bin/env bash
# Train the embedded depth network (renders + real photos + sky head) on one GPU machine in
# ~9 minutes of wall time. Run from the repository root; needs, in outputs/carry/ (made
# here by scripts/prepare_gpu_carry.py, see docs/training.md): effnet_lite0_encoder_fp16.pt
# (ImageNet encoder), real_pool/ (scripts/build_real_pool.py: SfM depth, plane and line
# normal labels, sky labels), textures/ (facade photos); and, where pycolmap is missing, its
# wheel in .whl/. Writes to $OUT/run (default /tmp/rectsift_gpu). Extra arguments go to
# scripts/train_depth.py (later ones win).
#
# Defaults (2026-12-02): v3b's real-photo weight from the start (real_frac 0.5, w_lines 2),
# and renders with trees and clouds (tree_prob, cloud_prob 0.3), which v3b never saw: it
# labels 52 % of tree pixels planar (training.evaluate --outdoor). The v3 run of 2026-12-01
# used --real_frac 0.3 --w_lines 1 --tree_prob 0 --cloud_prob 0.
set -euo pipefail
OUT=${OUT:-/tmp/rectsift_gpu}
MINUTES=${MINUTES:-7.0}
if ! python3 -c "import pycolmap" 2>/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || true
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
DEVICE=${DEVICE:-cuda}
AMP=--amp
[ "$DEVICE" = cpu ] && AMP=
python3 scripts/train_depth.py --device "$DEVICE" $AMP --out "$OUT/run" \
  --steps 1000000 --time_budget "$MINUTES" --batch 32 --lr 6e-4 --height 192 --width 256 \
  --pool_size 1200 --pool_dir "${POOL:-/tmp/rectsift_pool}" --render_processes 15 \
  --texture_dir outputs/carry/textures --stream --render_background 5 --workers 10 \
  --sky --real_pool outputs/carry/real_pool --real_frac 0.5 --w_lines 2.0 \
  --tree_prob 0.3 --cloud_prob 0.3 \
  --encoder_weights outputs/carry/effnet_lite0_encoder_fp16.pt \
  --threads 4 --log_every 100 --ckpt_every 1000 --export_every 1000 --fp16_storage "$@"
