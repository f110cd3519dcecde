#!/usr/bin/env bash
# One device session: the CUDA tests and the GPU bench (card named), the CPU side on 2 host cores, quiet and with
# one CPU-bound competitor on one of those two cores. `bash bench/device_run.sh --fleet` (optionally BASE=dir):
# the fleet alone; `--compensation`: compensation alone. Wheels the image lacks travel in .whl (numba's own llvmlite
# included: the image's numba does not import with its NumPy).
set -o pipefail
# .whl: wheels, or site.tar.xz (the same packages installed here with --target, xz-packed: llvmlite's wheel alone
# is 60 MB, the 64 MiB a call may carry)
if [ -f .whl/site.tar.xz ]; then mkdir -p /tmp/site && tar -C /tmp/site -xJf .whl/site.tar.xz || exit 1
else python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1; fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR=/tmp/numba-cache
python3 -c "import torch, numpy, numba; print('torch', torch.__version__, torch.cuda.get_device_name(), 'numpy', numpy.__version__, 'numba', numba.__version__)"
lscpu | grep -E "Model name|^CPU\(s\)"
if [ "$1" = "--compensation" ]; then  # compensation alone (~3 min): its CUDA tests, the damped path's graphs on
  # and off side by side (bench/gpu_compensation_probe.py), then the bench's compensation rows quiet and loaded
  # the CPU side's kernels; FLEET=1: the fleet's row too (quiet), PROBE=0: no graphs on/off probe
  python3 -m torchcal.cli compile --only targets,damped,flange${FLEET:+,fleet} > $OUT/compile.txt 2>&1 &
  timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py tests/compensate/test_det_sign.py \
    tests/compensate/test_damped_fixed_shape.py -k "not cartesian" 2>&1 | tail -4
  TORCHCAL_NO_NUMBA=1 timeout 90 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py -k cartesian 2>&1 | tail -1
  [ "$PROBE" = 0 ] || timeout 150 python3 bench/gpu_compensation_probe.py 2>&1 | tee $OUT/probe.txt | grep -E "graphs|best|NVIDIA"
  wait; tail -2 $OUT/compile.txt | head -1
  timeout 100 taskset -c 0,1 python3 bench/gpu.py --cpu-threads 2 --only compensation 2>&1 | tee $OUT/comp_quiet.txt | tail -4
  taskset -c 0 python3 -c "while True: pass" & C=$!
  timeout 100 taskset -c 0,1 python3 bench/gpu.py --cpu-threads 2 --only compensation 2>&1 | tee $OUT/comp_loaded.txt | tail -4
  kill $C
  [ -z "$FLEET" ] || timeout 150 taskset -c 0,1 python3 bench/gpu.py --units 100 --cpu-threads 2 --only fleet 2>&1 | tee $OUT/fleet_quiet.txt | tail -2
  exit 0
fi
if [ "$1" = "--fleet" ]; then  # the fleet (~6 min): the CUDA tests, the fleet's ratio quiet and loaded, with
  # BASE=<a source tree carried in> that tree's GPU fleet beside this one's, alternated (the same session: GPU
  # hosts differ by up to 1.7x between sessions), cProfile of the host's time in one GPU solve quiet and
  # loaded, then the other GPU cases (one fit, prediction, compensation) quiet
  python3 -m torchcal.cli compile --only fleet > $OUT/compile.txt 2>&1 &  # the CPU side's kernels, cached
  timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py -k "not cartesian" 2>&1 | tail -2
  # its CPU reference by torch ops: the compiled targets pass is a cold compile of ~2 min on a fresh machine
  TORCHCAL_NO_NUMBA=1 timeout 90 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py -k cartesian 2>&1 | tail -1
  wait; tail -2 $OUT/compile.txt | head -1
  timeout 150 taskset -c 0,1 python3 bench/gpu.py --units 100 --cpu-threads 2 --only fleet > $OUT/fleet_quiet.txt 2>&1
  tail -2 $OUT/fleet_quiet.txt | sed "s/^/quiet  /"
  taskset -c 0 python3 -c "while True: pass" & C=$!
  timeout 150 taskset -c 0,1 python3 bench/gpu.py --units 100 --cpu-threads 2 --only fleet > $OUT/fleet_loaded.txt 2>&1
  tail -2 $OUT/fleet_loaded.txt | sed "s/^/loaded /"
  timeout 60 taskset -c 0,1 python3 bench/gpu_fleet_profile.py --cprofile > $OUT/cprofile_loaded.txt 2>&1
  kill $C
  grep -m1 "profiled solve" $OUT/cprofile_loaded.txt | sed 's/^/loaded /'
  for s in ${BASE:+$BASE} . ${BASE:+$BASE} .; do
    PYTHONPATH=/tmp/site:$PWD/$s timeout 40 python3 bench/gpu_fleet_profile.py --modes default --no-table 2>&1 | tail -1 | sed "s|^|$s: |"
  done
  timeout 60 python3 bench/gpu_fleet_profile.py --cprofile > $OUT/cprofile.txt 2>&1
  grep -m1 "profiled solve" $OUT/cprofile.txt; grep -A12 "Ordered by: internal" $OUT/cprofile.txt | tail -9 | cut -c1-130
  timeout 150 taskset -c 0,1 python3 bench/gpu.py --units 100 --cpu-threads 2 --only fit,prediction,compensation 2>&1 | tee $OUT/gpu_rest.txt | tail -7
  exit 0
fi
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
timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py tests/test_contract.py tests/compensate/test_snapshot.py tests/compensate/test_det_sign.py -k "not cartesian" 2>&1 | tail -6
TORCHCAL_NO_NUMBA=1 timeout 90 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py -k cartesian 2>&1 | tail -1
wait $W; cat $OUT/warm.txt
timeout 220 taskset -c 0,1 python3 bench/gpu.py --units 100 --cpu-threads 2 2>&1 | tee $OUT/gpu_quiet.txt | grep -v "^\s*$" | tail -12
taskset -c 0 python3 -c "while True: pass" & C=$!
timeout 120 taskset -c 0,1 python3 bench/gpu.py --units 100 --cpu-threads 2 --only compensation,fleet 2>&1 | tee $OUT/gpu_loaded.txt | tail -8
kill $C
