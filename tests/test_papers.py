"""torchcal.papers: each paper's map (its module docstring) and its re-exports agree, and every re-export is
the library's own object (the map points at the code, it holds none)."""

import importlib

import pytest

PAPERS = ["torchcal.papers.paper1_machine_tool", "torchcal.papers.paper2_robot", "torchcal.papers.paper3_sensor"]


@pytest.mark.parametrize("name", PAPERS)
def test_every_export_is_in_the_map_and_is_the_librarys_own_object(name):
    paper = importlib.import_module(name)
    assert paper.__all__, name
    for export in paper.__all__:
        obj = getattr(paper, export)
        assert f"{export}`" in paper.__doc__ or f"{export}(" in paper.__doc__, f"{name}: {export} not in its map"
        home = importlib.import_module(obj.__module__)
        assert getattr(home, export) is obj and not obj.__module__.startswith("torchcal.papers"), export


@pytest.mark.parametrize("name", PAPERS)
def test_every_file_the_map_names_exists(name):
    """The map's 'where' column names files under torchcal/: each must exist (a moved module breaks the map)."""
    import re
    from pathlib import Path

    import torchcal

    root = Path(torchcal.__file__).parent
    paths = set(re.findall(r"\b([a-z_]+/[a-z_]+\.py)\b", importlib.import_module(name).__doc__))
    assert paths
    for p in sorted(paths):
        assert (root / p).is_file(), f"{name} names torchcal/{p}, which does not exist"
