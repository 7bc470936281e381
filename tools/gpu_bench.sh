#!/usr/bin/env bash
# The benches on a lent GPU machine (run there from the repository root, .whl and .gl carried; see
# tools/gpu_bundle.sh): the 150-frame bench session is generated there (about a minute, the anny
# cache included), the pipeline runs on CUDA with the profiler, then on the CPU with
# CPU_WORKERS workers. First, unless TESTS_S=0, tests/test_cuda.py (a broken CUDA path shows
# there in a minute or two; TESTS names other test ids); CPU_S=0 skips the CPU run. Logs, metrics
# and the profile go to $OUT. GPU_ARGS: more arguments of the GPU run; GPU2_ARGS: a second GPU
# run on the same session with these (an A/B on one machine).
#   TESTS_S=200 FRAMES=150 GPU_S=420 CPU_S=230 CPU_WORKERS=8 bash tools/gpu_bench.sh
T0=$(date +%s)
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
dpkg -x .whl/deb/libusb*.deb /tmp/usb
export LD_LIBRARY_PATH=$(dirname "$(find /tmp/usb -name libusb-1.0.so.0 | head -1)"):${LD_LIBRARY_PATH:-}
mkdir -p /tmp/site && tar xJf .whl/site.tar.xz -C /tmp/site || exit 1
# body_models/ and calib/ install inside the package (setup.cfg's package_dir); here they are linked
ln -sfn ../body_models intercap/body_models; ln -sfn ../calib intercap/calib
if [ ! -f data_samples/sample/calibration.json ]; then  # the sample's first 12 frames
    rm -rf data_samples/sample; mkdir -p data_samples; cp -r .whl/sample data_samples/sample
fi
export PYGLET_HEADLESS=true PYTHONPATH=/tmp/site:$PWD PYOPENGL_PLATFORM=egl PYTHONUNBUFFERED=1
nvidia-smi -L; nproc
python3 -c "import torch, intercap.body_models.anny_backend, open3d, pyrender, roma; print(torch.__version__, torch.cuda.is_available())" || exit 1
echo "set up in $(( $(date +%s) - T0 )) s"
bench() {  # NAME TIMEOUT ARGS...
    local name=$1 limit=$2; shift 2
    timeout "$limit" python3 -m tools.bench_pipeline --frames "${FRAMES:-150}" --keep /tmp/k_$name \
        --set report.enabled=false "$@" > "$OUT/$name.log" 2>&1
    echo "$name: rc $? after $(( $(date +%s) - T0 )) s"; grep -A15 "^whole pipeline" "$OUT/$name.log"; tail -n 3 "$OUT/$name.log"
    cp /tmp/k_$name/*_out/metrics.json "$OUT/${name}_metrics.json" 2>/dev/null
    cp /tmp/k_$name/*_out/profile.txt "$OUT/${name}_profile.txt" 2>/dev/null
}
if [ "${TESTS_S:-200}" != 0 ]; then
    # SIGINT at the limit: pytest stops and still reports the failures so far; one process
    # (without setup.cfg's xdist workers, which the bundle need not carry), the GPU to itself
    timeout -s INT -k 15 "${TESTS_S:-200}" python3 -m pytest -q --tb=short -p no:cacheprovider -o addopts=-ra -p no:xdist ${TESTS:-tests/test_cuda.py} \
        > "$OUT/test_cuda.log" 2>&1
    echo "test_cuda: rc $? after $(( $(date +%s) - T0 )) s"; tail -n 15 "$OUT/test_cuda.log"
fi
bench gpu "${GPU_S:-420}" --set run.device=cuda --profile ${GPU_ARGS:-}
session=$(ls -d /tmp/k_gpu/*/ | grep -v _out/ | head -1)  # later runs take the same session
if [ -n "${GPU2_ARGS:-}" ]; then  # an A/B run on the same machine, e.g. GPU2_ARGS="--set object.cuda_graphs=false"
    bench gpu2 "${GPU_S:-420}" --session "$session" --set run.device=cuda $GPU2_ARGS
fi
[ "${CPU_S:-230}" = 0 ] && exit 0  # CPU_S=0: no CPU run
bench cpu "${CPU_S:-230}" --session "$session" --set run.workers="${CPU_WORKERS:-8}"
