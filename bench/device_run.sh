#!/usr/bin/env bash
# One device session: the CUDA tests and the GPU bench (card named), CPU side on 2 host cores.
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
export PYTHONPATH=/tmp/site:$PWD
python3 -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name())"
timeout 240 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py tests/test_contract.py tests/compensate/test_snapshot.py tests/compensate/test_det_sign.py 2>&1 | tail -8
timeout 420 taskset -c 0,1 python3 bench/gpu.py --units 100 --cpu-threads 2 2>&1 | tail -40
