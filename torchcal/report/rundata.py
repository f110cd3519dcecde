"""What a calibration report reads: the files of one run directory, each loaded on its own.

The report is written from the run directory alone (never from the data files a
config names: they may have moved or changed since the fit), and every kind of
run writes a different subset of files (robot, machine-tool and sensor fits,
``torchcal update`` runs, runs that failed half-way). So each file is read
independently here; one that is absent or unreadable becomes a :class:`Missing`
with the reason, which the report's section prints as "not available", instead
of stopping the report. Only a folder that is no run directory at all is an
error (:class:`ReportError`, naming the folder).
"""

from __future__ import annotations

import csv
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from ..core.exceptions import TorchcalError
from ..io import yamlio

PLOT_TITLES = {
    "joint_errors": "Identified error terms per joint (rotation and translation against the joint command; Figure 12)",
    "distribution_identification": "Residual distribution with its Gamma fit, identification set (Figure 13)",
    "distribution_validation": "Residual distribution with its Gamma fit, held-out validation set (Figure 13)",
    "residuals_identification": "Nominal and calibrated residual per measurement, identification set (Figures 14-15)",
    "residuals_validation": "Nominal and calibrated residual per measurement, held-out validation set (Figures 14-15)",
    "compensation_validation": "Nominal and compensated residual, validation commands measured on the simulated robot "
                               "(Figure 16)",
    "sweep": "Validation residual over the sweep's grid (Figure 11)",
}
"""Captions of the plots torchcal writes into ``plots/``; any other PNG is shown under its file name."""

PLOT_ORDER = ("distribution_validation", "distribution_identification", "residuals_validation",
              "residuals_identification", "compensation_validation", "joint_errors")


class ReportError(TorchcalError, ValueError):
    """A folder the report cannot be written for (no run directory); the message names the folder."""


@dataclass(frozen=True)
class Missing:
    """A file the run directory lacks or that could not be read; ``reason`` says which and why."""

    reason: str

    def __bool__(self) -> bool:
        return False


def _json(path: Path):
    if not path.is_file():
        return Missing(f"{path.name} not in the run directory")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        return Missing(f"{path.name} is not readable JSON ({type(exc).__name__}: {exc})")


def _text(path: Path):
    if not path.is_file():
        return Missing(f"{path.name} not in the run directory")
    try:
        return path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        return Missing(f"{path.name} is not readable ({exc.strerror or exc})")


def _yaml(text):
    if isinstance(text, Missing):
        return text
    import yaml

    try:
        cfg = yamlio.safe_load(text)
    except yaml.YAMLError as exc:
        return Missing(f"config.yaml is not readable YAML ({exc})")
    return cfg if isinstance(cfg, dict) else Missing("config.yaml holds no mapping")


@dataclass
class Residuals:
    """``residuals.csv`` by set: per row the nominal and modeled residual in mm (float64, every row kept)."""

    nominal: dict[str, list[float]]
    modeled: dict[str, list[float]]
    poses: dict[str, set]

    def rms(self, set_name: str, which: str) -> float | None:
        values = (self.nominal if which == "nominal" else self.modeled).get(set_name.lower())
        if not values:
            return None
        return math.sqrt(math.fsum(v * v for v in values) / len(values))


def _residuals(path: Path):
    if not path.is_file():
        return Missing(f"{path.name} not in the run directory")
    nominal: dict[str, list[float]] = {}
    modeled: dict[str, list[float]] = {}
    poses: dict[str, set] = {}
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            need = {"set", "nominal_mm", "modeled_mm"}
            if not need <= set(reader.fieldnames or ()):
                return Missing(f"{path.name} lacks the columns {sorted(need - set(reader.fieldnames or ()))}")
            for line, row in enumerate(reader, start=2):
                try:
                    nom, mod = float(row["nominal_mm"]), float(row["modeled_mm"])
                except (TypeError, ValueError):
                    return Missing(f"{path.name}, row {line}: nominal_mm / modeled_mm not numbers "
                                   f"({row['nominal_mm']!r}, {row['modeled_mm']!r})")
                name = row["set"].lower()
                nominal.setdefault(name, []).append(nom)
                modeled.setdefault(name, []).append(mod)
                poses.setdefault(name, set()).add(row.get("pose"))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        return Missing(f"{path.name} is not readable ({type(exc).__name__}: {exc})")
    return Residuals(nominal, modeled, poses)


