"""A URDF that passed validation is not validated again (yourdfpy's imports cost seconds per CLI run);
one that failed, or was edited, is."""

import subprocess
import sys

from torchcal.kinematics.robot import urdf_dir


def _loads(tmp_path, urdf, cache):
    code = ("import sys, torchcal; from torchcal.kinematics.urdf import load_urdf; "
            f"load_urdf({str(urdf)!r}); print('yourdfpy' in sys.modules)")
    env = {"TORCHCAL_CACHE": str(cache), "PATH": "", "HOME": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip() == "True"


def test_second_load_skips_the_validator_and_an_edit_validates_again(tmp_path):
    src = next(urdf_dir().glob("fanuc*.urdf"))
    urdf = tmp_path / "r.urdf"
    urdf.write_text(src.read_text())
    cache = tmp_path / "cache"
    assert _loads(tmp_path, urdf, cache) is True      # validated: yourdfpy imported
    assert _loads(tmp_path, urdf, cache) is False     # remembered
    urdf.write_text(urdf.read_text() + "\n<!-- edited -->\n")
    assert _loads(tmp_path, urdf, cache) is True      # new text: validated again


def test_a_failed_validation_is_not_remembered(tmp_path, monkeypatch):
    import pytest

    from torchcal.kinematics.urdf import URDFError, load_urdf

    monkeypatch.setenv("TORCHCAL_CACHE", str(tmp_path / "cache"))
    bad = '<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="revolute"><parent link="a"/>' \
          '<child link="b"/><axis xyz="0 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>'
    for _ in range(2):
        with pytest.raises(URDFError, match="zero vector"):
            load_urdf(bad)
    assert not list((tmp_path / "cache").rglob("*.*")) and not list((tmp_path / "cache").glob("urdf-valid/*"))
