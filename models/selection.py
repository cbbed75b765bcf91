"""Structure selection by forward regression orthogonal least squares (FROLS, SPEC §3).

Greedy selection from a candidate matrix P = [p_1 … p_M] for the target y (Billings, Chen &
Korenberg 1989). After k steps the chosen columns span the orthonormal basis q_1 … q_k; each
remaining candidate's part orthogonal to them is w_j = p_j − Σ_s (q_sᵀp_j)·q_s, and its
error reduction ratio

    ERR_j = (w_jᵀy)² / (w_jᵀw_j · yᵀy),

the share of the target's energy yᵀy (not centred) it would explain. Step k + 1 takes the
candidate of largest ERR. This is the definition SysIdentPy's FROLS uses (without the eps
it adds to every value). The residual sum of squares after k steps is RSS_k = ‖r_k‖², with
r_k = y − Σ_s (q_sᵀy)·q_s, so the error-to-signal ratio is ESR_k = RSS_k/yᵀy = 1 − Σ ERR.

Stopping rules: a fixed number of terms; ESR_k below a tolerance ρ (Billings' 1 − ΣERR < ρ);
or the minimum over the path of an information criterion, σ²_k = RSS_k/N and n_k parameters,

    AIC = N·ln σ²_k + 2·n_k,   BIC = N·ln σ²_k + n_k·ln N,   FPE = N·ln σ²_k + N·ln((N + n_k)/(N − n_k)),

the forms SysIdentPy uses (it takes σ² as the residuals' variance with ddof = 1 and stops at
the first local minimum; here σ² is the maximum-likelihood RSS/N and the global minimum over
the path is taken). All are evaluated along the single greedy path: one pass, not a re-run
per model size. Optional pruning then drops terms, one at a time, while the rule still holds.

Grouped selection (FNARX, SPEC §4) ranks blocks of columns: term j carries the p columns
φ_j(t)·G_i(k_e) of its functional basis, and the ERR of a block is the energy of the
residual's projection on the block's orthogonalised span, ERR_j = c_jᵀ·G_j⁻¹·c_j / yᵀy with
c_j = W_jᵀr and G_j = W_jᵀW_j.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import blas

from models.basis import BasisFamily, FunctionalBasis
from models.candidates import CandidateMatrix, candidate_matrix
from models.errors import InputError
from models.fnarx import FNARX, Experiment, fit_fnarx
from models.narx import NARX
from models.regression import least_squares
from models.terms import Term, parse_terms

Criterion = Literal["aic", "bic", "fpe"]
CRITERIA: tuple[Criterion, ...] = ("aic", "bic", "fpe")
# A candidate whose part orthogonal to the chosen terms keeps less than this fraction of its
# norm is treated as dependent on them: rounding (~eps of the column) would already be ~1e-8 of
# what is left of it, and a model holding it would have a condition number of 1e8 or more.
DEFAULT_TOLERANCE = 1e-8
# The precise path keeps candidates down to this fraction: its twice-projected remainders are
# exact to ~eps of the column, so a remainder of 1e-13 is still known to three digits, and on
# noise-free data the terms that matter are collinear to ~1e-8 (their remainders ~1e-8 to 1e-13).
PRECISE_TOLERANCE = 1e-13
# Squared remaining norms are downdated, d_j ← d_j − (q_kᵀp_j)², which loses relative accuracy
# ~eps·d_ref/d_j after falling from d_ref; below √eps·d_ref they are recomputed from the
# explicitly orthogonalised column (LAPACK's pivoted QR, xLAQP2, uses the same threshold), so
# each d_j keeps a relative accuracy of ~√eps ≈ 1.5e-8: ERR values are ranked to that accuracy.
_DOWNDATE_LIMIT = float(np.sqrt(np.finfo(np.float64).eps))
# Numerators p_jᵀr are updated, n_j ← n_j − (q_kᵀr)·(q_kᵀp_j), with rounding ~eps·‖p_j‖·‖r‖ of
# the residual they were last computed from; they are recomputed as Pᵀr once ‖r‖ has fallen by
# this factor since, so their error stays within ~10·k·eps·‖p_j‖·‖r‖. (On the paper's data
# that is 4 recomputations in 15 steps, on steps whose Pᵀq_k then comes without a product.)
_REFRESH = 10.0
# Columns orthogonalised at once when recomputing remaining norms (bounds the temporary).
_CHUNK = 32

Progress = Callable[[int], None]


def information_criterion(name: str, rss: ArrayLike, n_obs: int, n_params: ArrayLike) -> np.ndarray:
    """AIC, BIC or FPE (module docstring) of models with residual sum of squares ``rss``."""
    check_criterion(name)
    k = np.asarray(n_params, dtype=np.float64)
    sigma2 = np.maximum(np.asarray(rss, dtype=np.float64) / n_obs, np.finfo(np.float64).tiny)
    fit = n_obs * np.log(sigma2)
    if name == "aic":
        return fit + 2 * k
    if name == "bic":
        return fit + k * np.log(n_obs)
    return fit + n_obs * np.log((n_obs + k) / (n_obs - k))


def check_criterion(name: str | None) -> None:
    if name not in CRITERIA:
        raise InputError(f"unknown criterion {name!r}; choose one of {', '.join(CRITERIA)}")


@dataclass(frozen=True)
class SelectionPath:
    """The greedy path: step k took candidate (or block) ``order[k]``.

    Attributes
    ----------
    order : candidate indices in the order chosen.
    err : ERR of each step.
    rss : residual sum of squares after each step.
    energy : yᵀy.
    n_obs : number of equations N.
    group_size : parameters each step adds (1, or p for a functional basis).
    """

    order: np.ndarray
    err: np.ndarray
    rss: np.ndarray
    energy: float
    n_obs: int
    group_size: int = 1

    def __len__(self) -> int:
        return len(self.order)

    @property
    def esr(self) -> np.ndarray:
        """RSS_k / yᵀy after each step: 1 − ΣERR, computed from the residual itself."""
        return self.rss / self.energy

    def criterion(self, name: str) -> np.ndarray:
        """The information criterion after each step."""
        n_params = self.group_size * np.arange(1, len(self) + 1)
        return information_criterion(name, self.rss, self.n_obs, n_params)


def frols(
    P: np.ndarray,
    target: np.ndarray,
    max_terms: int,
    *,
    err_tolerance: float | None = None,
    tolerance: float = DEFAULT_TOLERANCE,
    scale: np.ndarray | None = None,
    forced: Sequence[int] = (),
    progress: Progress | None = None,
) -> SelectionPath:
    """Greedy FROLS path of up to ``max_terms`` columns of P (which is not modified).

    Left-looking Gram–Schmidt: only the chosen columns are orthogonalised, explicitly and
    twice (q_k to working precision). Every candidate keeps its squared remaining norm
    d_j = ‖w_j‖²/‖p_j‖² and numerator n_j = p_jᵀr/‖p_j‖ (= w_jᵀr, as r ⟂ q_1 … q_k), both
    updated from the one product Pᵀq_k per step, so a step reads P once and writes nothing:
    O(N·M) time and O(N·max_terms) extra memory, P (N×M) being the only large array. The
    first ``forced`` columns are taken in the order given. Candidates with d_j ≤ tolerance²
    are skipped as dependent. The path ends early when ESR < ``err_tolerance`` or no
    independent candidate is left. ``scale`` are the column norms if already known.
    """
    path = _Downdates(P, target, max_terms, scale)
    order: list[int] = []
    err: list[float] = []
    rss: list[float] = []
    floor = tolerance**2
    while len(order) < max_terms:
        live = ~path.taken & (path.remaining > floor)
        if not live.any():
            break
        k = len(order)
        j = forced[k] if k < len(forced) else path.strongest(live)
        q = _orthogonalise(P[:, j] * path.inverse[j], path.basis[:, :k])
        norm2 = float(q @ q)
        if k < len(forced) and norm2 <= floor:
            raise InputError(f"forced column {j} is zero or dependent on the columns forced before it")
        if norm2 <= floor:
            # The downdated norm overstated it: the candidate is dependent after all.
            path.remaining[j] = norm2
            continue
        q /= np.sqrt(norm2)
        g, current = path.take(j, k, q, rss[-1] if rss else path.energy)
        order.append(j)
        err.append(g * g / path.energy)
        rss.append(current)
        if progress is not None:
            progress(len(order))
        if err_tolerance is not None and current < err_tolerance * path.energy:
            break
    return SelectionPath(
        np.array(order, dtype=np.intp), np.array(err), np.array(rss), path.energy, P.shape[0]
    )


class _Downdates:
    """What :func:`frols` keeps of its path as it grows: the orthonormal basis q_1 … q_k, the
    residual r, and every candidate's numerator n_j and squared remaining norm d_j, downdated
    at each step and recomputed where they lose accuracy (``_REFRESH``, ``_DOWNDATE_LIMIT``)."""

    def __init__(self, P: np.ndarray, target: np.ndarray, max_terms: int, scale: np.ndarray | None) -> None:
        n_obs, n_cand = P.shape
        norms = np.sqrt(np.einsum("ij,ij->j", P, P)) if scale is None else scale
        self.P = P
        self.usable = norms > 0
        self.inverse = np.where(self.usable, 1.0 / np.where(self.usable, norms, 1.0), 0.0)
        self.energy = float(target @ target)
        self.residual = np.array(target, dtype=np.float64)
        self.basis = np.empty((n_obs, max_terms), order="F")
        self.numerator = (P.T @ self.residual) * self.inverse
        self.remaining = self.usable.astype(np.float64)
        self.reference = np.ones(n_cand)
        self.taken = np.zeros(n_cand, dtype=bool)
        self.refreshed_at, self.exact = self.energy, True

    def strongest(self, live: np.ndarray) -> int:
        """The ``live`` candidate of largest ERR n_j²/d_j."""
        ratio = np.full(len(self.taken), -1.0)
        ratio[live] = self.numerator[live] ** 2 / self.remaining[live]
        return int(np.argmax(ratio))

    def take(self, j: int, k: int, q: np.ndarray, before: float) -> tuple[float, float]:
        """Candidate ``j`` enters as step ``k`` with its orthonormal ``q``: the residual is
        projected off it (twice), the numerators and remaining norms downdated; g = q_kᵀr and
        the residual sum of squares after it (``before``: the one before it)."""
        self.basis[:, k] = q
        residual = self.residual
        g = float(q @ residual)
        residual -= g * q
        again = float(q @ residual)
        residual -= again * q
        g += again
        current = float(residual @ residual)
        self._downdate(q, g, before, current)
        self.taken[j] = True
        self._recompute_stale(k)
        return g, current

    def _downdate(self, q: np.ndarray, g: float, before: float, current: float) -> None:
        P, inverse = self.P, self.inverse
        if current * _REFRESH**2 < self.refreshed_at:
            fresh = (P.T @ self.residual) * inverse
            if self.exact and current * _REFRESH**2 < before:
                # This step alone removed all but 1/10 of ‖r‖: q_k = (r_{k−1} − r_k)/g with
                # |g| > 0.99·‖r_{k−1}‖, so Pᵀq_k is the difference of two exact numerator
                # vectors, as accurate as a product with P and one pass over P cheaper.
                projection = (self.numerator - fresh) / g
            else:
                projection = (P.T @ q) * inverse
            self.numerator, self.refreshed_at, self.exact = fresh, current, True
        else:
            projection = (P.T @ q) * inverse
            self.numerator -= g * projection
            self.exact = False
        self.remaining -= projection**2

    def _recompute_stale(self, k: int) -> None:
        """Remaining norms that have fallen below ``_DOWNDATE_LIMIT`` of their last exact value,
        recomputed from the columns orthogonalised against q_1 … q_(k+1)."""
        stale = np.flatnonzero(
            ~self.taken & self.usable & (self.remaining < _DOWNDATE_LIMIT * self.reference)
        )
        for start in range(0, stale.size, _CHUNK):
            chunk = stale[start : start + _CHUNK]
            W = _orthogonalise(self.P[:, chunk] * self.inverse[chunk], self.basis[:, : k + 1])
            self.remaining[chunk] = self.reference[chunk] = np.einsum("ij,ij->j", W, W)


def frols_grouped(
    B: np.ndarray,
    target: np.ndarray,
    group_size: int,
    max_terms: int,
    *,
    err_tolerance: float | None = None,
    tolerance: float = DEFAULT_TOLERANCE,
    overwrite: bool = False,
    progress: Progress | None = None,
) -> SelectionPath:
    """Greedy FROLS path over blocks of ``group_size`` columns of B.

    Block j is the columns j, j + M, …, j + (p−1)·M (M = number of blocks). Right-looking
    block Gram–Schmidt: after each step the chosen block is orthonormalised (QR, after one
    more orthogonalisation against the basis) and projected out of every column of B in
    place, W ← W − Q_b·(Q_bᵀW). A block is dependent when the smallest eigenvalue of the Gram
    matrix of its remaining (originally unit-norm) columns is ≤ tolerance². The projection is
    applied twice each step, so that the path stays exact to rounding level. B is overwritten
    when ``overwrite`` is true and B is a Fortran-ordered float64 array, else copied.
    """
    n_obs, total = B.shape
    p = group_size
    if p < 1 or total % p:
        raise InputError(f"{total} columns do not split into blocks of {group_size}")
    n_blocks = total // p
    W = B if overwrite and B.dtype == np.float64 and B.flags.f_contiguous else np.array(B, order="F")
    norms = np.sqrt(np.einsum("ij,ij->j", W, W))
    usable = (norms > 0).reshape(p, n_blocks).all(axis=0)
    W *= np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 0.0)
    blocks = W.reshape((n_obs, n_blocks, p), order="F")  # blocks[:, j, i] is column j + i·M
    energy = float(target @ target)
    residual = np.array(target, dtype=np.float64)
    basis = np.empty((n_obs, max_terms * p), order="F")
    taken = ~usable
    order: list[int] = []
    err: list[float] = []
    rss: list[float] = []
    while len(order) < max_terms:
        numerator = (W.T @ residual).reshape(p, n_blocks).T
        gram = np.empty((n_blocks, p, p))
        for a in range(p):
            for b in range(a, p):
                gram[:, a, b] = gram[:, b, a] = np.einsum("ij,ij->j", blocks[:, :, a], blocks[:, :, b])
        eigenvalues, eigenvectors = np.linalg.eigh(gram)
        live = ~taken & (eigenvalues[:, 0] > tolerance**2)
        if not live.any():
            break
        along = np.einsum("mab,ma->mb", eigenvectors[live], numerator[live])
        ratio = np.full(n_blocks, -1.0)
        ratio[live] = np.sum(along**2 / eigenvalues[live], axis=1)
        j = int(np.argmax(ratio))
        used = len(order) * p
        chosen = _orthogonalise(blocks[:, j, :].copy(), basis[:, :used])
        Q, R = np.linalg.qr(chosen)
        taken[j] = True
        if np.min(np.abs(np.diag(R))) <= tolerance:
            continue
        basis[:, used : used + p] = Q
        g = Q.T @ residual
        residual -= Q @ g
        residual -= Q @ (Q.T @ residual)
        # Twice: one pass leaves W orthogonal to Q only to ~eps·‖W‖/‖W⊥‖, which ruins the
        # ranking once the residual nears rounding level (noise-free data); twice is enough.
        for _ in range(2):
            blas.dgemm(-1.0, Q, Q.T @ W, beta=1.0, c=W, overwrite_c=True)
        current = float(residual @ residual)
        order.append(j)
        err.append(float(g @ g) / energy)
        rss.append(current)
        if progress is not None:
            progress(len(order))
        if err_tolerance is not None and current < err_tolerance * energy:
            break
    return SelectionPath(np.array(order, dtype=np.intp), np.array(err), np.array(rss), energy, n_obs, p)


def _orthogonalise(A: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """A − basis·(basisᵀA), twice (classical Gram–Schmidt with reorthogonalisation), in place."""
    if basis.shape[1]:
        for _ in range(2):
            A -= basis @ (basis.T @ A)
    return A


@dataclass(frozen=True)
class _Rule:
    """One stopping rule: how long the path runs and how many of its steps are kept."""

    kind: Literal["n_terms", "criterion", "err_tolerance"]
    length: int
    criterion: Criterion | None = None
    err_tolerance: float | None = None

    def select(self, path: SelectionPath, fixed: int) -> tuple[int, str]:
        """The number of path steps kept (at least ``fixed``) and what stopped the selection."""
        if self.kind == "criterion":
            assert self.criterion is not None
            first = max(fixed, 1)
            return first + int(np.argmin(path.criterion(self.criterion)[first - 1 :])), self.criterion
        complete = len(path) == self.length
        if self.kind == "err_tolerance":
            assert self.err_tolerance is not None
            if path.esr[-1] < self.err_tolerance:
                return len(path), "err_tolerance"
            return len(path), "max_terms" if complete else "exhausted"
        return len(path), "n_terms" if complete else "exhausted"

    def allows_removal(self, rss: float, rss_before: float, n_params: int, path: SelectionPath) -> bool:
        """Whether a model with ``n_params`` parameters and ``rss`` still satisfies the rule,
        against the model one term larger with ``rss_before``."""
        if self.kind == "err_tolerance":
            assert self.err_tolerance is not None
            return rss < self.err_tolerance * path.energy
        assert self.criterion is not None
        after, before = information_criterion(
            self.criterion, [rss, rss_before], path.n_obs, [n_params, n_params + path.group_size]
        )
        return bool(after <= before)


def _rule(
    n_terms: int | None,
    criterion: str | None,
    err_tolerance: float | None,
    max_terms: int,
    n_candidates: int,
    prune: bool,
) -> _Rule:
    given = [
        name
        for name, value in (("n_terms", n_terms), ("criterion", criterion), ("err_tolerance", err_tolerance))
        if value is not None
    ]
    if len(given) > 1:
        raise InputError(f"choose one stopping rule, not {' and '.join(given)}")
    if isinstance(max_terms, bool) or not isinstance(max_terms, int) or max_terms < 1:
        raise InputError(f"max_terms must be an integer >= 1, got {max_terms!r}")
    length = min(max_terms, n_candidates)
    if n_terms is not None:
        if isinstance(n_terms, bool) or not isinstance(n_terms, int) or not 1 <= n_terms <= n_candidates:
            raise InputError(
                f"n_terms must be an integer from 1 to {n_candidates} (the candidates), got {n_terms!r}"
            )
        if prune:
            raise InputError("pruning needs a criterion or an ERR tolerance to decide which terms to drop")
        return _Rule("n_terms", n_terms)
    if err_tolerance is not None:
        if not 0 < err_tolerance < 1:
            raise InputError(f"err_tolerance must lie between 0 and 1 (a share of yᵀy), got {err_tolerance}")
        return _Rule("err_tolerance", length, err_tolerance=float(err_tolerance))
    name = "bic" if criterion is None else str(criterion).lower()
    check_criterion(name)
    return _Rule("criterion", length, criterion=name)  # type: ignore[arg-type]  # checked above


def _prune(
    columns: np.ndarray, target: np.ndarray, path: SelectionPath, rule: _Rule, fixed: int
) -> list[int]:
    """Backward elimination: the blocks (of p = path.group_size consecutive columns) kept.

    While the model has more than ``fixed`` blocks, the block (beyond the first ``fixed``)
    whose removal raises the RSS least is dropped if the rule still holds without it. The RSS
    of each reduced model comes from the triangular factor R of [Φ | y] (Φ column-scaled):
    dropping columns of R and re-triangularising leaves ‖residual‖ in the last diagonal entry.
    """
    p = path.group_size
    R = np.linalg.qr(np.column_stack([columns / np.linalg.norm(columns, axis=0), target]), mode="r")
    kept = list(range(columns.shape[1] // p))
    rss = float(R[-1, -1] ** 2)
    while len(kept) > max(fixed, 1):
        trials = []
        for block in kept[fixed:]:
            cols = [c for b in kept if b != block for c in range(b * p, (b + 1) * p)]
            reduced = np.linalg.qr(R[:, [*cols, R.shape[1] - 1]], mode="r")
            trials.append((float(reduced[-1, -1] ** 2), block))
        trial_rss, block = min(trials)
        if not rule.allows_removal(trial_rss, rss, (len(kept) - 1) * p, path):
            break
        kept.remove(block)
        rss = trial_rss
    return kept


def _ordered_err(columns: np.ndarray, target: np.ndarray, group_size: int, energy: float) -> np.ndarray:
    """ERR of each block in the given order: ‖(Qᵀy) of its rows‖²/yᵀy from the QR of [Φ | y]."""
    R = np.linalg.qr(np.column_stack([columns / np.linalg.norm(columns, axis=0), target]), mode="r")
    return (R[:-1, -1] ** 2).reshape(-1, group_size).sum(axis=1) / energy


@dataclass(frozen=True)
class _Selected:
    """Fields shared by the NARX and FNARX selection results.

    Attributes
    ----------
    err : ERR of each selected term, in the model's term order (recomputed in that order
        after pruning).
    esr : RSS/yᵀy of the selected model on the selection data.
    path : the greedy path (indices into ``candidates``).
    candidates : the dictionary the terms were selected from.
    criterion : the information criterion used, if any.
    stopped_by : ``n_terms``, ``err_tolerance``, a criterion's name, ``max_terms`` (the ERR
        tolerance was not reached within max_terms) or ``exhausted`` (no independent
        candidate was left).
    removed : terms dropped by pruning, in the order of the path.
    """

    err: np.ndarray
    esr: float
    path: SelectionPath
    candidates: tuple[Term, ...]
    criterion: Criterion | None
    stopped_by: str
    removed: tuple[Term, ...]

    @property
    def path_terms(self) -> tuple[Term, ...]:
        return tuple(self.candidates[i] for i in self.path.order)

    def path_table(self) -> list[dict[str, Any]]:
        """One row per greedy step: term, ERR, ESR and the criterion if one was used."""
        values = self.path.criterion(self.criterion) if self.criterion else None
        rows = []
        for k, term in enumerate(self.path_terms):
            row: dict[str, Any] = {
                "term": term.name,
                "err": float(self.path.err[k]),
                "esr": float(self.path.esr[k]),
            }
            if values is not None and self.criterion is not None:
                row[self.criterion] = float(values[k])
            rows.append(row)
        return rows

    def to_dict(self) -> dict[str, Any]:
        return {
            "err": self.err.tolist(),
            "esr": self.esr,
            "n_candidates": len(self.candidates),
            "criterion": self.criterion,
            "stopped_by": self.stopped_by,
            "removed": [term.name for term in self.removed],
            "path": self.path_table(),
        }


@dataclass(frozen=True)
class NarxSelection(_Selected):
    """Result of :func:`select_narx`; ``model`` is the least-squares fit of the selected terms."""

    model: NARX

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible: ``terms`` is readable by ``narxwatch train … --terms``."""
        return model_fields(self.model) | super().to_dict()


