#!/usr/bin/env bash
# build-image.sh - build the stylestream image with podman (or docker) from the repository root.
#
#   bash docker/build-image.sh [extra build args...]     IMAGE=stylestream:dev to change the tag
#
# Stages the torch CPU wheel into the git-ignored docker/wheels/ first (hard link when on the same
# filesystem), looked up in TORCH_WHEEL_DIRS (default: pip's find-links, then /opt/wheels), and
# the kernels numba compiled in this checkout into docker/numba-seed/ (docker/numba_seed.py). No
# registry is needed: the base image must already be local (../shared/tools/container-base.sh).
set -Eeuo pipefail
cd "$(dirname "$0")/.."
IMAGE=${IMAGE:-stylestream:latest}
ENGINE=${ENGINE:-$(command -v podman || command -v docker || true)}
[ -n "$ENGINE" ] || { echo "build-image: neither podman nor docker found" >&2; exit 1; }
WHEEL_GLOB='torch-2.13.0+cpu-cp311-cp311-*linux*_x86_64.whl'

mkdir -p docker/wheels
if ! compgen -G "docker/wheels/$WHEEL_GLOB" >/dev/null; then
  dirs=${TORCH_WHEEL_DIRS:-"$(python3 -m pip config get global.find-links 2>/dev/null || true) /opt/wheels"}
  for dir in $dirs; do
    for wheel in "$dir"/$WHEEL_GLOB; do
      [ -f "$wheel" ] || continue
      ln -f "$wheel" docker/wheels/ 2>/dev/null || cp "$wheel" docker/wheels/
      echo "build-image: staged $wheel"
      break 2
    done
  done
fi
compgen -G "docker/wheels/$WHEEL_GLOB" >/dev/null || {
  echo "build-image: no $WHEEL_GLOB in docker/wheels/ or in: ${dirs:-}" >&2
  echo "  put the torch 2.13.0 CPU wheel there (e.g. pip download from the PyTorch CPU index)" >&2; exit 1; }

# numba's kernels as this checkout compiled them (docker/numba_seed.py): the image's warm-up loads
# those whose source matches instead of compiling them (minutes on two cores); none staged is fine
python3 docker/numba_seed.py stage docker/numba-seed || { rm -rf docker/numba-seed; mkdir -p docker/numba-seed; }

# podman: docker format (OCI has no HEALTHCHECK), --pull=never (no registry is reachable)
flags=(); [[ $(basename "$ENGINE") == podman ]] && flags=(--format docker --pull=never)
exec "$ENGINE" build "${flags[@]}" -t "$IMAGE" -f docker/Dockerfile "$@" .
