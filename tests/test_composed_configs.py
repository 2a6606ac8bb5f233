"""Rearranging the config files changes no value a command composes: each command of
tests/helpers/composed.py composes, value for value, what it composed before (the fixtures were
written by the code of commit f6400ed, before the model recipes moved into Python)."""

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


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_command_composes_the_values_it_composed_before(case, monkeypatch) -> None:
    monkeypatch.setenv("FUSION_DEPTH_CACHE", CACHE_DIR)
    expected = yaml.safe_load((FIXTURES / f"{case}.yaml").read_text())
    found = _differences(expected, composed_values(CASES[case]))
    assert not found, f"{' '.join(CASES[case]) or '(defaults)'}: " + "; ".join(found[:8])


def test_every_fixture_is_a_case() -> None:
    assert {path.stem for path in FIXTURES.glob("*.yaml")} == set(CASES)
