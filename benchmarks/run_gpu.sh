#!/usr/bin/env bash
# The GPU measurements behind benchmarks/RESULTS.md, as they were run (warpsim installed, one CUDA
# device). `bash benchmarks/run_gpu.sh core` needs only warp-lang; `usd` also needs usd-core,
# viser and ray (the render, viewer and sweep figures read or write caches).
set -u
cd "$(dirname "$0")"
D=${DEVICE:-cuda:0}
quiet() { grep -v -E "^Module |took [0-9.]+ ms|^Warp [0-9]|CUDA Toolkit|Devices:|\"cpu\" |\"cuda:[0-9]\"|Kernel cache|/\.cache/warp"; }
run() { echo; echo "### $*"; timeout "${T:-240}" "$@" 2>&1 | quiet; }
case "${1:-core}" in
  core)
    run python3 roofline.py --device "$D"
    run python3 roofline.py --device "$D" --only smoke --smoke-graph
    run python3 bench_worlds.py --device "$D" --worlds 1024
    T=400 run python3 bench_worlds.py --device "$D" --worlds 10000 --paths shared,block,tiled --sequential 4 --builder-worlds 2
    T=500 run python3 bench_worlds.py --device "$D" --worlds 100000 --paths shared,block --sequential 4 --builder-worlds 0
    run python3 bench_donuts.py --device "$D" --settle 3000 --steps 500
    T=600 run python3 bench_donuts.py --device "$D" --count 1000 --settle 3000 --steps 200
    run python3 bench_differentiable.py --device "$D" --dims 64 128 256 --steps 1000
    ;;
  usd)
    run python3 bench_render.py --device "$D" --case liquid --points 1000000
    run python3 bench_render.py --device "$D" --case teapot
    run python3 bench_viewer.py --device "$D" --scene dam_break --set spacing=0.00493 --set surface=false --max-points 200000
    run python3 bench_viewer.py --device cpu
    ;;
  sweep)  # issue 21 on one GPU: the same sweep in one process and as Ray tasks of 256 worlds
    V="--vary stiffness=20:60 --vary restitution=0.2:0.8 --sample lhs --seed 1 --frames ${FRAMES:-30} --no-progress ${SWEEP_EXTRA:-}"
    rm -rf /tmp/sweep1 /tmp/sweep2
    for mode in 1 2; do
      extra=""; [ "$mode" = 2 ] && extra="--ray --batch-size 256"
      t0=$(date +%s.%N)
      T=590 run python3 -m warpsim sweep teapot --device "$D" --worlds "${WORLDS:-2048}" $V $extra --out /tmp/sweep$mode/teapots.usda
      echo "sweep mode $mode wall $(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN{printf "%.1f", b - a}') s"
    done
    cmp /tmp/sweep1/teapots.csv /tmp/sweep2/teapots.csv && echo "tables identical"
    python3 -c "import sys; from warpsim.usd.validate import validate_cache as v; print('validation errors:', [v(p) for p in sys.argv[1:]])" /tmp/sweep1/teapots.usda /tmp/sweep2/teapots.usda
    ;;
  vbd)  # issue 53: the donut heap by vertex block descent (step, contact share, frames/s, graph, depth, crossings)
    (cd .. && run python3 -m pytest -q tests/test_vbd.py -k allocates)  # CUDA graph replay gives the eager bits
    T=590 run python3 bench_donuts.py --integrator vbd --device "$D" --dt 0.0041666667 --settle 2400 --steps 200 \
      --reference-integrator fast_mass_spring --set solver_chebyshev=true --solver-iterations 12
    T=590 run python3 bench_donuts.py --integrator vbd --device "$D" --count 100 --dt 0.0041666667 --settle 2400 --steps 100
    T=590 run python3 bench_donuts.py --integrator vbd --device "$D" --count 1000 --dt 0.0041666667 --settle 1200 --steps 40
    T=590 run python3 check_heap.py --device "$D" --count 12 --integrator vbd --dt 1/240 --frames 600 --check-every 10
    # VBD at 1/60 s against fast mass-spring at the 1/240 s it needs: time per simulated second
    T=590 run python3 bench_donuts.py --integrator vbd --device "$D" --dt 0.0166666667 --settle 240 --steps 60 \
      --reference-integrator fast_mass_spring --reference-dt 0.0041666667 \
      --set solver_chebyshev=true --solver-iterations 12
    # Newton's SolverVBD on the same heap (benchmarks/prepare_newton.sh: .gpu3/newton.tgz unpacked onto PYTHONPATH)
    T=590 run python3 bench_donuts.py --integrator vbd --device "$D" --dt 0.0041666667 --settle 900 --steps 100 \
      --no-oracles --reference-integrator newton_vbd
    T=590 run python3 bench_donuts.py --integrator vbd --device "$D" --dt 0.0041666667 --settle 0 --steps 600 \
      --reference-integrator newton_vbd --newton-from-build
    ;;
  occupancy)  # issue 29: record cost, bytes and query time at 10,000 teapots x 120 frames
    T=590 run python3 bench_occupancy.py --device "$D" --worlds 10000 --frames 120 --sweep-frames ${SWEEP_FRAMES:-4} --repeat 1
    ;;
esac
