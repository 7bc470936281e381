"""Declared energy terms: a fitting stage's energy is a table of `Term`s, each a name, an energy
function and the config setting that holds its weight.

A stage's `terms` room holds its table; its phases refer to the `Term` objects themselves, so a
misspelt term is a NameError at import, and `check_weights` (called by each table at import) fails
when a term names a weight its config does not have. The energy of a phase is `weighted_sum` over
its terms, in table order. Adding a loss is one function in `intercap.energies` and one entry in a
stage's table.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable, Iterable


@dataclass(frozen=True)
class Term:
    """One energy term: `energy(evaluation)` gives its unweighted value (per frame, or a scalar), or
    None where it does not apply (no floor, too few frames); its weight is the setting `weight` of
    the config section named by `section` (a stage's own section when empty)."""

    name: str
    energy: Callable[[Any], Any]
    weight: str
    section: str = ""

    def weight_in(self, configs: dict[str, Any]) -> float:
        """The term's weight from `configs` ({section: config}; "" is the stage's own)."""
        return getattr(configs[self.section], self.weight)


def check_weights(table: Iterable[Term], configs: dict[str, type]) -> tuple[Term, ...]:
    """`table` as a tuple, once every term's weight is a field of its section's config class
    ({section: dataclass}) and no two terms share a name; raises ValueError otherwise."""
    table = tuple(table)
    names = [t.name for t in table]
    if len(set(names)) != len(names):
        raise ValueError(f"terms named twice: {sorted({n for n in names if names.count(n) > 1})}")
    for term in table:
        fields = {f.name for f in dataclasses.fields(configs[term.section])}
        if term.weight not in fields:
            raise ValueError(f"term {term.name!r}: its weight {term.weight!r} is not a setting of "
                             f"{configs[term.section].__name__}")
    return table


def evaluate_terms(table: Iterable[Term], evaluation) -> dict:
    """{name: unweighted value} of the terms of `table` that apply to `evaluation`, in table order."""
    values = {}
    for term in table:
        value = term.energy(evaluation)
        if value is not None:
            values[term.name] = value
    return values


def weighted_sum(table: Iterable[Term], values: dict, configs: dict[str, Any], reduce: Callable | None = None):
    """sum over the terms of `table` present in `values` of weight x value (each value passed through
    `reduce` first when given, e.g. a sum over frames), in table order."""
    total = 0
    for term in table:
        if term.name in values:
            value = values[term.name]
            total = total + term.weight_in(configs) * (value if reduce is None else reduce(value))
    return total
