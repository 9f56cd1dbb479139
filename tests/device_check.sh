#!/bin/bash
# The CUDA path on a lent GPU machine (no CI machine has one): gsplat's kernels built, the CUDA tests, and
# `ns-train sg-feature-splat` + `ns-register-meta` on CUDA tensors, with the time of each stage.
#
#   bash tests/device_check.sh prepare   # here (PyPI reachable): wheels the GPU image lacks -> .devcheck/whl
#   bash tests/device_check.sh run       # there, from the repository root, with .devcheck carried; logs in $OUT
#
# The GPU image (Python 3.12, its own torch, numpy 2, no registry) lacks nerfstudio and the packages its
# imports need; `prepare` fetches those as cp312 wheels (about 50 MB, under the 64 MiB a call may carry).
# Three modules nerfstudio imports at module level but the checked path never calls are replaced by empty
# stubs instead (fpsample has no cp312 wheel; tensorly is 7 MB; boto3 is imported inside a try).
#
# gsplat 1.4.0 ships CUDA sources and builds them on first import (about 190 s on 16 cores). Every process
# must see the same TORCH_CUDA_ARCH_LIST: torch re-runs ninja in each new process, and different arch flags
# rebuild everything (a run lost 200 s of training that way).
set -u
WHEELS="appdirs==1.4.4 defusedxml==0.7.1 dill==0.4.1 docstring_parser==0.18.0 gsplat==1.4.0 msgspec==0.23.0
multiprocess==0.70.19 pathos==0.3.5 ppft==1.7.8 nerfacc==0.5.2 nerfstudio==1.1.5 outcome==1.3.0.post0 trio==0.22.2
PySocks==1.7.1 pycolmap==4.2.1 pyquaternion==0.9.9 pytorch-msssim==1.0.0 rawpy==0.28.0 splines==0.3.0
torch-fidelity==0.4.0 truststore==0.10.5 typeguard==4.6.1 tyro==1.0.17 viser==0.2.7 websockets==17.4 sniffio==1.3.1"

prepare() {
    mkdir -p .devcheck/whl
    grep -qx "/.devcheck/" .git/info/exclude 2>/dev/null || echo "/.devcheck/" >> .git/info/exclude
    local platforms="" n
    for n in 5 17 24 27 28 31 34 35; do platforms="$platforms --platform manylinux_2_${n}_x86_64"; done
    for wheel in $WHEELS; do
        python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
            $platforms --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d .devcheck/whl "$wheel" \
            || { echo "no cp312 wheel for $wheel"; return 1; }
    done
    du -sh .devcheck
}

run() {
    export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 PATH=/usr/local/cuda/bin:$PATH
    local start=$(date +%s) summary=$OUT/summary.txt repo=$PWD
    note() { echo "$*" | tee -a "$summary"; }
    since() { echo $(( $(date +%s) - $1 )); }

    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee -a "$summary"
    python3 -c "import sys,torch,numpy; print('python', sys.version.split()[0], 'torch', torch.__version__, 'numpy', numpy.__version__)" | tee -a "$summary"

    mkdir -p /tmp/stubs/tensorly /tmp/stubs/fpsample
    printf 'def set_backend(name):\n    pass\n' > /tmp/stubs/tensorly/__init__.py
    : > /tmp/stubs/fpsample/__init__.py
    python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site .devcheck/whl/*.whl || { note "wheel install failed"; return 1; }
    PYTHONPATH=/tmp/site python3 -m pip install -q --no-index --no-deps --no-build-isolation --no-compile --target /tmp/sg . || { note "project install failed"; return 1; }
    export PYTHONPATH=/tmp/sg:/tmp/site:/tmp/stubs PATH=/tmp/sg/bin:/tmp/site/bin:$PATH

    (cd /tmp && sg-make-scene --preset default --output /tmp/church > /tmp/make_scene.log 2>&1) &  # CPU work beside the build
    local scene_pid=$! t=$(date +%s)
    python3 -c "from gsplat.cuda._backend import _C; assert _C is not None" > "$OUT/gsplat_build.log" 2>&1 || { tail -30 "$OUT/gsplat_build.log"; note "gsplat build failed"; return 1; }
    note "gsplat CUDA build: $(since $t) s"

    t=$(date +%s)
    timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py > "$OUT/pytest_cuda.log" 2>&1
    note "tests/test_cuda.py rc=$? in $(since $t) s: $(grep -E '[0-9]+ (passed|failed|error)' "$OUT/pytest_cuda.log" | tail -1)"

    wait $scene_pid || { tail /tmp/make_scene.log; note "sg-make-scene failed"; return 1; }
    cd /tmp
    t=$(date +%s)
    timeout 240 ns-train sg-feature-splat --max-num-iterations 2000 --vis tensorboard --output-dir /tmp/ns --experiment-name church \
        --timestamp gpu --pipeline.datamanager.teacher.name offline colmap --data /tmp/church/reference > "$OUT/ns_train.log" 2>&1
    note "ns-train sg-feature-splat on CUDA (2000 steps, offline teacher) rc=$? in $(since $t) s"
    local config=/tmp/ns/church/sg-feature-splat/gpu/config.yml meta=/tmp/church/meta
    local common="--load-config $config --meta-image $meta/front --meta-image $meta/rear --init colmap --gt $meta/front/gt_transform.json --gt $meta/rear/gt_transform.json"

    t=$(date +%s)
    timeout 150 ns-register-meta $common --output-dir /tmp/reg_fast --config fast-cpu --device cuda > "$OUT/register_fast_cpu_preset.log" 2>&1
    note "ns-register-meta --config fast-cpu on CUDA rc=$? in $(since $t) s"
    t=$(date +%s)
    timeout 150 ns-register-meta $common --output-dir /tmp/reg_paper --optimiser.steps 600 > "$OUT/register_default_600_steps.log" 2>&1
    note "ns-register-meta (default preset on CUDA, --optimiser.steps 600) rc=$? in $(since $t) s"
    for log in register_fast_cpu_preset register_default_600_steps; do tail -12 "$OUT/$log.log" | tee -a "$summary"; done
    cd "$repo"
    echo; echo "=== $(since $start) s"; cat "$summary"
}

case "${1:-}" in
    prepare) prepare ;;
    run) run ;;
    *) echo "usage: bash tests/device_check.sh prepare|run"; exit 2 ;;
esac
