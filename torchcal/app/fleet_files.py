"""A fleet's folders -> its units: one measurement file per unit, named by the file's stem, and its
validation file of the same stem; what the folders hold besides is named, not skipped in silence."""

from __future__ import annotations

from pathlib import Path

from ..core.exceptions import ConfigError
from .config import source_of


def unit_files(cfg) -> list[tuple[str, Path, Path | None]]:
    """(name, identification file, validation file or None) per unit, sorted by name."""
    label = cfg.config_file or "config"
    ident = Path(cfg.data.identification)
    if not ident.is_dir():
        raise ConfigError(f"{source_of(cfg, 'data.identification', label)}: key 'data.identification': a fleet needs a folder with one CSV per unit, "
                          f"got {ident} ({'a file' if ident.is_file() else 'not found'})")
    files = measurement_files(ident)
    if not files:
        raise ConfigError(f"{source_of(cfg, 'data.identification', label)}: key 'data.identification': {ident} holds no .csv files")
    val = Path(cfg.data.validation) if cfg.data.validation else None
    if val is not None and not val.is_dir():
        raise ConfigError(f"{source_of(cfg, 'data.validation', label)}: key 'data.validation': a fleet needs a folder with files named like the "
                          f"identification files, got {val}")
    by_stem = _by_stem(files, source_of(cfg, "data.identification", label), "data.identification")
    val_by_stem = _by_stem(measurement_files(val), source_of(cfg, "data.validation", label), "data.validation") if val is not None else {}
    return [(stem, f, val_by_stem.get(stem)) for stem, f in sorted(by_stem.items())]


def measurement_files(folder: Path) -> list[Path]:
    """The measurement files of a folder: .csv / .tsv in any case, sorted."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in (".csv", ".tsv") and p.is_file())


def _by_stem(files: list[Path], label: str, key: str) -> dict[str, Path]:
    """{unit name (the file's stem): file}; two files of one stem are refused (one unit's run twice)."""
    stems: dict[str, list[Path]] = {}
    for f in files:
        stems.setdefault(f.stem, []).append(f)
    clash = {k: v for k, v in stems.items() if len(v) > 1}
    if clash:
        raise ConfigError(f"{label}: key '{key}': a unit is named by its file, and "
                          + "; ".join(f"{' and '.join(p.name for p in v)} both name unit '{k}'" for k, v in clash.items())
                          + ": rename or remove one of each")
    return {k: v[0] for k, v in stems.items()}


def validation_gaps(cfg, files: list) -> tuple[list[str], list[Path]]:
    """With ``data.validation``: the units without a validation file of their name, and the validation files
    that name no unit (neither is used; both are worth a word, not silence)."""
    if not cfg.data.validation:
        return [], []
    names = {name for name, _, _ in files}
    orphans = [p for p in measurement_files(Path(cfg.data.validation)) if p.stem not in names]
    return [n for n, _, fv in files if fv is None], orphans


def ignored_files(cfg) -> list[str]:
    """What the data folders hold besides measurement files (not read: a word in the log, not silence)."""
    out = []
    for key in ("identification", "validation"):
        folder = getattr(cfg.data, key)
        if folder and Path(folder).is_dir():
            out += [f"{Path(folder).name}/{p.name}" for p in sorted(Path(folder).iterdir())
                    if not p.name.startswith(".") and not (p.is_file() and p.suffix.lower() in (".csv", ".tsv"))]
    return out


__all__ = ["identical_files", "ignored_files", "measurement_files", "unit_files", "validation_gaps"]


def identical_files(files) -> list[list[str]]:
    """Groups of units (names) whose identification files are byte for byte the same; ``files``: as
    :func:`unit_files` returns them."""
    import hashlib

    by_hash: dict[str, list[str]] = {}
    for name, ident, _ in files:
        by_hash.setdefault(hashlib.sha256(Path(ident).read_bytes()).hexdigest(), []).append(name)
    return [names for names in by_hash.values() if len(names) > 1]
