#!/bin/sh
# An image FROM scratch holding the `formation` binary (stripped) and the
# shared libraries `ldd` lists: for machines that cannot pull a base image
# from a registry. Every node runs from it (`formation node agent …`).
#
#   deploy/scratch-image.sh TAG [BINARY]     (default BINARY: target/release/formation)
#
# Needs podman (or docker: set ENGINE=docker), ldd and strip.
set -eu
tag=${1:?usage: deploy/scratch-image.sh TAG [BINARY]}
bin=${2:-target/release/formation}
engine=${ENGINE:-podman}
[ -x "$bin" ] || { echo "scratch-image: no executable $bin (cargo build --release first)" >&2; exit 2; }
ctx=$(mktemp -d)
trap 'rm -rf "$ctx"' EXIT
cp "$bin" "$ctx/formation"
strip "$ctx/formation" 2>/dev/null || true
for lib in $(ldd "$bin" | grep -o '/[^ ]*'); do
    mkdir -p "$ctx$(dirname "$lib")"
    cp -L "$lib" "$ctx$lib"
done
mkdir -p "$ctx/tmp" "$ctx/out" "$ctx/scenarios"
chmod 1777 "$ctx/tmp"
cat > "$ctx/Containerfile" <<'END'
FROM scratch
COPY . /
ENTRYPOINT ["/formation"]
END
"$engine" build -q -t "$tag" -f "$ctx/Containerfile" "$ctx"
