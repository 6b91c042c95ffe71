#!/bin/bash
# The GPU checks of a session lent a device machine, as one call from the repository root (ran as it
# stood at f6aa665 on an H200 on 2026-11-30: docs/results.md). Before the call, on this machine:
#   echo /.gpu/ >> .git/info/exclude; mkdir -p .gpu/wheels .gpu/data; cp -r ../shared/data/* .gpu/data/
#   python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 -d .gpu/wheels diffusers==0.42.1 omegaconf==2.4.0 plyfile==1.1.5 \
#     gsplat==1.5.3 importlib_metadata
# then run `bash docs/gpu/device_run.sh` with carry [".gpu"] and a timeout of about 590 s (it plans for
# 500). In order of what matters most if the call is cut short: the priors and the IP2P step (while
# gsplat's CUDA kernels build in the background, about 70 s), the paper's budget at 100k and 1M
# Gaussians stage by stage with the start-up split, the CUDA tests (whole output kept), gsplat against
# the torch rasterizer and the donut edit, the demo on the GPU, the 1M localization and checkpoint
# (bench_scale). Everything lands in $OUT.
exec > >(tee "$OUT/run.log") 2>&1
t0=$(date +%s); el() { echo "=== [$(( $(date +%s) - t0 )) s] $*"; }
left() { echo $(( 500 - ($(date +%s) - t0) )); }
el start; nvidia-smi -L; nproc
python3 -m pip install -q --no-deps --no-index --no-compile .gpu/wheels/*.whl 2>&1 | tail -2
python3 -c "import torch, diffusers, transformers, lightning, importlib.metadata as m; print('torch', torch.__version__, torch.version.cuda, torch.cuda.get_device_name(0), '| diffusers', diffusers.__version__, '| transformers', transformers.__version__, '| lightning', lightning.__version__, '| gsplat', m.version('gsplat'))"
export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 GS_REGIONAL_DATA=$PWD/.gpu/data PYTHONPATH=$PWD PYTHONUNBUFFERED=1

el "gsplat JIT build (background)"
python3 - > /tmp/gsplat_build.log 2>&1 <<'EOF' &
import time, torch, gsplat
t = time.time(); d = "cuda"; n = 16
means = torch.randn(n, 3, device=d) + torch.tensor([0.0, 0.0, 5.0], device=d)
img = gsplat.rasterization(means, torch.randn(n, 4, device=d), torch.rand(n, 3, device=d) * 0.1, torch.rand(n, device=d),
                           torch.rand(n, 3, device=d), torch.eye(4, device=d)[None],
                           torch.tensor([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]], device=d)[None], 64, 64)[0]
torch.cuda.synchronize(); print(f"gsplat built and ran in {time.time() - t:.1f} s: {tuple(img.shape)}")
EOF
BUILD=$!

el "gpu_check priors ip2p_fp16"
timeout 200 python3 scripts/gpu_check.py --only priors ip2p_fp16 --budget 190 --out /tmp/gc1/gpu_check.json 2>&1 | tail -12
el "waiting for the gsplat build"; wait $BUILD; cat /tmp/gsplat_build.log | tail -3

el "gpu_check paper_budget (100k, 1M)"
timeout 300 python3 scripts/gpu_check.py --only paper_budget --budget 295 --out /tmp/gc2/gpu_check.json 2>&1 | tail -12
cp /tmp/gc2/paper_budget.json $OUT/ 2>/dev/null

el "CUDA tests"
timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_device_and_batching.py tests/test_renderer.py::test_cuda_matches_cpu tests/test_auto_batch.py > $OUT/pytest_cuda.txt 2>&1; tail -4 $OUT/pytest_cuda.txt

if [ "$(left)" -gt 80 ]; then
  el "gpu_check gsplat_vs_torch donut_edit"
  timeout $(left) python3 scripts/gpu_check.py --only gsplat_vs_torch donut_edit --budget $(( $(left) - 10 )) --out /tmp/gc3/gpu_check.json 2>&1 | tail -8
fi
if [ "$(left)" -gt 45 ]; then
  el "demo on the GPU"
  timeout $(left) python3 launch.py --config configs/demo.yaml --train --gpu 0 exp_root_dir=/tmp/demo_gpu 2>&1 | tail -9
  cp "$(ls -d /tmp/demo_gpu/*/*/save | head -1)/metrics.json" $OUT/demo_gpu_metrics.json 2>/dev/null
fi
if [ "$(left)" -gt 30 ]; then
  el "bench_scale localize and checkpoint at 1M on cuda"
  timeout $(left) python3 scripts/bench_scale.py --sizes 1000000 --stages localize checkpoint --device cuda --out /tmp/bs 2>&1 | tail -6
fi
el "collecting"
tar czf $OUT/reports.tgz --ignore-failed-read /tmp/gc1/*.json /tmp/gc2/*.json /tmp/gc3/*.json /tmp/gc*/logs/pytest.log \
  /tmp/gc2/paper_budget/*/bench_pipeline.json /tmp/bs/bench_scale.json /tmp/gsplat_build.log 2>/dev/null
el done
