"""Side-by-side timing harness of the benchmark suite: quiet and with one CPU-bound competitor.

Every case is timed twice in the same process, interleaved (quiet, loaded,
quiet, loaded, ...), median of k runs each:

- quiet: nothing of ours runs beside the measured work;
- loaded: :func:`competitor` runs ``python -c "while True: pass"`` as a
  subprocess (one core of a 2-core machine busy), started before and killed
  after each loaded run.

CLI cases run the ``torchcal`` command as a subprocess in both conditions.
The harness also measures what the rest of the machine did meanwhile (busy
cores from /proc/stat minus this process, its children and the competitor:
"other CPU"), since a shared machine is never quiet by itself; with
``--wait-quiet S`` each run first waits up to S seconds for the other CPU to
drop below ``--quiet-below`` cores.

A bench module defines ``NAME`` and ``run(ctx) -> list[Row]``; ``python
bench/<name>.py`` runs it alone, ``python bench/run.py`` runs the suite.
Missing optional packages or data raise :class:`Skip`: the table gets a
"skipped: why" row, never a traceback.
"""

from __future__ import annotations

import torchcal  # noqa: F401  first: sets OMP_WAIT_POLICY=PASSIVE before anything loads torch (torchcal/core/threads.py)

import argparse
import contextlib
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
BENCH_DIR = ROOT / "bench"
DEFAULT_WORKDIR = ROOT / "runs" / "bench"
COMPETITOR_CODE = "while True: pass"


class Skip(Exception):
    """A case that cannot run here (optional package or data missing, command not there yet): the reason."""


class CaseError(Exception):
    """A case that ran and failed (a command's non-zero exit, a wrong result): the reason."""


# --------------------------------------------------------------------------- load