def model_fields(model: NARX) -> dict[str, Any]:
    """A selected model as a selection's JSON gives it: terms (readable by ``narxwatch train …
    --terms``), θ with standard errors, σ̂² and the number of equations."""
    return {
        "terms": model.term_names,
        "theta": model.theta.tolist(),
        "standard_errors": model.standard_errors().tolist(),
        "sigma2": model.sigma2,
        "n_obs": model.n_obs,
    }


@dataclass(frozen=True)
class FnarxSelection(_Selected):
    """Result of :func:`select_fnarx`; ``model`` is the FNARX fit of the selected terms."""

    model: FNARX


def select_narx(
    records: Iterable[tuple[ArrayLike, ArrayLike]],
    candidates: Sequence[str | Term],
    *,
    n_terms: int | None = None,
    criterion: str | None = None,
    err_tolerance: float | None = None,
    max_terms: int = 20,
    prune: bool = False,
    include: Sequence[str | Term] = (),
    tolerance: float | None = None,
    precise: bool = False,
    progress: Progress | None = None,
) -> NarxSelection:
    """Select NARX terms from ``candidates`` by FROLS on one or more records.

    One stopping rule: ``n_terms`` (a fixed number), ``err_tolerance`` (stop once ESR < ρ,
    within ``max_terms``) or ``criterion`` (``aic``, ``bic`` — the default — or ``fpe``,
    minimised over a path of ``max_terms``). ``prune`` then drops terms while the rule holds.
    ``include`` names candidates taken first and always kept (known physics, or a model whose
    extension is sought). Every record contributes its equations t = L … N−1 (L the
    dictionary's largest lag), so lags never cross records; the parameters are least-squares
    estimates on those equations.

    ``precise`` runs the path on explicitly orthogonalised candidates (:func:`frols_grouped`,
    twice-projected Gram–Schmidt) instead of the fast updates of :func:`frols`: ~20× slower, and
    exact down to rounding level, which noise-free data needs — there the cubic regressors of an
    oversampled response differ from each other by ~1e-8, and the updated norms and numerators
    of the fast path lose the digits that rank them once the residual nears 1e-12 of y.
    ``tolerance`` (the remaining-norm fraction below which a candidate counts as dependent)
    defaults to ``DEFAULT_TOLERANCE``, or ``PRECISE_TOLERANCE`` on the precise path.

    Examples
    --------
    The three terms of a second-order structure, found among the 14 monomials of degree 2 in
    y[t-1], y[t-2], x[t-1] and x[t-2]:

    >>> import numpy as np
    >>> from models.candidates import candidate_terms
    >>> rng = np.random.default_rng(0)
    >>> x, y = rng.standard_normal(2000), np.zeros(2000)
    >>> for t in range(2, 2000):
    ...     y[t] = 1.5 * y[t - 1] - 0.7 * y[t - 2] + x[t - 1] + 0.01 * rng.standard_normal()
    >>> candidates = candidate_terms(degree=2, ny=2, nx=2, delay=1, constant=False)
    >>> selection = select_narx([(x, y)], candidates, n_terms=3)
    >>> sorted(term.name for term in selection.model.terms)
    ['x[t-1]', 'y[t-1]', 'y[t-2]']
    """
    if tolerance is None:
        tolerance = PRECISE_TOLERANCE if precise else DEFAULT_TOLERANCE
    dictionary = candidate_matrix(candidates, records)
    rule = _rule(n_terms, criterion, err_tolerance, max_terms, len(dictionary.terms), prune)
    forced = _positions(dictionary.terms, include)
    if len(forced) > rule.length:
        raise InputError(
            f"{len(forced)} included terms exceed the {rule.length} terms the selection may take"
        )
    path = _path(dictionary, rule, forced, tolerance, precise, progress)
    if not len(path):
        raise InputError("every candidate column is zero on these records: nothing can be selected")
    chosen, err, removed, stopped_by = _kept(dictionary, path, rule, len(forced), prune)
    terms = tuple(dictionary.terms[j] for j in chosen)
    fit = least_squares(dictionary.P[:, chosen], dictionary.target, [t.name for t in terms])
    model = NARX(terms, fit.theta, fit.covariance, fit.sigma2, dictionary.n_obs)
    esr = float(fit.residuals @ fit.residuals) / path.energy
    return NarxSelection(err, esr, path, dictionary.terms, rule.criterion, stopped_by, removed, model)


