#!/bin/sh
# Style-ERD fine-tuning on a lent GPU, from the packed training set: the device machine gets the
# working tree and the carried paths, none of the mocap. Pack first (`python -m models.erd.carry
# pack .data/carry/erd.npz`, 39 MiB) and carry it with the pydantic wheels the image lacks:
#   run(command="sh models/erd/gpu_run.sh", carry=[".data/carry/erd.npz", ".data/carry/whl"], timeout_s=600)
# It trains on cuda for $MINUTES (default 8) from the committed generator with the recipe measured
# on CPU (hinge loss, transfer kept near the starting generator's, no adversarial term), and sends back the resumable checkpoint (ckpt.pt + classifier.pt: copy both into a run_dir and
# continue with `--resume`), snapshots and the log in $OUT. Extra arguments go to models.erd.train.
set -e
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .data/carry/whl/*.whl
export PYTHONPATH=/tmp/site
OUT=${OUT:-out/erd-gpu}
RUN=/tmp/erd-gpu
mkdir -p "$OUT" "$RUN"
PYTHONUNBUFFERED=1 python3 -m models.erd.train --device=cuda --threads=8 --data=.data/carry/erd.npz \
    --init_weights=models/weights/erd --minutes="${MINUTES:-8}" --batch=256 --lr_g=2e-4 --lr_d=2e-4 \
    --w_hinge=5 --w_teacher=1 --w_adv=0 --eval_every=500 --ckpt_every=250 --snapshot_every=2000 --render_every=0 \
    --run_dir="$RUN" --out_dir="$RUN/out" "$@" 2>&1 | tr '\r' '\n' | grep -v '^style-erd:\|^classifier:' || true
cp "$RUN"/ckpt.pt "$RUN"/classifier.pt "$RUN"/train.log "$OUT"/
ls "$RUN"/ckpt_*.pt 2>/dev/null | tail -4 | xargs -r -I{} cp {} "$OUT"/
ls -la "$OUT"
