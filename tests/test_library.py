"""The library's one active-set parser: what it accepts is exactly the rule, and every
caller's error names the field."""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from epc_offboard.common.errors import EpcError
from epc_offboard.control.library_types import (
    EntryError,
    LibraryEntry,
    parse_active_set,
    parse_entry,
)

N_CON = 12
MAX_ROWS = 4

rows_st = st.one_of(
    st.lists(st.one_of(st.integers(-3, N_CON + 3), st.booleans(), st.floats(0, 5)), max_size=6),
    st.lists(st.integers(-3, N_CON + 3), max_size=6).map(tuple),
    st.text(max_size=4),
    st.none(),
)


def _valid(rows: object) -> bool:
    """The rule, written plainly: a list or tuple of at most MAX_ROWS ints (not bools), each
    in 0..N_CON-1, strictly increasing."""
    return (
        isinstance(rows, list | tuple)
        and len(rows) <= MAX_ROWS
        and all(type(i) is int and 0 <= i < N_CON for i in rows)
        and all(a < b for a, b in itertools.pairwise(rows))
    )


@given(rows_st)
def test_parse_accepts_exactly_sorted_unique_ints_in_range(rows):
    if _valid(rows):
        assert parse_active_set(rows, n_con=N_CON, max_rows=MAX_ROWS) == tuple(rows)
    else:
        with pytest.raises(EntryError):
            parse_active_set(rows, n_con=N_CON, max_rows=MAX_ROWS)


@pytest.mark.parametrize(
    ("rows", "reason"),
    [
        ([2, 1], "sorted and unique"),
        ((1, 1), "sorted and unique"),
        ([0, N_CON], f"index {N_CON} out of range 0..{N_CON - 1}"),
        ([-1], "index -1 out of range"),
        ([True], "tuple of ints"),
        ((1.0,), "tuple of ints"),
        ("1,2", "tuple of ints"),
        (list(range(MAX_ROWS + 1)), f"{MAX_ROWS + 1} active rows exceed {MAX_ROWS}"),
    ],
)
def test_each_rule_names_itself(rows, reason):
    with pytest.raises(EntryError, match=reason) as info:
        parse_active_set(rows, n_con=N_CON, max_rows=MAX_ROWS)
    assert str(info.value).startswith("active_set")
    assert isinstance(info.value, EpcError)
    assert isinstance(info.value, ValueError)


def test_without_a_problem_only_negative_indices_are_out_of_range():
    assert parse_active_set([0, 70000]) == (0, 70000)
    with pytest.raises(EntryError, match="out of range"):
        parse_active_set([-2])


@pytest.mark.parametrize(
    ("importance", "uses", "field"),
    [
        (math.nan, 0, "importance"),
        (math.inf, 0, "importance"),
        (True, 0, "importance"),
        ("1", 0, "importance"),
        (10**400, 0, "importance"),  # beyond any float: an error, not an OverflowError
        (1.0, -1, "uses"),
        (1.0, 1.0, "uses"),
        (1.0, False, "uses"),
    ],
)
def test_entry_fields_are_checked_naming_the_field(importance, uses, field):
    with pytest.raises(EntryError, match=f"^{field} must be"):
        parse_entry((1,), importance, uses)


def test_parse_entry_returns_the_entry_with_a_tuple():
    assert parse_entry([1, 3], 2, 5, "prior", n_con=N_CON) == LibraryEntry((1, 3), 2.0, 5, "prior")
