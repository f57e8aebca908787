#!/bin/sh
# Re-fetches the vendored three.js from the npm registry (`make viewer-vendor`), so the viewer
# needs no CDN and no build step at run time. `npm pack` checks the tarball against the registry's
# sha512 integrity; we record it in three/VERSION. Only the files the page imports are kept:
# the minified core and WebGL renderer modules and OrbitControls (which imports "three", resolved
# by the import map in index.html).
#
# 0.185.1 is pinned because it is the newest release that still ships minified builds (0.186 and
# later publish only un-minified modules, 2.1 MB instead of 0.75 MB). Override with THREE_VERSION=.
set -eu
version="${THREE_VERSION:-0.185.1}"
here="$(cd "$(dirname "$0")" && pwd)"
dest="$here/three"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

(cd "$tmp" && npm pack --silent "three@$version" >/dev/null)
integrity="$(npm view "three@$version" dist.integrity)"
tarball="$tmp/three-$version.tgz"
actual="sha512-$(openssl dgst -sha512 -binary "$tarball" | openssl base64 -A)"
[ "$actual" = "$integrity" ] || { echo "three@$version: tarball $actual does not match the registry's $integrity" >&2; exit 1; }
tar xzf "$tarball" -C "$tmp"
pkg="$tmp/package"
for f in build/three.module.min.js build/three.core.min.js; do
  [ -f "$pkg/$f" ] || { echo "three@$version has no $f (minified builds were dropped in 0.186)" >&2; exit 1; }
done

rm -rf "$dest" && mkdir -p "$dest/addons/controls"  # addons/ mirrors the package's "three/addons/*" export
cp "$pkg/build/three.module.min.js" "$pkg/build/three.core.min.js" "$pkg/LICENSE" "$dest/"
cp "$pkg/examples/jsm/controls/OrbitControls.js" "$dest/addons/controls/"
cat > "$dest/VERSION" <<INFO
three@$version from the npm registry (https://registry.npmjs.org/three/-/three-$version.tgz)
integrity $integrity
files: build/three.module.min.js, build/three.core.min.js, LICENSE (MIT); examples/jsm/controls/OrbitControls.js as addons/controls/
fetched by clients/viewer/vendor/fetch-three.sh (make viewer-vendor); do not edit these files by hand
INFO
du -sh "$dest"