@contextlib.contextmanager
def competitor(settle: float = 0.3):
    """One CPU-bound process (``python -c "while True: pass"``) for the duration of the block; killed after."""
    proc = subprocess.Popen([sys.executable, "-c", COMPETITOR_CODE], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(settle)  # running (and spinning) before the measured work starts
        yield proc
    finally:
        proc.kill()
        proc.wait()


_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _machine_busy() -> float | None:
    """Busy CPU seconds of the whole machine so far (/proc/stat), None where unreadable."""
    try:
        with open("/proc/stat") as f:
            vals = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = vals[3] + (vals[4] if len(vals) > 4 else 0)
    guest = sum(vals[8:10]) if len(vals) > 8 else 0  # already counted in user / nice
    return (sum(vals) - idle - guest) / _TICK


def _proc_cpu(pid: int) -> float:
    """CPU seconds used by process ``pid`` (0 where it is gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / _TICK
    except (OSError, ValueError, IndexError):
        return 0.0


def _own_cpu() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


class CpuMeter:
    """Cores the rest of the machine kept busy over an interval (not this process, its children, the competitor)."""

    def __init__(self, competitor_pid: int | None = None):
        self.pid = competitor_pid

    def __enter__(self):
        self.t0, self.m0, self.o0 = time.perf_counter(), _machine_busy(), _own_cpu()
        self.c0 = _proc_cpu(self.pid) if self.pid else 0.0
        return self

    def __exit__(self, *exc):
        self.wall = time.perf_counter() - self.t0
        m1 = _machine_busy()
        own = _own_cpu() - self.o0
        comp = (_proc_cpu(self.pid) - self.c0) if self.pid else 0.0
        if self.m0 is None or m1 is None or self.wall <= 0:
            self.other = float("nan")
        else:
            self.other = max(0.0, (m1 - self.m0 - own - comp) / self.wall)
        return False


def other_cpu_now(seconds: float = 1.0) -> float:
    """Cores busy outside this process over the next ``seconds``."""
    with CpuMeter() as m:
        time.sleep(seconds)
    return m.other


# --------------------------------------------------------------------------- results


@dataclass
class Target:
    """A bound on a value: ``op`` '<=' or '>=', ``value``, printed as ``text`` (e.g. '<= 2 s')."""

    op: str
    value: float
    text: str = ""

    def ok(self, x: float | None) -> bool | None:
        if x is None or x != x:
            return None
        return x <= self.value if self.op == "<=" else x >= self.value

    def __str__(self) -> str:
        return self.text or f"{self.op} {self.value:g}"


def at_most(value: float, unit: str = "") -> Target:
    return Target("<=", value, f"<= {value:g}{(' ' + unit) if unit else ''}")


def at_least(value: float, unit: str = "") -> Target:
    return Target(">=", value, f">= {value:g}{unit}")


@dataclass
class Row:
    """One line of the table: a value quiet and loaded, its target and the loaded / quiet target."""

    bench: str
    case: str
    quiet: float | None = None
    loaded: float | None = None
    unit: str = "s"
    target: Target | None = None  # applies to the quiet and to the loaded value
    ratio_target: float | None = None  # loaded / quiet <= this
    note: str = ""
    other_cpu: tuple[float, float] | None = None  # cores busy elsewhere during the quiet / loaded runs
    runs: tuple[list, list] | None = None  # every run's value, quiet and loaded
    skipped: str | None = None
    error: str | None = None

    @property
    def ratio(self) -> float | None:
        if self.quiet and self.loaded is not None and self.quiet > 0:
            return self.loaded / self.quiet
        return None

    def failures(self) -> list[str]:
        out = []
        if self.target is not None:
            for label, v in (("quiet", self.quiet), ("loaded", self.loaded)):
                if self.target.ok(v) is False:
                    out.append(label)
        if self.ratio_target is not None and self.ratio is not None and self.ratio > self.ratio_target:
            out.append("ratio")
        return out

    @property
    def verdict(self) -> str:
        if self.skipped is not None:
            return "skipped"
        if self.error is not None:
            return "ERROR"
        if self.target is None and self.ratio_target is None:
            return "-"
        fails = self.failures()
        return "PASS" if not fails else "FAIL (" + ", ".join(fails) + ")"

    def target_text(self) -> str:
        parts = []
        if self.target is not None:
            parts.append(str(self.target))
        if self.ratio_target is not None:
            parts.append(f"ratio <= {self.ratio_target:g}")
        return "; ".join(parts) or "-"

    def as_json(self) -> dict:
        d = asdict(self)
        d["target"] = self.target_text()
        d["ratio"] = self.ratio
        d["verdict"] = self.verdict
        return d


@dataclass
class Pair:
    """Quiet and loaded runs of one case: medians, every run, other CPU, each run's return value."""

    quiet: list[float] = field(default_factory=list)
    loaded: list[float] = field(default_factory=list)
    other_quiet: list[float] = field(default_factory=list)
    other_loaded: list[float] = field(default_factory=list)
    out_quiet: list = field(default_factory=list)
    out_loaded: list = field(default_factory=list)

    @property
    def q(self) -> float:
        return statistics.median(self.quiet)

    @property
    def l(self) -> float:
        return statistics.median(self.loaded)

    @property
    def other(self) -> tuple[float, float]:
        def m(xs):
            xs = [x for x in xs if x == x]
            return statistics.mean(xs) if xs else float("nan")

        return m(self.other_quiet), m(self.other_loaded)

    def row(self, bench: str, case: str, **kw) -> Row:
        return Row(bench, case, self.q, self.l, other_cpu=self.other, runs=(self.quiet, self.loaded), **kw)


# --------------------------------------------------------------------------- context


class Context:
    """What a bench gets: options, the work directory, and the quiet / loaded timers."""

    def __init__(self, args):
        self.quick: bool = args.quick
        self.repeats: int = args.repeats if args.repeats else (1 if args.quick else 3)
        self.workdir: Path = Path(args.workdir).resolve()
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.wait_quiet: float = args.wait_quiet
        self.quiet_below: float = args.quiet_below
        self.irb120_data: Path = Path(args.irb120_data)
        self.verbose: bool = args.verbose
        self.log_path = self.workdir / "bench.log"

    def log(self, text: str) -> None:
        with open(self.log_path, "a") as f:
            f.write(text.rstrip() + "\n")
        if self.verbose:
            print(text, file=sys.stderr, flush=True)

    def _settle(self) -> None:
        """Wait (up to --wait-quiet s) until the rest of the machine is below --quiet-below busy cores."""
        if self.wait_quiet <= 0:
            return
        end = time.monotonic() + self.wait_quiet
        while time.monotonic() < end:
            if other_cpu_now(1.0) < self.quiet_below:
                return

    def pair(self, fn: Callable[[], object], repeats: int | None = None, timer: Callable | None = None,
             label: str = "") -> Pair:
        """Run ``fn`` quiet and loaded, interleaved, ``repeats`` times each.

        The time of a run is its wall clock, or ``timer(return value)`` when
        given (e.g. a solver's own time). -> :class:`Pair`.
        """
        k = max(1, repeats or self.repeats)
        p = Pair()
        for i in range(k):
            for loaded in (False, True):
                self._settle()
                with (competitor() if loaded else contextlib.nullcontext()) as comp:
                    with CpuMeter(comp.pid if comp is not None else None) as meter:
                        t0 = time.perf_counter()
                        out = fn()
                        wall = time.perf_counter() - t0
                t = timer(out) if timer is not None else wall
                (p.loaded if loaded else p.quiet).append(t)
                (p.other_loaded if loaded else p.other_quiet).append(meter.other)
                (p.out_loaded if loaded else p.out_quiet).append(out)
                self.log(f"  {label} run {i + 1}/{k} {'loaded' if loaded else 'quiet '}: {t:.4g} "
                         f"(wall {wall:.3g} s, other CPU {meter.other:.2f} cores)")
        return p

    def both(self, fn: Callable[[bool], object], label: str = "") -> tuple[object, object, tuple[float, float]]:
        """``fn(loaded)`` once quiet and once loaded (a case that times several things itself). -> (quiet, loaded, other CPU)."""
        outs, others = [], []
        for loaded in (False, True):
            self._settle()
            with (competitor() if loaded else contextlib.nullcontext()) as comp:
                with CpuMeter(comp.pid if comp is not None else None) as meter:
                    outs.append(fn(loaded))
            others.append(meter.other)
            self.log(f"  {label} {'loaded' if loaded else 'quiet'} done (other CPU {meter.other:.2f} cores)")
        return outs[0], outs[1], (others[0], others[1])


# --------------------------------------------------------------------------- the CLI as a subprocess


def torchcal_command() -> list[str]:
    """How to start the ``torchcal`` CLI of this environment."""
    exe = Path(sys.executable).parent / "torchcal"
    if exe.exists():
        return [str(exe)]
    found = shutil.which("torchcal")
    if found:
        return [found]
    return [sys.executable, "-c", "import sys; from torchcal.cli import main; sys.exit(main())"]


def run_cli(args: list[str], timeout: float = 1800, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """``torchcal ARGS`` as a subprocess; a non-zero exit raises :class:`CaseError` with the end of stderr."""
    proc = subprocess.run(torchcal_command() + [str(a) for a in args], cwd=cwd or ROOT, capture_output=True,
                          text=True, timeout=timeout)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-6:]
        raise CaseError(f"torchcal {' '.join(map(str, args[:2]))} exited {proc.returncode}: " + " | ".join(tail))
    return proc


def cli_available(command: str) -> bool:
    """Whether ``torchcal COMMAND --help`` exits 0."""
    try:
        return subprocess.run(torchcal_command() + [command, "--help"], capture_output=True, timeout=120).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def fresh_out(ctx: Context, name: str) -> Path:
    """A new, empty run-directory path under the work directory (torchcal fit creates it)."""
    base = ctx.workdir / "out"
    base.mkdir(exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=name + "-", dir=base)) / "run"


