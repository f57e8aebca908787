#!/bin/sh
# The container's command (under tini): seed numba's writable cache folder with the kernels the
# image compiled at build time, then become the server. Without the seed a fresh container or pod
# JIT-compiles every kernel before it is ready (~30 s on 2 cores); with it, numba loads them. A
# kernel whose cached build does not fit this CPU is simply compiled again by numba.
set -eu
seed=/opt/stylestream/numba-cache
if [ -n "${NUMBA_CACHE_DIR:-}" ] && [ -d "$seed" ]; then
    mkdir -p "$NUMBA_CACHE_DIR"
    cp -R -n "$seed/." "$NUMBA_CACHE_DIR/" 2>/dev/null || echo "entrypoint: could not seed $NUMBA_CACHE_DIR; kernels compile on first use" >&2
fi
exec stylestream serve "$@"
