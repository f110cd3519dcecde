"""`torchcal fleet` with fleet.reuse: a 100-unit fleet whose one broken file is mended afterwards. Times the rerun
that fits only that unit against a fresh run of every unit, and checks that both write the same fleet.

    python experiments/fleet/reuse.py [--units 100] [--repeat 2] [--out runs/fleet_reuse]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import pandas as pd

from ray_check import write_fleet  # the same folder: run as a script


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--units", type=int, default=100)
    ap.add_argument("--broken", type=int, default=13)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--out", default="runs/fleet_reuse")
    args = ap.parse_args(argv)
    from torchcal.app.fleet import run_fleet

    out = Path(args.out)
    good = write_fleet(out / "mended", args.units, None).parent / "units" / f"unit{args.broken:03d}.csv"
    cfg = write_fleet(out / "fleet", args.units, args.broken)
    first = run_fleet(cfg, out=out / "first").run_dir
    shutil.copy(good, cfg.parent / "units" / good.name)  # the broken file mended
    for rep in range(args.repeat):
        t = time.perf_counter()
        whole = run_fleet(cfg, out=out / f"whole{rep}").run_dir
        t_whole = time.perf_counter() - t
        t = time.perf_counter()
        again = run_fleet(cfg, [f"fleet.reuse={first}"], out=out / f"again{rep}").run_dir
        t_again = time.perf_counter() - t
        a, w = (pd.read_csv(r / "summary.csv").set_index("unit") for r in (again, whole))
        score = float(((a["outlier_score"] - w["outlier_score"]).abs() / w["outlier_score"].abs()).max())
        flags_same = a["flagged"].tolist() == w["flagged"].tolist()
        print(f"run {rep + 1}: every unit fitted afresh {t_whole:.1f} s; fleet.reuse (1 unit fitted, "
              f"{int(a['reused_from'].notna().sum())} reused) {t_again:.1f} s: {t_whole / t_again:.1f}x; outlier scores "
              f"within {score:.1e} (relative), flags {'the same' if flags_same else 'DIFFERENT'}: "
              f"{[u for u in a.index if a.loc[u, 'flagged']]}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
