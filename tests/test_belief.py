"""The Dempster-Shafer belief of a cell: worked examples, order independence, unit sum, extreme counts."""

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mcrs.env.belief import belief_masses


def masses(positive: int, negative: int, m_f: float = 0.8, m_e: float = 0.8) -> tuple[float, float, float]:
    empty, full, unknown = belief_masses(torch.tensor(positive), torch.tensor(negative), m_f, m_e)
    return empty.item(), full.item(), unknown.item()


def dempster_sequence(readings: list[bool], m_f: float, m_e: float) -> tuple[float, float, float]:
    """Reference: combine the readings one at a time with Dempster's rule over {E, F, U}."""
    empty, full, unknown = 0.0, 0.0, 1.0
    for positive in readings:
        # A reading is a simple support function: F with m_f (positive) or E with m_e (negative).
        r_empty, r_full = (0.0, m_f) if positive else (m_e, 0.0)
        r_unknown = 1.0 - r_empty - r_full
        conflict = empty * r_full + full * r_empty
        norm = 1.0 - conflict
        empty, full, unknown = (
            (empty * r_empty + empty * r_unknown + unknown * r_empty) / norm,
            (full * r_full + full * r_unknown + unknown * r_full) / norm,
            unknown * r_unknown / norm,
        )
    return empty, full, unknown


def test_spec_worked_examples():
    empty, full, unknown = masses(0, 1)
    assert math.isclose(empty, 0.8, abs_tol=1e-6) and math.isclose(unknown, 0.2, abs_tol=1e-6) and full == 0
    empty, full, unknown = masses(2, 0)
    assert math.isclose(full, 0.96, abs_tol=1e-6) and full >= 0.95
    assert masses(0, 0) == (0.0, 0.0, 1.0)


@settings(max_examples=200, deadline=None)
@given(
    readings=st.lists(st.booleans(), max_size=30),
    m_f=st.floats(0.05, 0.95),
    m_e=st.floats(0.05, 0.95),
    seed=st.integers(0, 10_000),
)
def test_counts_form_equals_sequential_dempster_in_any_order(readings, m_f, m_e, seed):
    shuffled = readings[:]
    torch.manual_seed(seed)
    shuffled = [shuffled[i] for i in torch.randperm(len(shuffled)).tolist()]
    expected = dempster_sequence(readings, m_f, m_e)
    in_other_order = dempster_sequence(shuffled, m_f, m_e)
    got = masses(sum(readings), len(readings) - sum(readings), m_f, m_e)
    for a, b, c in zip(expected, in_other_order, got, strict=True):
        assert math.isclose(a, b, abs_tol=1e-6)  # double rounding grows with the conflict
        assert math.isclose(a, c, abs_tol=2e-5)


@settings(max_examples=300, deadline=None)
@given(
    positive=st.integers(0, 10**7),
    negative=st.integers(0, 10**7),
    m_f=st.floats(0.0, 0.999),
    m_e=st.floats(0.0, 0.999),
)
def test_masses_are_finite_probabilities_summing_to_one(positive, negative, m_f, m_e):
    values = masses(positive, negative, m_f, m_e)
    assert all(math.isfinite(v) and -1e-7 <= v <= 1 + 1e-7 for v in values)
    assert math.isclose(sum(values), 1.0, abs_tol=1e-5)


def test_extreme_counts_where_f_and_e_underflow():
    counts = torch.tensor([0, 1, 10**3, 10**6, 2**31 - 1])
    pos, neg = torch.meshgrid(counts, counts, indexing="ij")
    empty, full, unknown = belief_masses(pos, neg, 0.8, 0.8)
    total = empty + full + unknown
    assert torch.isfinite(total).all() and torch.allclose(total, torch.ones_like(total), atol=1e-5)
    # Many readings of one kind and none of the other: certainty of that kind.
    assert full[-1, 0] == 1.0 and empty[0, -1] == 1.0
    # Equal overwhelming evidence both ways: split evenly, nothing unknown.
    assert torch.isclose(full[3, 3], torch.tensor(0.5)) and unknown[3, 3] == 0


def test_batched_shapes_are_preserved():
    pos = torch.randint(0, 5, (3, 4, 7))
    neg = torch.randint(0, 5, (3, 4, 7))
    for mass in belief_masses(pos, neg, 0.8, 0.8):
        assert mass.shape == (3, 4, 7) and mass.dtype == torch.float32