def _path(
    dictionary: CandidateMatrix,
    rule: _Rule,
    forced: list[int],
    tolerance: float,
    precise: bool,
    progress: Progress | None,
) -> SelectionPath:
    """The FROLS path the rule reads: the fast one (:func:`frols`), or the precise one
    (:func:`frols_grouped`), which takes no included terms."""
    common: dict[str, Any] = {
        "err_tolerance": rule.err_tolerance,
        "tolerance": tolerance,
        "progress": progress,
    }
    if precise:
        if forced:
            raise InputError("included terms are not available with the precise path: select without them")
        return frols_grouped(dictionary.P, dictionary.target, 1, rule.length, **common)
    return frols(
        dictionary.P, dictionary.target, rule.length, scale=dictionary.scale, forced=forced, **common
    )


def _kept(
    dictionary: CandidateMatrix, path: SelectionPath, rule: _Rule, forced: int, prune: bool
) -> tuple[list[int], np.ndarray, tuple[Term, ...], str]:
    """The dictionary positions of the terms the rule keeps of the path (less those ``prune``
    drops), their ERR, the terms pruned, and why the path stopped."""
    size, stopped_by = rule.select(path, forced)
    chosen = list(path.order[:size])
    err = path.err[:size]
    removed: tuple[Term, ...] = ()
    if prune:
        kept = _prune(dictionary.P[:, chosen], dictionary.target, path, rule, forced)
        removed = tuple(dictionary.terms[chosen[i]] for i in range(size) if i not in kept)
        chosen = [chosen[i] for i in kept]
        err = _ordered_err(dictionary.P[:, chosen], dictionary.target, 1, path.energy)
    return chosen, err, removed, stopped_by


