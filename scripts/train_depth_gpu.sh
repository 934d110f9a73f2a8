#!/usr/bin/env bash
# Train the embedded depth network (v3: renders + real photos + sky head) on one GPU machine
# in ~8 minutes of wall time. Run from the repository root; needs, in outputs/carry/ (made
# here by scripts/prepare_gpu_carry.py, see docs/training.md): effnet_lite0_encoder_fp16.pt (ImageNet encoder),
# real_pool/ (scripts/build_real_pool.py), textures/ (facade photos); and, where pycolmap
# is missing, its wheel in .whl/. Writes to $OUT/run (default /tmp/rectsift_gpu). Extra
# arguments go to scripts/train_depth.py (later ones win, e.g. --real_frac 0.5).
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
python3 scripts/train_depth.py --device cuda --amp --out "$OUT/run" \
  --steps 1000000 --time_budget "$MINUTES" --batch 32 --lr 6e-4 --height 192 --width 256 \
  --pool_size 1200 --pool_dir /tmp/rectsift_pool --render_processes 15 \
  --texture_dir outputs/carry/textures --stream --render_background 5 --workers 10 \
  --sky --real_pool outputs/carry/real_pool --real_frac 0.3 \
  --encoder_weights outputs/carry/effnet_lite0_encoder_fp16.pt \
  --threads 4 --log_every 100 --ckpt_every 1000 --export_every 1000 --fp16_storage "$@"
