#!/usr/bin/env bash
# The GPU checks, for a lent GPU machine (see the README's performance section), in two calls because one call carries
# at most 64 MiB:
#   bash benchmarks/gpu_check.sh tests   # the suite on cuda_ad_rgb, the training loop's throughput (frozen against
#                                        # traced, GPU utilization, profile), ours on mi_objects/colmap to 7k
#   bash benchmarks/gpu_check.sh peers   # the rasterizer against gsplat, gsplat's simple_trainer recipe to 7k
#   bash benchmarks/gpu_check.sh quality setup|start|finish   # ours against gsplat's recipe, 7k of 30k, on the four
#                                        # shared datasets, quality and minutes (two calls: see "quality" below)
#   bash benchmarks/gpu_check.sh layouts # the blend's lane layouts on a trained model, then the rasterizer against
#                                        # gsplat (after "quality setup": see "layouts" below)
#   bash benchmarks/gpu_check.sh issue53 # issue 53's GPU rows in ONE call sized for a 15-minute device budget: see
#                                        # "issue53" below
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
part=${1:?usage: gpu_check.sh tests|peers|quality|layouts|issue53}
OUT=${OUT:-/tmp/gpu_check}
mkdir -p "$OUT"
T0=$(date +%s)
say() { echo "[$(($(date +%s) - T0)) s] $*" | tee -a "$OUT/setup.log"; }

nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm,power.limit --format=csv | tee -a "$OUT/setup.log"
source .gpu/bootstrap.sh
site=${MIGS_SITE:-/tmp/mi-gs-site}
data() { mkdir -p ../shared && ln -sfn "$PWD/.gpu/data" ../shared/data; }

if [ "$part" = quality ]; then
    # Training quality and whole-run minutes, ours against gsplat's recipe, 7k of the 30k schedule, one run at a time
    # (so the minutes mean something), in this order: mi_room/colmap, fox -r 4, maryrose -r 8, mi_objects/colmap.
    # What a run needs goes to /tmp, which outlives a call on a warm machine (ignored files in the checkout do not:
    # a later call removes what it does not carry). One call carries at most 64 MiB, so two calls, back to back:
    #   call 1 (carry .gpu/site.tar.xz .gpu/pycolmap.tar.xz .gpu/bootstrap.sh):   gpu_check.sh quality setup
    #   call 2 (carry .gpu/gsplat-1.5.3-py3-none-any.whl .gpu/data.tar.xz .gpu/bootstrap.sh):
    #          gpu_check.sh quality setup && gpu_check.sh quality start
    #   a call 3 within the warm time, if call 2's wait ended first:   gpu_check.sh quality finish
    # Here, first: prepare.sh --gsplat; pycolmap's wheel unpacked and packed again as .gpu/pycolmap.tar.xz; and
    #   python benchmarks/pack_data.py .gpu/data fox:4 maryrose:8 mi_objects/colmap mi_room/colmap
    #   tar -C .gpu -cf - data | xz -T2 -6 > .gpu/data.tar.xz && rm -r .gpu/data        # ~18 MB
    # The runs go on detached (setsid) between calls. Q_SHORT (7000) and WAIT_S (seconds a call waits) allow a short
    # dry run on the CPU (Q_DATA=../shared/data there). Seen on an H200: seven of our runs at once made no more
    # iterations per second together than one alone, hence one at a time.
    phase=${2:-start}
    R=${Q_ROOT:-/tmp/q}
    short=${Q_SHORT:-7000}
    QDATA=${Q_DATA:-/tmp/q-data}
    collect() {
        python3 benchmarks/collect_runs.py "$R/ablation" --curve 2000 4000 6000 "$short" \
            --json "$OUT/ours.json" > "$OUT/ours.md" 2>> "$OUT/collect.log"
        cat "$R"/gsplat_*.md > "$OUT/gsplat.md" 2>/dev/null
        # (with each of our runs' metrics.json and history.json: the time split of issue 36, recordings, overflows)
        tar -C "$R" -czf "$OUT/logs.tar.gz" logs $(cd "$R" && ls gsplat_*.json 2>/dev/null) \
            $(cd "$R" && find ablation \( -name metrics.json -o -name history.json -o -name config.json \) 2>/dev/null)
        echo "== ours"; cat "$OUT/ours.md"; echo "== gsplat"; grep -hE '^\| gsplat|rror' "$R"/gsplat_*.md
        python3 benchmarks/compare_views.py "$R" > "$OUT/views.md" 2>> "$OUT/collect.log"   # (view by view)
    }
    running() { pgrep -f "$R/" > /dev/null; }
    case "$phase" in
    setup)
        [ -f .gpu/pycolmap.tar.xz ] && tar -xJf .gpu/pycolmap.tar.xz -C "$site"
        [ -f .gpu/data.tar.xz ] && mkdir -p "$QDATA" && tar -xJf .gpu/data.tar.xz -C "$QDATA" --strip-components 1
        python3 -c "import mitsuba, pycolmap" 2>&1 | tail -n 1
        say "set up: $(ls "$site" | tr '\n' ' ')"
        exit 0 ;;
    start)
        python3 -c "import mitsuba, pycolmap" && [ -d "$site/gsplat" ] || { say "not set up (the setup calls first)"; exit 2; }
        [ -d "$QDATA/mi_objects" ] || { say "$QDATA: no datasets (the setup call with data.tar.xz)"; exit 2; }
        mkdir -p ../shared "$R/logs"
        if [ ! -e ../shared/data ] || [ -L ../shared/data ]; then ln -sfn "$QDATA" ../shared/data; fi
        G="python3 benchmarks/gsplat_train.py"
        A="python3 benchmarks/ablation.py"
        lane="MAX_JOBS=14 python3 -c 'from gsplat.cuda._backend import _C' > $R/logs/gsplat_build.log 2>&1;"
        # (mi_room first: where ours is furthest behind; mi_objects, measured most, last; then ours with gsplat
        # 1.5.3's no-reset rule on mi_room, if the call lasts)
        # (Q_SETUPS: our ablation setups per dataset, default "defaults"; e.g. "defaults no_reset" to rank the opacity
        # reset on all four, about 12 runs: a finish call's worth more)
        for pair in mi_room_colmap:mi_room_colmap fox_r4:fox maryrose_r8:maryrose mi_objects_colmap:mi_objects_colmap; do
            ours=${pair%%:*}; peer=${pair##*:}
            for setup in ${Q_SETUPS:-defaults}; do
                lane="$lane $A $ours --only $setup --iterations $short --schedule 30000 --out $R/ablation \
                    > $R/logs/ours_${ours}_$setup.log 2>&1;"
            done
            lane="$lane $G $peer --milestones $short --schedule 30000 \
                --out $R/gsplat_${peer}.json > $R/gsplat_${peer}.md 2>&1;"
        done
        lane="$lane $A mi_room_colmap --only no_reset --iterations $short --schedule 30000 --out $R/ablation \
            > $R/logs/ours_mi_room_no_reset.log 2>&1;"
        # the gsplat build (~90 s of 16 cores) runs beside our first run; its minutes are read with that in mind
        setsid nohup timeout -k 30 "${RUN_S:-1500}" bash -c "$lane" > "$R/logs/lane.log" 2>&1 < /dev/null &
        say "started; waiting up to ${WAIT_S:-540} s"
        while running && [ $(($(date +%s) - T0)) -lt "${WAIT_S:-540}" ]; do sleep 5; done ;;
    finish)
        say "waiting up to ${WAIT_S:-150} s for the runs still going"
        while running && [ $(($(date +%s) - T0)) -lt "${WAIT_S:-150}" ]; do sleep 5; done
        if running; then
            say "stopping the runs still going (they checkpoint on SIGTERM)"
            pkill -TERM -f "$R/"; for i in $(seq 30); do running || break; sleep 1; done
        fi ;;
    *) echo "usage: gpu_check.sh quality setup|start|finish" >&2; exit 2 ;;
    esac
    say "collecting"
    collect
    exit 0