def need(module: str, why: str = ""):
    """Import an optional package or raise :class:`Skip` saying how to install it."""
    import importlib

    try:
        return importlib.import_module(module)
    except Exception as e:  # ImportError, or a broken binary dependency
        hint = why or f'pip install -e ".[bench]"'
        raise Skip(f"{module} not importable ({type(e).__name__}: {e}); {hint}") from None


# --------------------------------------------------------------------------- output


def machine_state() -> dict:
    from torchcal.core.threads import usable_cpus

    import torch

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "usable_cpus": usable_cpus(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
        "python": platform.python_version(),
        "loadavg_1_5_15": os.getloadavg() if hasattr(os, "getloadavg") else None,
        "other_cpu_at_start": round(other_cpu_now(1.0), 2),
        "competitor": f'{Path(sys.executable).name} -c "{COMPETITOR_CODE}" (one process)',
        "time": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def _fmt(x: float | None, unit: str) -> str:
    if x is None or x != x:
        return "-"
    if unit == "x":
        return f"{x:.2f}x"
    if abs(x) >= 100:
        return f"{x:.0f} {unit}".strip()
    if abs(x) >= 1:
        return f"{x:.2f} {unit}".strip()
    return f"{x:.3g} {unit}".strip()


def print_table(rows: list[Row], state: dict, title: str = "torchcal benchmarks") -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console(highlight=False, width=200)
    console.print(f"[bold]{title}[/bold]: {state['cpu']}, {state['cpu_count']} CPUs ({state['usable_cpus']} usable), "
                  f"torch {state['torch']}, OMP_WAIT_POLICY={state['OMP_WAIT_POLICY']}, "
                  f"load average {', '.join(f'{x:.2f}' for x in state['loadavg_1_5_15'] or [])} at start, "
                  f"other processes' CPU at start {state['other_cpu_at_start']:.2f} cores, bench niceness "
                  f"{state.get('niceness', 0)}; loaded = "
                  f"{state['competitor']}", markup=True)
    t = Table(show_lines=False)
    for col, just in (("bench", "left"), ("case", "left"), ("quiet", "right"), ("loaded", "right"),
                      ("loaded/quiet", "right"), ("target", "left"), ("verdict", "left"), ("other CPU q/l", "right"),
                      ("note", "left")):
        t.add_column(col, justify=just, overflow="fold")
    for r in rows:
        if r.skipped is not None:
            t.add_row(r.bench, r.case, "", "", "", r.target_text(), "skipped", "", r.skipped)
            continue
        if r.error is not None:
            t.add_row(r.bench, r.case, "", "", "", r.target_text(), "[red]ERROR[/red]", "", r.error)
            continue
        v = r.verdict
        color = "green" if v == "PASS" else ("red" if v.startswith("FAIL") else "white")
        oc = "" if r.other_cpu is None else f"{r.other_cpu[0]:.2f}/{r.other_cpu[1]:.2f}"
        t.add_row(r.bench, r.case, _fmt(r.quiet, r.unit), _fmt(r.loaded, r.unit),
                  "-" if r.ratio is None else f"{r.ratio:.2f}", r.target_text(), f"[{color}]{v}[/{color}]", oc, r.note)
    console.print(t)
    console.print("other CPU q/l: cores kept busy by processes outside the bench during the quiet / loaded runs "
                  "(the competitor excluded); medians of the runs; the full log: bench.log in the work directory.",
                  markup=False)


def run_benches(modules, ctx: Context) -> list[Row]:
    rows: list[Row] = []
    for mod in modules:
        name = getattr(mod, "NAME", mod.__name__)
        t0 = time.perf_counter()
        ctx.log(f"== {name} ({time.strftime('%H:%M:%S')})")
        print(f"[bench] {name} ...", file=sys.stderr, flush=True)
        try:
            out = mod.run(ctx)
        except Skip as e:
            out = [Row(name, "(all)", skipped=str(e))]
        except Exception as e:  # a broken bench must not hide the others
            ctx.log(traceback.format_exc())
            out = [Row(name, "(all)", error=f"{type(e).__name__}: {e} (traceback in bench.log)")]
        for r in out:
            ctx.log(f"  row {r.case}: quiet {r.quiet} loaded {r.loaded} {r.unit} -> {r.verdict} {r.note}")
        rows.extend(out)
        print(f"[bench] {name} done in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return rows


def guarded(bench: str, case: str, fn: Callable[[], list[Row] | Row], ctx: Context | None = None, **row) -> list[Row]:
    """Run one case; Skip / errors become a row (with ``row``'s target, ...) instead of a traceback."""
    try:
        out = fn()
        return out if isinstance(out, list) else [out]
    except Skip as e:
        return [Row(bench, case, skipped=str(e), **row)]
    except Exception as e:
        if ctx is not None:
            ctx.log(traceback.format_exc())
        return [Row(bench, case, error=f"{type(e).__name__}: {e}", **row)]


def parser(description: str) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--quick", action="store_true", help="one run per condition, smaller sizes, the slowest cases skipped")
    ap.add_argument("--repeats", type=int, default=0, help="runs per condition (median); default 3, 1 with --quick")
    ap.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR, help="data and run directories (default runs/bench)")
    ap.add_argument("--wait-quiet", type=float, default=0.0,
                    help="before each run wait up to this many seconds for other processes to go below --quiet-below")
    ap.add_argument("--quiet-below", type=float, default=0.25, help="busy cores of other processes counted as quiet")
    ap.add_argument("--irb120-data", type=Path,
                    default=Path(os.environ.get("TORCHCAL_IRB120_DATA", "/work/shared/data/irb120_faro")),
                    help="raw IRB 120 + FARO files (4-DataProcess/Input of icelinker/Robot-Calibration-LaserTracker)")
    ap.add_argument("--nice", type=int, default=None,
                    help="run the bench (and so its subprocesses and the competitor) at this niceness, e.g. -10 "
                         "(negative needs root): on a shared machine, other processes then take less of the CPU")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here (default WORKDIR/results.json)")
    ap.add_argument("-v", "--verbose", action="store_true", help="print every run's time")
    return ap


def main(modules, argv=None, description: str = "torchcal benchmark") -> int:
    args = parser(description).parse_args(argv)
    return execute(modules, args)


def execute(modules, args) -> int:
    if args.nice is not None:
        os.setpriority(os.PRIO_PROCESS, 0, args.nice)  # inherited by every subprocess, the competitor included
    ctx = Context(args)
    state = machine_state()
    state["niceness"] = os.getpriority(os.PRIO_PROCESS, 0)
    ctx.log(f"\n#### {state['time']} {json.dumps(state)}")
    rows = run_benches(modules, ctx)
    print_table(rows, state)
    out = args.json or (ctx.workdir / "results.json")
    Path(out).write_text(json.dumps({"machine": state, "rows": [r.as_json() for r in rows]}, indent=1, default=str))
    print(f"rows written to {out}", file=sys.stderr)
    return 0
