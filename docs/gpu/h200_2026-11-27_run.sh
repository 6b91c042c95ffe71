#!/bin/bash
# Device run: CUDA tests, the demo recolour on the GPU, gpu_check (priors, gsplat vs torch, donut edit), bench_pipeline at the paper's budget.
cd "$(dirname "$0")/.."
exec > >(tee "$OUT/run.log") 2>&1
t0=$(date +%s); el() { echo "=== [$(( $(date +%s) - t0 )) s] $*"; }
el start; nvidia-smi -L; python3 -c "import torch;print(torch.__version__, torch.version.cuda, torch.cuda.get_device_name(0))"; nproc
python3 -m pip install -q --no-deps --no-index .gpu/wheels/*.whl 2>&1 | tail -2
export TORCH_CUDA_ARCH_LIST=9.0 GS_REGIONAL_DATA=$PWD/.gpu/data PYTHONPATH=$PWD
el pytest
timeout 220 python3 -m pytest -q -p no:cacheprovider tests/test_device_and_batching.py tests/test_renderer.py tests/test_instructpix2pix.py::test_dtype_auto_resolution -k "cuda or gsplat or dtype_auto" 2>&1 | tail -30 > $OUT/pytest_cuda.txt; cat $OUT/pytest_cuda.txt | tail -5
el demo_recolor_gpu
timeout 120 python3 launch.py --config configs/demo.yaml --train --gpu 0 data.edit=recolor 'system.prompt=make his head red' exp_root_dir=/tmp/demo_gpu 2>&1 | tail -25
cp $(ls -d /tmp/demo_gpu/*/*/save | head -1)/metrics.json $OUT/demo_recolor_gpu_metrics.json
el gpu_check
timeout 260 python3 scripts/gpu_check.py --only priors gsplat_vs_torch donut_edit --budget 240 --out /tmp/gc/gpu_check.json 2>&1 | tail -30
cp /tmp/gc/gpu_check.json $OUT/
el bench_pipeline_paper
timeout 250 python3 scripts/bench_pipeline.py --models real-size --fp16 --device cuda --resolution 512 --gaussians 100000 --out /tmp/bp 2>&1 | tail -30
cp /tmp/bp/bench_pipeline.json $OUT/bench_pipeline_paper.json
el done
