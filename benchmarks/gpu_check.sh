#!/usr/bin/env bash
# The GPU checks, for a lent GPU machine (see the README's performance section), in two calls because one call carries
# at most 64 MiB:
#   bash benchmarks/gpu_check.sh tests   # the suite on cuda_ad_rgb, the training loop's throughput (frozen against
#                                        # traced, GPU utilization, profile), ours on mi_objects/colmap to 7k
#   bash benchmarks/gpu_check.sh peers   # the rasterizer against gsplat, gsplat's simple_trainer recipe to 7k
# Run from the project's root on the GPU machine. Here, first:
#   bash ../shared/tools/gpu/prepare.sh --gsplat        # .gpu/: Mitsuba/Dr.Jit runtime (+ gsplat's wheel)
#   mkdir -p .gpu/data/mi_objects && cp -r ../shared/data/mi_objects/colmap .gpu/data/mi_objects/
#   for "tests": pycolmap's wheel unpacked and packed again as .gpu/pycolmap.tar.xz (xz: 38 MB -> 20 MB), and
#   .gpu/whl/ holding pypng's wheel; move gsplat's wheel out of .gpu/ (it would not fit beside them)
#   for "peers": gsplat's wheel in .gpu/ (prepare.sh --gsplat), pycolmap.tar.xz moved out
# viser (the viewer's tests) does not fit beside pycolmap: those tests fail there for want of it. Every step has its
# own time limit, so that a slow step cannot eat the others' results; logs and tables go to $OUT (default
# /tmp/gpu_check) and the tables are repeated at the end.
set -u
part=${1:?usage: gpu_check.sh tests|peers}
OUT=${OUT:-/tmp/gpu_check}
mkdir -p "$OUT"
T0=$(date +%s)
say() { echo "[$(($(date +%s) - T0)) s] $*" | tee -a "$OUT/setup.log"; }

nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm,power.limit --format=csv | tee -a "$OUT/setup.log"
source .gpu/bootstrap.sh
site=${MIGS_SITE:-/tmp/mi-gs-site}
data() { mkdir -p ../shared && ln -sfn "$PWD/.gpu/data" ../shared/data; }

if [ "$part" = peers ]; then
    say "gsplat's CUDA build"
    timeout 300 python3 -c "from gsplat.cuda._backend import _C; print('gsplat built', _C is not None)" \
        >> "$OUT/setup.log" 2>&1
    data
    say "rasterizer against gsplat"
    timeout "${RENDER_S:-90}" python3 benchmarks/render.py --variant cuda_ad_rgb --peers gsplat --repeats 7 --profile \
        --cases 10000:256 100000:800 1000000:1600 > "$OUT/render.md" 2>&1
    say "gsplat's recipe, mi_objects/colmap, 7k of the 30k schedule"
    timeout "${GSPLAT_S:-120}" python3 benchmarks/gsplat_train.py mi_objects_colmap --milestones 7000 --schedule 30000 \
        > "$OUT/train_gsplat.md" 2>&1
    say done
    for f in render train_gsplat; do echo "== $f"; grep -E '^\| [0-9g]|rror' "$OUT/$f.md" | tail -n 12; done
    exit 0
fi

[ -f .gpu/pycolmap.tar.xz ] && tar -xJf .gpu/pycolmap.tar.xz -C "$site"
[ -d .gpu/whl ] && python3 -m pip install -q --no-index --no-deps --no-compile --target "$site" .gpu/whl/*.whl
py=$(python3 -c 'import sys; print(sys.executable)')       # the tests start the installed mi-gs
printf '#!%s\nimport sys\nfrom mi_gaussians.cli import main\nsys.exit(main())\n' "$py" > "$(dirname "$py")/mi-gs"
chmod +x "$(dirname "$py")/mi-gs"

data
say "training-loop throughput"
S="benchmarks/train_speed.py --variant cuda_ad_rgb --cases 200:50000 mi_objects_colmap --iterations 40 --rounds 3"
timeout "${SPEED_S:-90}" python3 $S --busy 600 --profile > "$OUT/train_speed.md" 2>&1 || \
    timeout 60 python3 $S --loops traced --busy 300 >> "$OUT/train_speed.md" 2>&1
say "ours, mi_objects/colmap, 7k of the 30k schedule"
timeout "${OURS_S:-120}" python3 benchmarks/train.py mi_objects_colmap --milestones 7000 --schedule 30000 \
    --variant cuda_ad_rgb --out /tmp/ours > "$OUT/train_ours.md" 2>&1
rm -f ../shared/data             # (the tests take ../shared/data as holding every shared dataset)
say "the test suite on cuda_ad_rgb"
timeout -k 15 -s INT "${PYTEST_S:-240}" python3 -m pytest -v -n 12 --variant cuda_ad_rgb -p no:cacheprovider \
    -o console_output_style=classic -rfEs > "$OUT/pytest.log" 2>&1
say "pytest exit $?"
pkill -9 -f 'pytest|execnet|mi_gaussians.cli' 2>/dev/null
echo "== speed"; grep -E '^\||rror|fault' "$OUT/train_speed.md" | head -n 30
echo "== ours"; grep -E '^\| mi|rror|fault' "$OUT/train_ours.md"
echo "== suite"; grep -E "^(FAILED|ERROR)|passed|failed" "$OUT/pytest.log" | tail -n 40
