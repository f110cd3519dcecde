"""Probe (device): where GPU compensation time goes — chunk sizes, float64 / float32, fast vs damped path."""
import time, sys
import torch, torchcal, torchcal.sim
from torchcal.core import units as U
from torchcal.compensate import compensate
from torchcal.identify import fit
TOOLS = U.mm_to_m(torch.tensor([[33.06, 57.73, 161.22], [57.26, -33.86, 161.22], [-33.96, -57.23, 161.22]], dtype=torch.float64))
robot = torchcal.load_robot("fanuc_lrmate200i"); noise = torchcal.NoiseModel.from_robot(robot)
truth = torchcal.TruthRobot.fanuc_paper2(robot, TOOLS, 0)
q = torchcal.sim.quasi_random_commands(robot.joint_map.limits, 250, 0)
data = torchcal.simulate(truth, q, [0, 1, 2], noise, 0)
m = torchcal.RobotModel(robot, TOOLS, orders=6, backlash=True); fit(m, data, noise)
g = torchcal.RobotModel(robot, TOOLS, orders=6, backlash=True).cuda(); g.load_state_dict(m.state_dict())
N = 10**6
qp = torchcal.sim.quasi_random_commands(robot.joint_map.limits, N, 3).cuda(); s = torch.ones_like(qp)
def t(fn, k=3):
    fn(); torch.cuda.synchronize(); best=1e9
    for _ in range(k):
        a=time.perf_counter(); fn(); torch.cuda.synchronize(); best=min(best, time.perf_counter()-a)
    return best
for cs in [262144, 1000000]:
    print("float64 chunk", cs, f"{N / t(lambda: compensate(g, qp, s, chunk_size=cs)):.3g} poses/s")
g32 = torchcal.RobotModel(robot, TOOLS, orders=6, backlash=True).cuda(); g32.load_state_dict(m.state_dict()); g32 = g32.float()
print("float32 chunk 1e6", f"{N / t(lambda: compensate(g32, qp.float(), s.float(), chunk_size=N)):.3g} poses/s")
# fast path only: rows away from singularities (what fraction goes to the damped path?)
r = compensate(g, qp, s, chunk_size=N)
print("converged", float(r.converged.float().mean()), "fields", [f for f in vars(r)][:12])
from torch.profiler import profile, ProfilerActivity
with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
    compensate(g, qp, s, chunk_size=N); torch.cuda.synchronize()
print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=12))
print(prof.key_averages().table(sort_by="cpu_time_total", row_limit=8))