def _positions(terms: Sequence[Term], include: Sequence[str | Term]) -> list[int]:
    """Dictionary positions of the included terms, refusing any that is not a candidate."""
    if not include:
        return []
    index = {term: position for position, term in enumerate(terms)}
    missing = [term.name for term in parse_terms(include) if term not in index]
    if missing:
        raise InputError(
            f"included term {', '.join(missing)} is not among the candidates; add it as an extra term"
        )
    return [index[term] for term in parse_terms(include)]


def select_fnarx(
    experiments: Iterable[Experiment],
    candidates: Sequence[str | Term],
    *,
    name: str,
    family: BasisFamily = "chebyshev2",
    size: int = 2,
    k_range: tuple[float, float] | None = None,
    n_terms: int | None = None,
    criterion: str | None = None,
    err_tolerance: float | None = None,
    max_terms: int = 20,
    prune: bool = False,
    tolerance: float = DEFAULT_TOLERANCE,
    progress: Progress | None = None,
) -> FnarxSelection:
    """Select the terms of a fault-mode FNARX model (SPEC §4) by grouped FROLS.

    Each candidate term carries its functional basis: its block holds φ_j(t)·G_i(k_e) for
    the p basis functions, over the experiments (x, y, k_e) stacked without lags crossing
    them. Stopping rules and pruning as :func:`select_narx`, with p parameters per term.
    The model is then estimated by :func:`models.fnarx.fit_fnarx` on the same equations.
    """
    runs = list(experiments)
    if not runs:
        raise InputError("a fault-mode model needs experiments")
    parsed = parse_terms(candidates)
    magnitudes = np.array([float(k) for _, _, k in runs])
    if not np.all(np.isfinite(magnitudes)):
        raise InputError("every experiment needs a finite fault magnitude k")
    low, high = k_range if k_range is not None else (magnitudes.min(), magnitudes.max())
    basis = FunctionalBasis(family, size, float(low), float(high))
    dictionary = candidate_matrix(parsed, [(x, y) for x, y, _ in runs])
    rule = _rule(n_terms, criterion, err_tolerance, max_terms, len(parsed), prune)
    weights = np.repeat(basis.values(magnitudes), dictionary.rows, axis=0)  # g(k_e) on each row
    n_cand = len(parsed)
    B = np.empty((dictionary.n_obs, n_cand * size), order="F")
    for i in range(size):
        np.multiply(dictionary.P, weights[:, i : i + 1], out=B[:, i * n_cand : (i + 1) * n_cand])
    path = frols_grouped(
        B,
        dictionary.target,
        size,
        rule.length,
        err_tolerance=rule.err_tolerance,
        tolerance=tolerance,
        overwrite=True,
        progress=progress,
    )
    del B
    if not len(path):
        raise InputError("every candidate block is zero on these experiments: nothing can be selected")
    n_kept, stopped_by = rule.select(path, 0)
    chosen = list(path.order[:n_kept])
    err = path.err[:n_kept]
    removed: tuple[Term, ...] = ()
    if prune:
        kept = _prune(_blocks(dictionary.P, weights, chosen), dictionary.target, path, rule, 0)
        removed = tuple(parsed[chosen[i]] for i in range(n_kept) if i not in kept)
        chosen = [chosen[i] for i in kept]
        err = _ordered_err(_blocks(dictionary.P, weights, chosen), dictionary.target, size, path.energy)
    terms = tuple(parsed[j] for j in chosen)
    model = fit_fnarx(
        runs, terms, name=name, family=family, size=size, k_range=(low, high), lag=dictionary.lag
    )
    residual_energy = float(np.sum(model.experiment_sigma2 * np.array(dictionary.rows)))
    return FnarxSelection(
        err, residual_energy / path.energy, path, parsed, rule.criterion, stopped_by, removed, model
    )


def _blocks(P: np.ndarray, weights: np.ndarray, chosen: Sequence[int]) -> np.ndarray:
    """Columns φ_j·G_i of the chosen terms, term by term (each term's p columns together)."""
    return np.column_stack([P[:, j] * weights[:, i] for j in chosen for i in range(weights.shape[1])])
