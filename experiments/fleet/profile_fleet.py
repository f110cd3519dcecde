"""Profile the batched fleet solve on a small fleet (default 12 units): where each iteration's time goes.

    python experiments/fleet/profile_fleet.py [--units 12] [--mode torch|pyinstrument|plain]
"""
from __future__ import annotations

import argparse
import sys
import time

import torchcal  # noqa: F401  (before torch: OpenMP wait policy)

from torchcal.identify import fit
from torchcal.identify.fleet import fit_fleet



def setup(M, seed=0, damaged=(7,)):
    """(make, identification data per unit, noise): ratio.py's fleet, one damaged unit by default."""
    from ratio import fleet_data  # the same folder: run as a script

    return fleet_data(M, seed, damaged)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--units", type=int, default=12)
    ap.add_argument("--mode", default="plain")
    ap.add_argument("--out", default="/tmp/fleet_profile")
    a = ap.parse_args(argv)
    make, ident, noise = setup(a.units)
    fit(make(), ident[0], noise)
    t = time.perf_counter(); r = fit(make(), ident[0], noise); t1 = time.perf_counter() - t
    print(f"one fit {t1:.3f} s, {r.nit} it, nfev {r.nfev}")
    if a.mode == "torch":
        from torch.profiler import profile, ProfilerActivity
        with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
            t = time.perf_counter(); out = fit_fleet(make, ident, noise); tf = time.perf_counter() - t
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=40))
    elif a.mode == "pyinstrument":
        import pyinstrument
        p = pyinstrument.Profiler(interval=0.002)
        p.start(); t = time.perf_counter(); out = fit_fleet(make, ident, noise); tf = time.perf_counter() - t; p.stop()
        print(p.output_text(unicode=False, color=False, show_all=False))
    else:
        t = time.perf_counter(); out = fit_fleet(make, ident, noise); tf = time.perf_counter() - t
    its = [r.nit for r in out.results]
    print(f"fleet {a.units}: {tf:.3f} s = {tf / t1:.1f} x one fit; batched iterations {out.batch.iterations}, per-unit nit {its}")


if __name__ == "__main__":
    sys.exit(main())
