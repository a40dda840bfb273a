#!/usr/bin/env bash
# Newton 1.8.0 (the reference VBD of `bench_donuts.py --reference-integrator newton_vbd`) for a GPU machine with no
# package index: its pure-Python wheel without its tests and example assets (8.3 MB -> about 4 MB), in .gpu3/ (ignored
# by git) for a call of its own after Warp's two pieces (../shared/gpu/README.md). There:
#     mkdir -p /tmp/site && tar xzf .gpu3/newton.tgz -C /tmp/site   # PYTHONPATH=/tmp/site as for Warp
set -euo pipefail
cd "$(dirname "$0")/.."
work=$(mktemp -d)
python3 -m pip download -q --no-deps --only-binary=:all: -d "$work" newton==1.8.0
python3 -m zipfile -e "$work"/newton-1.8.0-py3-none-any.whl "$work/site"
rm -rf "$work/site/newton/tests" "$work/site/newton/examples/assets"
mkdir -p .gpu3
tar czf .gpu3/newton.tgz -C "$work/site" newton newton-1.8.0.dist-info
rm -rf "$work"
ls -la .gpu3/newton.tgz
