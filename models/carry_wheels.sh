#!/bin/sh
# The wheels a lent GPU machine's image lacks (its Python is 3.12; it reaches no index), for the
# device runs (models/lpn/gpu_run.sh, models/erd/gpu_run.sh): downloaded here into the carried
# .data/carry/whl, pure-Python or cp312 manylinux builds only.
set -e
DEST=${1:-.data/carry/whl}
mkdir -p "$DEST"
python3 -m pip download -q --dest "$DEST" --only-binary=:all: --python-version 3.12 \
    --platform manylinux2014_x86_64 --implementation cp \
    tqdm pydantic pydantic-settings
ls "$DEST"
