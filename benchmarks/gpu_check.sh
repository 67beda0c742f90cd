#!/usr/bin/env bash
# The GPU checks in one call (a lent machine's time is short): the test suite on cuda_ad_rgb, the training-loop
# throughput with the GPU's utilization, the rasterizer against gsplat, and a 7k training run of ours against gsplat's
# simple_trainer recipe. Run from the project's root on the GPU machine, after
#     bash ../shared/tools/gpu/prepare.sh --gsplat      # here: .gpu/ (Mitsuba/Dr.Jit runtime + gsplat)
# with .gpu/whl/ holding the wheels that machine lacks (viser and its needs, pypng) and .gpu/data/mi_objects/colmap a
# copy of the dataset. Every step has its own time limit, so that one slow step cannot eat the others' results; logs
# and tables go to $OUT (default /tmp/gpu_check), the tables are repeated at the end.
set -u
OUT=${OUT:-/tmp/gpu_check}
mkdir -p "$OUT"
T0=$(date +%s)
say() { echo "[$(($(date +%s) - T0)) s] $*" | tee -a "$OUT/setup.log"; }

nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm,temperature.gpu,power.limit \
    --format=csv | tee -a "$OUT/setup.log"
source .gpu/bootstrap.sh
say "gsplat's CUDA build (background, while the tests run)"
(MAX_JOBS=8 timeout 300 python3 -c "from gsplat.cuda._backend import _C; print('gsplat built', _C is not None)" \
    >> "$OUT/setup.log" 2>&1) &
build=$!
python3 -m pip install -q --no-index --no-deps --no-compile --target "${MIGS_SITE:-/tmp/mi-gs-site}" .gpu/whl/*.whl \
    >> "$OUT/setup.log" 2>&1
py=$(python3 -c 'import sys; print(sys.executable)')
printf '#!%s\nimport sys\nfrom mi_gaussians.cli import main\nsys.exit(main())\n' "$py" > "$(dirname "$py")/mi-gs"
chmod +x "$(dirname "$py")/mi-gs"
python3 -c 'import mitsuba as mi, drjit as dr, torch; mi.set_variant("cuda_ad_rgb"); import mi_gaussians
print("Mitsuba", mi.__version__, "Dr.Jit", dr.__version__, "torch", torch.__version__, torch.cuda.get_device_name())' \
    2>&1 | tee -a "$OUT/setup.log"

say "the test suite on cuda_ad_rgb"
timeout -k 15 -s INT "${PYTEST_S:-170}" python3 -m pytest -v -n 8 --variant cuda_ad_rgb -p no:cacheprovider \
    -o console_output_style=classic -rfE --durations=10 > "$OUT/pytest.log" 2>&1
rc=$?
say "pytest exit $rc: $(grep -cE '(PASSED|XPASS) ' "$OUT/pytest.log") passed, $(grep -cE '(FAILED|ERROR) ' \
    "$OUT/pytest.log") failed lines, $(grep -c 'SKIPPED ' "$OUT/pytest.log") skipped"
pkill -9 -f 'pytest|execnet|mi_gaussians.cli' 2>/dev/null
wait $build
say "gsplat build done"

mkdir -p ../shared && ln -sfn "$PWD/.gpu/data" ../shared/data
nvidia-smi dmon -s u -o T -d 1 > "$OUT/dmon.txt" 2>&1 &
dmon=$!
say "training-loop throughput"
timeout "${SPEED_S:-80}" python3 benchmarks/train_speed.py --variant cuda_ad_rgb --cases 200:50000 mi_objects_colmap \
    --iterations 40 --rounds 3 --busy 600 --profile > "$OUT/train_speed.md" 2>&1
say "rasterizer against gsplat"
timeout "${RENDER_S:-70}" python3 benchmarks/render.py --variant cuda_ad_rgb --peers gsplat --repeats 7 --profile \
    --cases 10000:256 100000:800 1000000:1600 > "$OUT/render.md" 2>&1
say "ours, mi_objects/colmap, 7k of the 30k schedule"
timeout "${OURS_S:-140}" python3 benchmarks/train.py mi_objects_colmap --milestones 7000 --schedule 30000 \
    --variant cuda_ad_rgb --out /tmp/ours > "$OUT/train_ours.md" 2>&1
say "gsplat's recipe, the same"
timeout "${GSPLAT_S:-100}" python3 benchmarks/gsplat_train.py mi_objects_colmap --milestones 7000 --schedule 30000 \
    > "$OUT/train_gsplat.md" 2>&1
kill $dmon
say "done"
tail -n 25 "$OUT/pytest.log"
for f in train_speed render train_ours train_gsplat; do echo "== $f"; grep -E '^\||rror' "$OUT/$f.md" | tail -n 40; done