def _uncertainty(path: Path):
    """parameters.csv (written by the fit: name, role, unit, value, std in mm / deg) -> {name: std}, or Missing."""
    if not path.is_file():
        return Missing(f"{path.name} not in the run directory (the fit computes it with its data checks)")
    out: dict[str, float] = {}
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            if not {"name", "std"} <= set(reader.fieldnames or ()):
                return Missing(f"{path.name} lacks the columns name, std")
            for line, row in enumerate(reader, start=2):
                try:
                    out[row["name"]] = float(row["std"])
                except (TypeError, ValueError):
                    return Missing(f"{path.name}, row {line}, column std: {row['std']!r} is not a number")
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        return Missing(f"{path.name} is not readable ({type(exc).__name__}: {exc})")
    return out


@dataclass
class RunFiles:
    """Everything of one run directory the report shows; each entry its content or a :class:`Missing`."""

    folder: Path
    config_text: object
    config: object
    versions: object
    metrics: object
    fit: object
    orders: object
    constraint: object
    frames: object
    update: object
    data_hashes: object
    alignment: object
    log: object
    residuals: object
    uncertainty: object
    plots: list[tuple[str, Path]] = field(default_factory=list)
    partial: bool = False


def read_run(run_dir) -> RunFiles:
    """Read every file of ``run_dir`` a report uses; absent or broken files become :class:`Missing`.

    Raises :class:`ReportError` when ``run_dir`` is no folder or holds none of
    the files ``torchcal fit`` / ``update`` write first (config.yaml, run.log,
    model.pt, versions.json, metrics.json).
    """
    from ..io.rundir import RUN_MARKERS, is_run_dir

    folder = Path(run_dir)
    if not folder.is_dir():
        raise ReportError(f"{folder}: not a folder; give a run directory written by 'torchcal fit' or 'torchcal update'")
    if not is_run_dir(folder):
        raise ReportError(f"{folder}: not a run directory (none of {', '.join(RUN_MARKERS)} in it); give a folder "
                          "written by 'torchcal fit' or 'torchcal update'")
    config_text = _text(folder / "config.yaml")
    plot_dir = folder / "plots"
    pngs = sorted(plot_dir.glob("*.png")) if plot_dir.is_dir() else []
    rank = {name: k for k, name in enumerate(PLOT_ORDER)}
    pngs.sort(key=lambda p: (rank.get(p.stem, len(rank)), p.name))
    return RunFiles(
        folder=folder.resolve(),
        config_text=config_text,
        config=_yaml(config_text),
        versions=_json(folder / "versions.json"),
        metrics=_json(folder / "metrics.json"),
        fit=_json(folder / "fit.json"),
        orders=_json(folder / "orders.json"),
        constraint=_json(folder / "constraint.json"),
        frames=_json(folder / "frames.json"),
        update=_json(folder / "update.json"),
        data_hashes=_json(folder / "data_hashes.json"),
        alignment=_json(folder / "alignment.json"),
        log=_text(folder / "run.log"),
        residuals=_residuals(folder / "residuals.csv"),
        uncertainty=_uncertainty(folder / "parameters.csv"),
        plots=[(PLOT_TITLES.get(p.stem, p.name), p) for p in pngs],
        partial=(folder / "PARTIAL").exists(),
    )


def get(obj, *keys, default=None):
    """``obj[k1][k2]...`` through dicts and lists, ``default`` where a level is absent or :class:`Missing`."""
    for k in keys:
        if isinstance(obj, dict) and k in obj:
            obj = obj[k]
        elif isinstance(obj, list) and isinstance(k, int) and -len(obj) <= k < len(obj):
            obj = obj[k]
        else:
            return default
    return default if isinstance(obj, Missing) else obj


_RECORD = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d (DEBUG|INFO|WARNING|ERROR|CRITICAL) (.*)$")
"""A record's first line in run.log (torchcal.io.rundir.run_log's format); other lines continue the record above."""


def log_warnings(log) -> list[str]:
    """The WARNING / ERROR records of run.log (their message part, continuation lines included: a data error's
    row and column are on its second line), in order."""
    if isinstance(log, Missing):
        return []
    out: list[str] = []
    inside = False  # the line above belongs to a warning record
    for line in log.splitlines():
        m = _RECORD.match(line)
        if m is None:
            if line.startswith("Traceback (most recent call last)"):
                inside = False  # a failed run's traceback is for run.log, not for the report's list
            if inside:
                out[-1] += "\n" + line
            continue
        inside = m.group(1) in ("WARNING", "ERROR", "CRITICAL")
        if inside:
            out.append(m.group(2) if m.group(1) == "WARNING" else f"{m.group(1).lower()}: {m.group(2)}")
    return out


__all__ = ["Missing", "PLOT_TITLES", "ReportError", "Residuals", "RunFiles", "get", "log_warnings", "read_run"]
