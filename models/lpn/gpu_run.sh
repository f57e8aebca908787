#!/bin/sh
# LPN-FiLM closed-loop training on a lent GPU, from the packed training set: the device machine
# gets the working tree and the carried .data/carry (`python -m models.lpn.carry pack
# .data/carry/lpn.npz`, and the wheels its image lacks, `sh models/carry_wheels.sh`), none of the
# mocap. It trains for $MINUTES (default 8) from the committed network (`--warm_from`, as the CPU
# run), and sends back the last six float16 snapshots and the log in $OUT, to be chosen with
# `python -m tools.lpn_snapshots` and exported with `python -m models.lpn.train --export=...`.
# Extra arguments go to models.lpn.train (e.g. --lr=3e-4).
set -e
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .data/carry/whl/*.whl
export PYTHONPATH=/tmp/site
OUT=${OUT:-out/lpn-gpu}
mkdir -p "$OUT"
PYTHONUNBUFFERED=1 python3 -m models.lpn.train --device=cuda --threads=8 --data=.data/carry/lpn.npz \
    --warm_from=models/weights/lpn --minutes="${MINUTES:-8}" --rollout=16 --batch=1024 --lr=4e-4 \
    --eval_every=1000 --snapshot_every=2000 --snapshot_half --run_dir=/tmp/lpn-gpu --out_dir=/tmp/lpn-gpu/out \
    --no_export "$@" 2>&1 | tr '\r' '\n' | grep -v '^lpn:' || true
ls /tmp/lpn-gpu/ckpt_*.pt | tail -6 | xargs -I{} cp {} "$OUT"/
cp /tmp/lpn-gpu/train.log "$OUT"/
ls -la "$OUT"