fi

if [ "$part" = layouts ]; then
    # The blend kernels' lane layouts on the GPU (issue 36: is a 200x200 run's step slow for want of threads?), on a
    # trained model and two synthetic scenes, then the rasterizer against gsplat. Two calls, back to back:
    #   call 1 (carry .gpu/site.tar.xz .gpu/pycolmap.tar.xz .gpu/bootstrap.sh):   gpu_check.sh quality setup
    #   call 2 (carry .gpu/run .gpu/gsplat-1.5.3-py3-none-any.whl .gpu/bootstrap.sh):   gpu_check.sh layouts
    # Here, first: a trained run's point_cloud.ply, cameras.json and config.json copied into .gpu/run (a 7k
    # mi_objects/colmap model: ~24 MB).
    (MAX_JOBS=14 timeout 300 python3 -c "from gsplat.cuda._backend import _C" > "$OUT/gsplat_build.log" 2>&1 &)
    say "lane layouts"
    timeout "${LAYOUTS_S:-150}" python3 benchmarks/layouts.py .gpu/run 100000:800 1000000:1600 --variant "${VARIANT:-cuda_ad_rgb}" \
        --layouts 4:64 2:128 1:256 4:32 2:64 --repeats 5 > "$OUT/layouts.md" 2>&1
    say "waiting for gsplat's build"
    for i in $(seq 120); do pgrep -f "gsplat.cuda._backend" > /dev/null || break; sleep 2; done
    say "rasterizer against gsplat"
    timeout "${RENDER_S:-120}" python3 benchmarks/render.py --variant cuda_ad_rgb --peers gsplat --repeats 7 --profile \
        --cases 10000:256 100000:800 1000000:1600 > "$OUT/render.md" 2>&1
    say done
    for f in layouts render; do echo "== $f"; grep -E '^\| [0-9a-zA-Z]|rror' "$OUT/$f.md" | tail -n 20; done
    exit 0
