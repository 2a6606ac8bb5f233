"""Rearranging the config files changes no value a command composes: each command of
tests/helpers/composed.py composes, value for value, what it composed before (the fixtures were
written by the code of commit f6400ed, before the model recipes moved into Python). A key added
since is named in :data:`ADDED_SINCE` with the value it holds when its feature is not asked for."""

from __future__ import annotations

import pytest
import yaml
from helpers import REPO
from helpers.composed import CACHE_DIR, CASES, composed_values

FIXTURES = REPO / "tests" / "fixtures" / "composed"


def _differences(expected: object, got: object, at: str = "") -> list[str]:
    if isinstance(expected, dict) and isinstance(got, dict):
        found = []
        for key in sorted(set(expected) | set(got), key=str):
            where = f"{at}.{key}" if at else str(key)
            if key not in got:
                found.append(f"{where}: missing (was {expected[key]!r})")
            elif key not in expected:
                found.append(f"{where}: new ({got[key]!r})")
            else:
                found += _differences(expected[key], got[key], where)
        return found
    return [] if expected == got else [f"{at}: {got!r} (was {expected!r})"]


# Keys that features after the fixtures added, with the value each must hold when the command
# does not ask for the feature: dropped from the comparison once checked.
NO_PRIOR = {
    "name": "none",
    "weights": None,
    "input_size": None,
    "kind": None,
    "max_depth": None,
    "dropout": 0.0,
    "cache": False,
}
ADDED_SINCE = {"prior": NO_PRIOR}  # the prior group (prior=none); DenseDepth reads it too
# The augmentation's geometry and saturation (each model's own augmentation): the paper's has
# none. A fixture that holds one of these keys (its recipe sets it) compares it as any other.
NO_GEOMETRY = {
    "saturation": None,
    "color_each": False,
    "crop": None,
    "crop_center": None,
    "crop_placement": "uniform",
    "scale": None,
    "rotation": 0.0,
    "resample": "bilinear",
    "outlier_filter": None,
}
ADDED_IF_PRESENT = {
    ("model", "net", "prior"): NO_PRIOR,
    ("model", "net", "fake_point_probability"): 0.0,  # RadarNet's fake points: none
    ("model", "net", "lidar_loss_weight"): 0.0,
    ("model", "net", "fake_column_noise"): None,  # RadarNet's second loss term: none
    ("dataset", "reader", "camera_height"): [1.4, 1.7],  # the built-in dataset's car camera
    ("dataset", "reader", "fov_range"): None,
    **{("augment", key): value for key, value in NO_GEOMETRY.items()},
    **{("model", "augmentation", key): value for key, value in NO_GEOMETRY.items()},
}


def _node(values: dict, parents: list[str]) -> dict | None:
    for parent in parents:
        values = values.get(parent) if isinstance(values, dict) else None
    return values if isinstance(values, dict) else None


def _without_added_keys(values: dict, expected: dict) -> dict:
    for key, default in ADDED_SINCE.items():
        assert values.pop(key) == default, key
    for path, default in ADDED_IF_PRESENT.items():
        *parents, key = path
        node, fixture = _node(values, parents), _node(expected, parents)
        if node is not None and key in node and key not in (fixture or {}):
            assert node.pop(key) == default, ".".join(path)
    return values


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_command_composes_the_values_it_composed_before(case, monkeypatch) -> None:
    monkeypatch.setenv("FUSION_DEPTH_CACHE", CACHE_DIR)
    expected = yaml.safe_load((FIXTURES / f"{case}.yaml").read_text())
    found = _differences(expected, _without_added_keys(composed_values(CASES[case]), expected))
    assert not found, f"{' '.join(CASES[case]) or '(defaults)'}: " + "; ".join(found[:8])


def test_every_fixture_is_a_case() -> None:
    assert {path.stem for path in FIXTURES.glob("*.yaml")} == set(CASES)
