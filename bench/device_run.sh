#!/usr/bin/env bash
# One device session: the CUDA tests and the GPU bench (card named), the CPU side on 2 host cores, quiet and with
# one CPU-bound competitor on one of those two cores. Wheels the image lacks travel in .whl (numba's own llvmlite
# included: the image's numba does not import with its NumPy).
set -o pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR=/tmp/numba-cache
python3 -c "import torch, numpy, numba; print('torch', torch.__version__, torch.cuda.get_device_name(), 'numpy', numpy.__version__, 'numba', numba.__version__)"
lscpu | grep -E "Model name|^CPU\(s\)"
# numba compiles the CPU kernels once (cached) while the CUDA tests run
python3 - > $OUT/warm.txt 2>&1 <<'PY' &
import torchcal, torch, torchcal.sim, time
from torchcal.identify.fleet import fit_fleet
t = time.perf_counter()
r = torchcal.load_robot("fanuc_lrmate200i")
tools = torch.tensor([[0.033, 0.058, 0.161], [0.057, -0.034, 0.161]], dtype=torch.float64)
make = lambda: torchcal.RobotModel(r, tools, orders=6, backlash=True)
q = torchcal.sim.quasi_random_commands(r.joint_map.limits, 2048, 0)
torchcal.compensate(make(), q, torch.ones_like(q))
noise = torchcal.NoiseModel.from_robot(r)
us = [torchcal.simulate(torchcal.TruthRobot.fanuc_paper2(r, tools, s), q[:80], [0, 1], noise, s) for s in range(2)]
fit_fleet(make, us, noise)
print("numba kernels compiled and cached in", round(time.perf_counter() - t, 1), "s")
PY
W=$!
timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py tests/test_contract.py tests/compensate/test_snapshot.py tests/compensate/test_det_sign.py 2>&1 | tail -6
wait $W; cat $OUT/warm.txt
timeout 220 taskset -c 0,1 python3 bench/gpu.py --units 100 --cpu-threads 2 2>&1 | tee $OUT/gpu_quiet.txt | grep -v "^\s*$" | tail -12
taskset -c 0 python3 -c "while True: pass" & C=$!
timeout 120 taskset -c 0,1 python3 bench/gpu.py --units 100 --cpu-threads 2 --only compensation,fleet 2>&1 | tee $OUT/gpu_loaded.txt | tail -8
kill $C
