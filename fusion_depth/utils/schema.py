"""Rules: what a value may hold, declared once beside the code that takes it (a module's or
model class's ``ARGUMENT_RULES``, by argument name), and checked before anything is built.

A schema maps a name (an argument, or a dotted config key where the config layer places it:
``loss.w_ssim``) to a :class:`Rule`: a test of the resolved value and the words for what it
accepts. A key that is absent is not checked (a config group that does not set it uses the
reader's default). A value that fails gives one line, ``<key>=<value as typed>: expected <what
it accepts>``, raised as :class:`~fusion_depth.errors.ConfigError`.
:func:`fusion_depth.config.validate_config` checks every table of the package in turn.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from fusion_depth.utils.overrides import show


@dataclass(frozen=True)
class Rule:
    """What a config value may be: ``ok(value)`` is true for the values it accepts (resolved,
    containers as plain lists and dicts), ``expected`` names them for the error message."""

    ok: Callable[[Any], bool]
    expected: str

    def or_null(self, meaning: str) -> Rule:
        """The same rule, also accepting null, which means ``meaning`` (``a number ≥ 0, or null
        (no clipping)``)."""
        return Rule(lambda v: v is None or self.ok(v), f"{self.expected}, or null ({meaning})")


# A schema: dotted key → its rule.
Schema = Mapping[str, Rule]


def is_int(value: Any) -> bool:
    """An int, not a bool (YAML's ``true`` is no count)."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    """An int or float, not a bool."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def one_of(*allowed: Any) -> Rule:
    """Exactly one of ``allowed``, type included (``1`` is not ``true``)."""
    return Rule(
        lambda v: any(type(v) is type(a) and v == a for a in allowed),
        f"one of {', '.join(show(a) for a in allowed)}",
    )


BOOLEAN = one_of(True, False)
POSITIVE_INT = Rule(lambda v: is_int(v) and v >= 1, "an integer ≥ 1")
NON_NEGATIVE_INT = Rule(lambda v: is_int(v) and v >= 0, "an integer ≥ 0")
NON_NEGATIVE = Rule(lambda v: is_number(v) and v >= 0, "a number ≥ 0")
POSITIVE = Rule(lambda v: is_number(v) and v > 0, "a number > 0")
PROBABILITY = Rule(lambda v: is_number(v) and 0 <= v <= 1, "a probability in [0, 1]")
