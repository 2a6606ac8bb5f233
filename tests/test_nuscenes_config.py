"""``dataset=nuscenes`` without the devkit: the config, and the install hint when it is missing.

These run whether or not the optional ``nuscenes`` extra is installed (``test_nuscenes.py`` covers
the data with the real devkit).
"""

from __future__ import annotations

import copy
import inspect
import math
import sys

import pytest
from helpers import run_module
from omegaconf import OmegaConf
from omegaconf.errors import MissingMandatoryValue

from fusion_depth.config import validate_config, validate_dataset_config
from fusion_depth.data.nuscenes import NuScenesDepth, condition_from_description
from fusion_depth.errors import ConfigError, MissingDependencyError
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


# What the command line makes of null, inf, nan, abc, [1], -1, 1.5 and true.
BAD_COUNTS = [None, math.inf, math.nan, "abc", [1], -1, 1.5, True]


@pytest.mark.parametrize("key", ["radar_nsweeps", "lidar_nsweeps", "lidar_keyframes", "stride"])
def test_a_bad_reader_count_is_one_line_naming_the_key_before_any_work(
    no_devkit, make_config, tmp_path, key: str
) -> None:
    """Before: null, inf or a list passed the checks and ended in a TypeError or OverflowError
    inside the reader; abc and nan got a line that did not name the key. Now every bad value is
    named with the key and what it takes, by train's checks and by prepare's (which run before
    the devkit is looked for, so the machine needs no devkit to be told)."""
    composed = make_config("dataset=nuscenes", f"dataset.root={tmp_path}")
    for value in BAD_COUNTS:
        cfg = copy.deepcopy(composed)
        OmegaConf.update(cfg, f"dataset.reader.{key}", value)
        for check in (validate_config, validate_dataset_config):
            with pytest.raises(ConfigError) as err:
                check(cfg)
            message = str(err.value)
            assert "\n" not in message
            assert message.startswith(f"dataset.reader.{key}="), message
            assert "expected an integer ≥" in message
    assert not (tmp_path / "cache").exists()


def test_a_bad_reader_value_names_where_it_is_set(no_devkit, make_config, tmp_path) -> None:
    # dataset.reader.fill is ${dataset.fill}: the error names the key the user sets.
    cfg = make_config("dataset=nuscenes", f"dataset.root={tmp_path}", "dataset.fill=cubic")
    with pytest.raises(ConfigError, match=r"^dataset\.fill=cubic: expected one of none, linear"):
        validate_dataset_config(cfg)
    cfg = make_config("dataset=nuscenes", f"dataset.root={tmp_path}", "dataset.reader.stride=2")
    with pytest.raises(MissingDependencyError):  # good values: on to the devkit
        validate_dataset_config(cfg)


@pytest.mark.slow
def test_prepare_names_a_bad_reader_value_in_one_line(tmp_path) -> None:
    """The command: exit status 1, one line on stderr naming the key and the value."""
    result = run_module(
        [
            "fusion_depth.prepare",
            "dataset=nuscenes",
            f"dataset.root={tmp_path}",
            "dataset.reader.lidar_keyframes=inf",
            f"hydra.run.dir={tmp_path / 'run'}",
        ],
        cwd=tmp_path,
        timeout=120,
    )
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 1 and len(lines) == 1, result.stderr
    assert lines[0].startswith("dataset.reader.lidar_keyframes=inf: expected an integer ≥ 0")
