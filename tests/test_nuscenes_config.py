"""``dataset=nuscenes`` without the devkit: the config, and the install hint when it is missing.

These run whether or not the optional ``nuscenes`` extra is installed (``test_nuscenes.py`` covers
the data with the real devkit).
"""

from __future__ import annotations

import inspect
import sys

import pytest
from omegaconf import OmegaConf
from omegaconf.errors import MissingMandatoryValue

from fusion_depth.config import validate_config
from fusion_depth.data.nuscenes import NuScenesDepth, condition_from_description
from fusion_depth.prepare.cli import prepare


@pytest.fixture
def no_devkit(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every ``import nuscenes...`` fails, as on a machine without the extra."""
    for name in [n for n in sys.modules if n == "nuscenes" or n.startswith("nuscenes.")]:
        monkeypatch.setitem(sys.modules, name, None)
    monkeypatch.setitem(sys.modules, "nuscenes", None)


def test_missing_devkit_fails_at_once_with_the_pip_command(no_devkit, make_config, tmp_path):
    with pytest.raises(ImportError, match=r'pip install -e "\.\[nuscenes\]"'):
        NuScenesDepth(split="train", root=tmp_path / "absent", cache_root=tmp_path / "cache")
    cfg = make_config("dataset=nuscenes", f"dataset.root={tmp_path / 'absent'}")
    with pytest.raises(ImportError, match=r"nuscenes-devkit.*pip install -e"):
        prepare(cfg)
    assert not (tmp_path / "cache").exists()


def test_root_must_be_given(make_config) -> None:
    cfg = make_config("dataset=nuscenes")
    with pytest.raises(MissingMandatoryValue, match="root"):
        validate_config(cfg)


def test_config_mirrors_the_other_datasets(make_config) -> None:
    procedural = make_config().dataset
    cfg = make_config("dataset=nuscenes", "dataset.root=/data/nuscenes")
    ds = cfg.dataset
    own = {"reader", "num_train", "num_val", "num_test"}  # the built-in dataset's frame counts
    assert set(procedural) - own <= set(ds)
    assert (ds.name, ds.sensor, ds.max_depth, ds.pretrained_backbone) == (
        "nuscenes",
        "radar",
        80.0,
        True,
    )
    assert list(ds.conditions) == ["day", "night", "rain"]
    assert ds.height % 32 == 0 and ds.width % 32 == 0
    assert ds.reader._target_ == "fusion_depth.data.nuscenes.NuScenesDepth"
    assert ds.reader._partial_ is True
    assert ds.reader.root == "/data/nuscenes" and ds.reader.fill == "colorization"
    assert ds.reader.cache_root == cfg.paths.cache_dir
    resolved = OmegaConf.to_container(cfg, resolve=True)
    assert resolved["model"]["net"]["depth_scale"] == ds.depth_scale
    # Every reader key is an argument of the reader.
    params = inspect.signature(NuScenesDepth).parameters
    reader = OmegaConf.to_container(ds.reader, resolve=True)
    assert {k for k in reader if not k.startswith("_")} <= set(params)


@pytest.mark.parametrize(
    ("description", "condition"),
    [
        ("Night, rain, peds, parking lot", "night"),
        ("night driving, big street", "night"),
        ("Rain, ped crossing, trucks", "rain"),
        ("Heavy raining at intersection", "rain"),
        ("Wait at intersection, peds, parked cars", "day"),
        ("Drive past train station, drain cover, terrain", "day"),
        ("", "day"),
    ],
)
def test_condition_from_scene_description(description: str, condition: str) -> None:
    assert condition_from_description(description) == condition