fi

if [ "$part" = issue53 ]; then
    # Issue 53's GPU rows, all in one call (a session's device time is 15 minutes, the machine's start included):
    # gsplat's recipe and ours on mi_objects/colmap, 7k of the 30k schedule, one after the other (minutes and scores
    # from the same machine), then the rasterizers' forward + backward at 100k/800x800 and 1M/1600x1600.
    # Here, first (about 45 MiB travels):
    #   bash ../shared/tools/gpu/prepare.sh --gsplat        # .gpu/site.tar.xz, the gsplat wheel, bootstrap.sh
    #   mkdir -p .gpu/data/mi_objects && cp -r ../shared/data/mi_objects/colmap .gpu/data/mi_objects/
    # and run it as: run(command="bash benchmarks/gpu_check.sh issue53", timeout_s=600,
    #   carry=[".gpu/site.tar.xz", ".gpu/gsplat-1.5.3-py3-none-any.whl", ".gpu/bootstrap.sh", ".gpu/data"])
    # Each step has its own limit and the whole stops starting steps after DEADLINE_S (default 540 s), so that the
    # call returns inside its 600 s with what it has: the training rows first (the must-show), then the kernels.
    deadline=${DEADLINE_S:-540}
    left() { echo $((deadline - ($(date +%s) - T0))); }
    step() {   # step LIMIT_S NAME LOG COMMAND...: run COMMAND (its output to LOG, appended) if LIMIT_S still fits
        local limit=$1 name=$2 log=$3; shift 3   # before the deadline; what became of it goes to the console
        if [ "$(left)" -lt "$limit" ]; then say "skipped $name: $(left) s left, it may take $limit"; return 1; fi
        say "$name"; timeout -k 10 "$limit" "$@" >> "$log" 2>&1; say "$name: exit $?"
    }
    data
    [ -d .gpu/data/mi_objects/colmap ] || say "no .gpu/data/mi_objects/colmap: the training rows will be skipped"
    step 240 "gsplat's CUDA build" "$OUT/setup.log" \
        python3 -c "from gsplat.cuda._backend import _C; print('gsplat built', _C is not None)"
    step 110 "gsplat's recipe, mi_objects/colmap, 7k of the 30k schedule" "$OUT/train_gsplat.md" \
        python3 benchmarks/gsplat_train.py mi_objects_colmap --milestones 7000 --schedule 30000
    step 150 "ours, mi_objects/colmap, 7k of the 30k schedule" "$OUT/train_ours.md" \
        python3 benchmarks/train.py mi_objects_colmap --milestones 7000 --schedule 30000 --variant "${VARIANT:-cuda_ad_rgb}" \
        --out /tmp/ours
    step 100 "forward + backward against gsplat" "$OUT/render.md" \
        python3 benchmarks/render.py --variant "${VARIANT:-cuda_ad_rgb}" --peers gsplat --repeats 7 --profile \
        --cases 100000:800 1000000:1600
    # then, as time allows: ours with the model padded to size classes (row_classes=4: fewer new sizes, so fewer
    # kernels compiled at the refinements, which took 8.1 s of a 46 s run on the H200 on 2026-11-29; on the CPU the
    # padding costs more than it saves), where our step's device time goes on the trained model (what to work on
    # next), and the blend's lane layouts on it
    step 110 "ours with size classes (row_classes=4)" "$OUT/train_ours_classes.md" \
        python3 benchmarks/train.py mi_objects_colmap --milestones 7000 --schedule 30000 --variant "${VARIANT:-cuda_ad_rgb}" \
        --out /tmp/ours_classes --set row_classes=4
    run=/tmp/ours/mi_objects_colmap_of_30000
    cp "$run/metrics.json" "$OUT/ours_metrics.json" 2>/dev/null
    step 80 "our training step's kernel profile on the trained model" "$OUT/step_profile.md" \
        python3 benchmarks/step_profile.py "$run" --steps 40 --variant "${VARIANT:-cuda_ad_rgb}"
    step 90 "the blend's lane layouts on the trained model" "$OUT/layouts.md" \
        python3 benchmarks/layouts.py "$run@.gpu/data/mi_objects/colmap" --variant "${VARIANT:-cuda_ad_rgb}" \
        --layouts 4:64 2:128 1:256 4:32 2:64 --repeats 5
    say done
    for f in train_gsplat train_ours render train_ours_classes step_profile layouts; do
        echo "== $f"; grep -E '^\| [0-9a-zA-Z]|rror' "$OUT/$f.md" 2>/dev/null | tail -n 14
    done
    # (where our run's time went besides the steps: refinements, recordings, kernels compiled)
    echo "== ours: loop"; python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['loop'])" \
        "$OUT/ours_metrics.json" 2>&1 | tail -n 2
    exit 0
fi

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
