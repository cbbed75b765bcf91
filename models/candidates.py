"""Candidate dictionaries for structure selection: monomials of lagged y and x.

A dictionary holds every monomial of the lagged variables

    y[t-1] … y[t-ny],    x[t-d] … x[t-d-nx+1]    (d the input delay)

of total degree 1 … ``degree``, optionally the constant ``1`` and terms named by the user.
With ny = nx = 4, d = 1 and degree 3 there are C(8 + 3, 3) = 165 candidates, the constant
included. They are ordered by degree, then as ``itertools.combinations_with_replacement``
orders the variables (y lags before x lags, increasing lag): the order SysIdentPy uses, so
that candidates whose error reduction ratios tie exactly are taken in the same order.

The candidate matrix P has one column per candidate and one row per equation t = L … N−1
of each record, L being the largest lag in the dictionary; records are stacked, so no lag
reaches across the boundary between two records.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from itertools import combinations_with_replacement

import numpy as np
from numpy.typing import ArrayLike

from models.errors import InputError
from models.signals import checked_records
from models.terms import Factor, Term, max_lag, parse_terms, regressor_matrix


def candidate_terms(
    degree: int = 3,
    ny: int = 4,
    nx: int = 4,
    delay: int = 1,
    *,
    constant: bool = True,
    extra: Iterable[str | Term] = (),
) -> tuple[Term, ...]:
    """All monomials of y[t-1 … t-ny] and x[t-delay … t-delay-nx+1] up to ``degree``.

    The constant comes first when ``constant`` is true; ``extra`` terms (names such as
    ``"y[t-1]^5"`` or terms) are appended and must not repeat a generated one.
    """
    for name, value, least in (("degree", degree, 1), ("ny", ny, 1), ("nx", nx, 1), ("delay", delay, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            raise InputError(f"{name} must be an integer >= {least}, got {value!r}")
    variables = [Factor("y", lag) for lag in range(1, ny + 1)]
    variables += [Factor("x", lag) for lag in range(delay, delay + nx)]
    terms = [Term()] if constant else []
    for power in range(1, degree + 1):
        terms += [Term.of(combo) for combo in combinations_with_replacement(variables, power)]
    named = tuple(extra)
    extra_terms = parse_terms(named) if named else ()
    generated = set(terms)
    for term in extra_terms:
        if term in generated:
            raise InputError(f"extra term {term.name} is already in the dictionary")
    return (*terms, *extra_terms)


@dataclass(frozen=True)
class CandidateMatrix:
    """Candidate regressors of one or more records, stacked.

    Attributes
    ----------
    terms : the candidates, one per column of ``P``.
    P : regressor matrix, shape (n_obs, len(terms)), column-major (Fortran) order.
    target : y[t] of the same equations.
    scale : Euclidean norm of each column of P.
    lag : L, the time index of each record's first equation.
    rows : number of equations each record contributes.
    """

    terms: tuple[Term, ...]
    P: np.ndarray
    target: np.ndarray
    scale: np.ndarray
    lag: int
    rows: tuple[int, ...]

    @property
    def n_obs(self) -> int:
        return self.P.shape[0]


def candidate_matrix(
    terms: Sequence[str | Term],
    records: Iterable[tuple[ArrayLike, ArrayLike]],
    lag: int | None = None,
) -> CandidateMatrix:
    """Build P once for all candidates, reusing lower-degree columns.

    A column whose term has a parent in the dictionary (the same monomial with the power of
    one lagged y or x lowered by one) is the parent's column times that lagged signal: one
    multiplication per column. Other columns (degree one, the constant, extra terms without a
    parent) come from :func:`models.terms.regressor_matrix`. ``lag`` defaults to the largest
    lag of the terms.
    """
    parsed = parse_terms(terms)
    L = max_lag(parsed) if lag is None else lag
    if max_lag(parsed) > L:
        raise InputError(f"lag {L} is shorter than the largest lag {max_lag(parsed)} of the candidates")
    checked = checked_records(records, L + 1)
    rows = tuple(len(y) - L for _, y in checked)
    n_obs = sum(rows)
    if n_obs <= len(parsed):
        raise InputError(
            f"{n_obs} usable samples cannot rank {len(parsed)} candidate terms: supply longer "
            "records or a smaller dictionary (lower degree or fewer lags)"
        )
    P = np.empty((n_obs, len(parsed)), order="F")
    target = np.empty(n_obs)
    plan = _parents(parsed)
    start = 0
    for (x, y), count in zip(checked, rows, strict=True):
        block = slice(start, start + count)
        signals = {"y": y, "x": x}
        target[block] = y[L:]
        for column, (term, step) in enumerate(zip(parsed, plan, strict=True)):
            if step is None:
                P[block, column] = regressor_matrix([term], x, y, L)[0][:, 0]
            else:
                parent, factor = step
                window = signals[factor.signal][L - factor.lag : len(y) - factor.lag]
                np.multiply(P[block, parent], window, out=P[block, column])
        start += count
    scale = np.sqrt(np.einsum("ij,ij->j", P, P))
    overflowed = [parsed[j].name for j in np.flatnonzero(~np.isfinite(scale))]
    if overflowed:
        raise InputError(
            f"candidate {', '.join(overflowed)} overflows on these signals: "
            "lower the degree or scale the data"
        )
    return CandidateMatrix(parsed, P, target, scale, L, rows)


def _parents(terms: Sequence[Term]) -> list[tuple[int, Factor] | None]:
    """For each term, the column of a parent term listed before it and the lagged y or x that
    multiplies the parent into the term, or None when it has no parent."""
    built: dict[Term, int] = {}
    plan: list[tuple[int, Factor] | None] = []
    for column, term in enumerate(terms):
        step = None
        for index, factor in enumerate(term.factors):
            if factor.signal not in ("y", "x"):
                continue
            lowered = (Factor(factor.signal, factor.lag, factor.power - 1),) if factor.power > 1 else ()
            parent = built.get(Term((*term.factors[:index], *lowered, *term.factors[index + 1 :])))
            if parent is not None:
                step = (parent, Factor(factor.signal, factor.lag))
                break
        plan.append(step)
        built[term] = column
    return plan
