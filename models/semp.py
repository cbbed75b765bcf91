"""Structure selection on the simulation error, with pruning (SEMP, Piroddi & Spinelli 2003).

FROLS (:mod:`models.selection`) ranks terms by what they do to the one-step error. On an
output measured with noise, or on slow, finely sampled data, the one-step error says little
about the free run: y[t−1] alone predicts y[t] almost perfectly, and the noise in the lagged
outputs is fitted by spurious terms. SEMP judges each model M by the mean squared error of its
free run (simulation) on records not used to fit it:

    J(M) = (1/N_J) Σ_r Σ_{t=L}^{N_r−1} (y_r[t] − ŷ_r[t; θ̂_M])²,

ŷ_r the free run of M driven by the input of judged record r alone and started from its first
L measured outputs (L the dictionary's largest lag, so that every model is judged on the same
N_J samples), θ̂_M the least-squares estimate on the one-step error of the fitting records (as
in SEMP: cheap, and the structure, not θ, is what is being chosen). A free run that diverges
has J = ∞, so a model that simulates unstably is never taken. The empty model predicts ŷ = 0.

The algorithm, from the model M₀ of the ``include`` and ``start`` terms:

1. Pruning of M₀ (below).
2. Preselection: the candidates outside M ranked by their error reduction ratio on the fitting
   records' one-step residual of M (the FROLS ERR, :mod:`models.selection`); the first
   ``preselect`` of them are tried.
3. Addition: the tried candidate c of least J(M ∪ {c}) enters if J(M ∪ {c}) < (1 − ρ)·J(M)
   (ρ = ``threshold``); otherwise, or once J(M) is at rounding level (below 1e-20 of the judged
   output's mean square), the selection stops (``no_improvement``). At the first addition
   only, when no single candidate is good enough, the first candidates FROLS would add (largest
   ERR first, up to ``max_terms``) enter, as many as give the least J, if that J is below
   (1 − ρ)·J(M): a model that does not yet simulate the output cannot be grown a term at a time
   (an oscillator's free run needs two output lags and the input at once; with fewer it decays
   to zero, no better than the empty model), and the pruning that follows removes those of them
   that are not needed.
4. Pruning: while some term m of M (not an ``include`` one) has J(M \\ {m}) ≤ (1 + ρ)·J_a,
   J_a being J right after the addition, the one of least J(M \\ {m}) is removed.
5. Back to 2, until M holds ``max_terms`` terms or after 2·``max_terms`` iterations.

Each iteration lowers J by a factor below (1 − ρ)(1 + ρ) = 1 − ρ² (and strictly when ρ = 0),
so no model is visited twice at the end of an iteration and the selection ends. θ̂_M of the
selected structure can then be refined on the free run (:mod:`models.output_error`), which the
one-step least squares, biased by noise on the output, is not.

Cost: k terms in M, N_F fitting equations, N_J judged samples and M candidates. An iteration
costs one QR of the model (2·N_F·k²), the ERR of every candidate (N_F·M, the Gram matrix of the
candidates being formed once, N_F·M²), and ``preselect`` + k·(r + 1) model evaluations, r the
terms it prunes; an evaluation is a least-squares fit (N_F·k for an addition; k³ for a removal,
after one QR of the model per pruning) and a free run (N_J·k, compiled:
:class:`models.simulation.FreeRun`). The first addition may also take one FROLS path
(N_F·M·max_terms) and evaluate up to ``max_terms`` models. With at most 2·max_terms iterations,
and no more removals than |M₀| plus the additions, the number of model evaluations is bounded
by max_terms·(2·preselect + 5·max_terms + |M₀| + 2) whatever the data (2 440 with the defaults
and no starting terms), each a free run of every judged record. On Silverbox (165 candidates,
48 792 fitting equations, 16 262 judged samples) the selection evaluates 146 models in 0.7 s
(``bench/test_bench_select.py``).

References
----------
L. Piroddi and W. Spinelli, "An identification algorithm for polynomial NARX models based on
simulation error minimization", International Journal of Control 76(17), 2003, 1767–1781.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike
from scipy import linalg

from models.candidates import CandidateMatrix, candidate_matrix
from models.errors import InputError
from models.narx import NARX, fit_narx
from models.selection import DEFAULT_TOLERANCE, Progress, frols, model_fields
from models.signals import Record, checked_records
from models.simulation import FreeRun
from models.terms import Term, parse_terms

# ρ in the module docstring: a term must lower the judged mean-square free-run error by 2 % (its RMS
# by 1 %) to enter and be worth as much to stay. Smaller changes are within what chance moves the
# difference of two models' J on a few thousand judged samples of a noisy output: at 0.5 % a
# spurious fourth term entered in 3 of 10 records of the example of Piroddi & Spinelli (output
# noise 5 % of the output), at 2 % in none (tests/test_semp.py).
DEFAULT_THRESHOLD = 0.02
DEFAULT_PRESELECT = 10
# The share of each record's end on which J is judged when no judged records are given.
DEFAULT_JUDGED_SHARE = 0.25

# A free run within this share of the judged output's mean square (an RMS of 1e-10 of it) is exact
# to the rounding of its recursion: no term can improve on it, and relative changes of J there are
# rounding noise.
EXACT = 1e-20

Stop = Literal["no_improvement", "max_terms", "max_steps", "exhausted"]


@dataclass(frozen=True)
class SimulationStep:
    """One change of the model: ``action`` (``start``, ``add`` or ``prune``) of ``term`` (None
    for the start), the free-run RMS √J on the judged samples after it and the model's size."""

    action: Literal["start", "add", "prune"]
    term: Term | None
    rms: float
    n_terms: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "action": self.action,
            "term": None if self.term is None else self.term.name,
            "rms": self.rms,
            "n_terms": self.n_terms,
        }


@dataclass(frozen=True)
class SimulationSelection:
    """Result of :func:`select_by_simulation`.

    Attributes
    ----------
    model : least-squares fit of the selected terms on all the records (fitting and judged); the
        fit on the fitting records alone if that one's free run diverges on the judged records.
    rms : √J of the selected structure (θ from the fitting records) on the judged samples.
    path : every start, addition and removal in order, with √J after it.
    removed : terms removed by pruning, in the order removed (a term may enter again later).
    diverged : candidates whose free run diverged when tried, in the order first seen.
    candidates : the dictionary.
    stopped_by : ``no_improvement``, ``max_terms``, ``max_steps`` (2·max_terms iterations) or
        ``exhausted`` (no independent candidate left).
    evaluations : free runs computed.
    judged_samples : N_J.
    """

    model: NARX
    rms: float
    path: tuple[SimulationStep, ...]
    removed: tuple[Term, ...]
    diverged: tuple[Term, ...]
    candidates: tuple[Term, ...]
    stopped_by: Stop
    evaluations: int
    judged_samples: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible: ``terms`` is readable by ``narxwatch train … --terms``."""
        return model_fields(self.model) | {
            "n_candidates": len(self.candidates),
            "criterion": "simulation",
            "stopped_by": self.stopped_by,
            "simulation_rms": self.rms,
            "judged_samples": self.judged_samples,
            "evaluations": self.evaluations,
            "removed": [term.name for term in self.removed],
            "diverged": [term.name for term in self.diverged],
            "path": [step.to_dict() for step in self.path],
        }


def select_by_simulation(
    records: Iterable[tuple[ArrayLike, ArrayLike]],
    candidates: Sequence[str | Term],
    *,
    judged: Iterable[tuple[ArrayLike, ArrayLike]] | None = None,
    judged_share: float = DEFAULT_JUDGED_SHARE,
    include: Sequence[str | Term] = (),
    start: Sequence[str | Term] = (),
    max_terms: int = 20,
    preselect: int = DEFAULT_PRESELECT,
    threshold: float = DEFAULT_THRESHOLD,
    progress: Progress | None = None,
) -> SimulationSelection:
    """Select NARX terms from ``candidates`` by their free-run error on held-out data (SEMP).

    Parameters
    ----------
    records : (x, y) pairs the parameters are fitted on.
    candidates : the dictionary (term names or terms).
    judged : records J is judged on. Without them, the last ``judged_share`` of each record is
        judged (its sinusoids' time continuing from the fitted part) and the rest is fitted.
    include : candidates taken first and never removed.
    start : candidates the model starts from, which pruning may remove.
    max_terms : the largest model; the selection also stops after 2·max_terms iterations.
    preselect : candidates tried per iteration, the first by ERR.
    threshold : ρ, the relative change of J that an addition must exceed and a removal may not.
    progress : called after each iteration with their number so far (at most 2·max_terms).

    Returns
    -------
    SimulationSelection

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(1)
    >>> x = rng.uniform(-1, 1, 4000)
    >>> w = np.zeros(4000)
    >>> for t in range(2, 4000):
    ...     w[t] = 0.75 * w[t - 2] + 0.25 * x[t - 1] - 0.2 * w[t - 2] * x[t - 1]
    >>> from models.candidates import candidate_terms
    >>> selection = select_by_simulation([(x, w)], candidate_terms(2, 2, 2, constant=False))
    >>> [step.term.name for step in selection.path if step.action == "add"]
    ['x[t-1]', 'y[t-2]', 'y[t-2]*x[t-1]']
    """
    _check_settings(max_terms, preselect, threshold)
    terms = parse_terms(candidates)
    fitting, judging, t0s, everything = _split(records, judged, judged_share)
    dictionary = candidate_matrix(terms, fitting)
    fixed, model = _starting(terms, include, start, max_terms)
    judge = _Judge(terms, judging, t0s, dictionary.lag)
    search = _Search(dictionary, judge, fixed)
    current = _starting_error(search, model)
    course = _iterations(search, model, current, max_terms, preselect, threshold, progress)
    if not course.model:
        raise InputError("no term lowers the simulation error of the empty model: nothing was selected")
    chosen = tuple(terms[j] for j in course.model)
    return SimulationSelection(
        model=_final_fit(chosen, search, course.model, fitting, everything),
        rms=float(np.sqrt(course.current)),
        path=course.path,
        removed=tuple(terms[j] for j in course.removed),
        diverged=tuple(terms[j] for j in course.diverged),
        candidates=terms,
        stopped_by=course.stopped_by,
        evaluations=judge.evaluations,
        judged_samples=judge.samples,
    )


@dataclass(frozen=True)
class _Course:
    """Where the iterations end: the model (dictionary positions) and its J, every change on the
    way, the terms pruned, the candidates whose free run diverged, and why they stopped."""

    model: list[int]
    current: float
    path: tuple[SimulationStep, ...]
    removed: list[int]
    diverged: list[int]
    stopped_by: Stop


def _iterations(
    search: _Search,
    model: list[int],
    current: float,
    max_terms: int,
    preselect: int,
    threshold: float,
    progress: Progress | None,
) -> _Course:
    """Steps 1 to 5 of the module docstring from M₀ (``model``, of J ``current``): its pruning,
    then additions each followed by a pruning, until one of the stopping rules holds."""
    terms = search.judge.terms
    path = [SimulationStep("start", None, float(np.sqrt(current)), len(model))]
    removed: list[int] = []
    diverged: list[int] = []
    model, current = search.prune(model, current, threshold, path, removed)
    stopped_by: Stop = "max_steps"
    for step in range(2 * max_terms):
        if len(model) >= max_terms:
            stopped_by = "max_terms"
            break
        tried = search.preselect(model, preselect)
        if not tried:
            stopped_by = "exhausted"
            break
        added = _added(search, model, current, tried, threshold, step == 0, max_terms, diverged)
        if not added:
            stopped_by = "no_improvement"
            break
        for j, error in added:
            model = [*model, j]
            path.append(SimulationStep("add", terms[j], float(np.sqrt(error)), len(model)))
        current = added[-1][1]
        model, current = search.prune(model, current, threshold, path, removed)
        if progress is not None:
            progress(step + 1)
    return _Course(model, current, tuple(path), removed, diverged, stopped_by)


def _check_settings(max_terms: int, preselect: int, threshold: float) -> None:
    """Refuse a selection's limits that no search could keep."""
    if isinstance(max_terms, bool) or not isinstance(max_terms, int) or max_terms < 1:
        raise InputError(f"max_terms must be an integer >= 1, got {max_terms!r}")
    if isinstance(preselect, bool) or not isinstance(preselect, int) or preselect < 1:
        raise InputError(f"preselect must be an integer >= 1, got {preselect!r}")
    if not 0 <= threshold < 1:
        raise InputError(f"threshold must lie in [0, 1) (a share of the simulation error), got {threshold}")


def _starting(
    terms: tuple[Term, ...],
    include: Sequence[str | Term],
    start: Sequence[str | Term],
    max_terms: int,
) -> tuple[list[int], list[int]]:
    """The dictionary positions of the ``include`` terms, and of the model M₀ they start with
    the ``start`` terms."""
    index = {term: j for j, term in enumerate(terms)}
    fixed = _positions(index, include, "included")
    initial = [j for j in _positions(index, start, "starting") if j not in fixed]
    if len(fixed) + len(initial) > max_terms:
        raise InputError(f"{len(fixed) + len(initial)} starting terms exceed max_terms = {max_terms}")
    return fixed, [*fixed, *initial]


def _starting_error(search: _Search, model: list[int]) -> float:
    """J of M₀, refused where its terms are dependent or its free run diverges."""
    current = search.error(model)
    if current is None:
        raise InputError("the starting terms are linearly dependent on these records: start from fewer")
    if not np.isfinite(current):
        raise InputError("the free run of the starting terms diverges on the judged data: start from fewer")
    return current


def _added(
    search: _Search,
    model: list[int],
    current: float,
    tried: list[int],
    threshold: float,
    first: bool,
    max_terms: int,
    diverged: list[int],
) -> list[tuple[int, float]]:
    """An iteration's addition (step 3 of the module docstring), each term with J after it: the
    ``tried`` candidate of least J if it lowers J by more than ρ; else, at the ``first``
    addition, the FROLS path's first terms that do; else none, as once J is at rounding level.
    The candidates whose free run diverges join ``diverged``."""
    errors = [(search.error([*model, j]), j) for j in tried]
    trials = [(error, j) for error, j in errors if error is not None]
    diverged.extend(j for error, j in trials if error == np.inf and j not in diverged)
    error, best = min(trials, default=(np.inf, -1))
    if current <= EXACT * search.judge.empty:
        return []
    if error < (1 - threshold) * current:
        return [(best, error)]
    if first:
        return search.along_err(model, (1 - threshold) * current, max_terms)
    return []


class _Judge:
    """J of a structure and θ on the judged records (free runs from their first L samples)."""

    def __init__(
        self,
        terms: Sequence[Term],
        records: Sequence[tuple[np.ndarray, np.ndarray]],
        t0s: list[int],
        lag: int,
    ) -> None:
        self.terms = terms
        self.records = records
        self.t0s = t0s
        self.lag = lag
        for number, (_, y) in enumerate(records, 1):
            if y.size <= lag:
                raise InputError(
                    f"judged record {number} has {y.size} samples; its free run needs more than the {lag} "
                    "that start it"
                )
        self.samples = sum(y.size - lag for _, y in records)
        self.empty = sum(float(np.sum(y[lag:] ** 2)) for _, y in records) / self.samples
        self.evaluations = 0

    def error(self, columns: Sequence[int], theta: np.ndarray) -> float:
        """J of the candidates at ``columns`` with parameters θ (∞ if a run diverges)."""
        if not columns:
            return self.empty
        structure = [self.terms[j] for j in columns]
        total = 0.0
        for (x, y), t0 in zip(self.records, self.t0s, strict=True):
            self.evaluations += 1
            run = FreeRun.build(structure, x, t0).run(theta, y)
            with np.errstate(over="ignore", invalid="ignore"):
                total += float(np.sum((y[self.lag :] - run[self.lag :]) ** 2))
            if not np.isfinite(total):
                return float("inf")
        return total / self.samples


class _Search:
    """Least-squares fits of subsets of the candidates on the fitting records, and their J."""

    def __init__(self, dictionary: CandidateMatrix, judge: _Judge, fixed: Sequence[int]) -> None:
        self.P = dictionary.P / dictionary.scale  # unit columns: ERR and QR are scale-free
        self.scale = dictionary.scale
        self.target = dictionary.target
        self.judge = judge
        self.fixed = set(fixed)
        self.energy = float(self.target @ self.target)
        self.unit = np.ones(self.P.shape[1])
        # Q, R and Qᵀy of the model the last preselection ranked against, for the additions to it.
        self._basis: tuple[list[int], np.ndarray, np.ndarray, np.ndarray] | None = None
        self._gram: np.ndarray | None = None

    def error(self, columns: list[int]) -> float | None:
        """J of the model on ``columns`` (∞ if its run diverges), None if its columns are dependent."""
        if not columns:
            return self.judge.error([], np.zeros(0))
        scaled = self._added(columns)
        if scaled is None:
            Q, R = linalg.qr(self.P[:, columns], mode="economic")
            scaled = _solve(R, Q.T @ self.target)
        return None if scaled is None else self.judge.error(columns, scaled / self.scale[columns])

    def _added(self, columns: list[int]) -> np.ndarray | None:
        """Scaled θ of the preselection's model plus its last column, by one Gram–Schmidt step
        (twice) against that model's basis: N_F·k instead of a QR's 2·N_F·k². None if
        ``columns`` is not such a model (or the new column depends on the others)."""
        if self._basis is None or columns[:-1] != self._basis[0]:
            return None
        _, Q, R, z = self._basis
        p = self.P[:, columns[-1]].copy()
        r = Q.T @ p
        p -= Q @ r
        again = Q.T @ p
        p -= Q @ again
        norm = float(np.linalg.norm(p))
        if not norm > DEFAULT_TOLERANCE:
            return None
        extended = np.block([[R, (r + again)[:, None]], [np.zeros((1, R.shape[1])), np.array([[norm]])]])
        return _solve(extended, np.append(z, p @ self.target / norm))

    def preselect(self, model: list[int], count: int) -> list[int]:
        """The ``count`` independent candidates outside ``model`` of largest ERR against its
        one-step residual on the fitting records.

        A candidate's squared norm orthogonal to the model's columns P_M = QR is
        ‖w_j‖² = 1 − ‖Qᵀp_j‖², with Qᵀp_j = R⁻ᵀ·(P_Mᵀp_j) read from the Gram matrix PᵀP (formed
        once): k²·M operations instead of the N_F·M·k of Qᵀ·P."""
        if model:
            Q, R = linalg.qr(self.P[:, model], mode="economic")
            z = Q.T @ self.target
            self._basis = (list(model), Q, R, z)
            residual = self.target - Q @ z
            if self._gram is None:
                self._gram = self.P.T @ self.P
            along = linalg.solve_triangular(R, self._gram[model], trans="T")
            remaining = 1.0 - np.einsum("ij,ij->j", along, along)  # P's columns have unit norm
        else:
            residual = self.target
            remaining = np.ones(self.P.shape[1])
        ratio = np.full(self.P.shape[1], -1.0)
        live = remaining > DEFAULT_TOLERANCE**2
        live[model] = False
        numerator = self.P.T @ residual
        ratio[live] = numerator[live] ** 2 / (remaining[live] * self.energy)
        order = np.argsort(-ratio, kind="stable")[:count]
        return [int(j) for j in order if ratio[j] >= 0]

    def along_err(self, model: list[int], ceiling: float, max_terms: int) -> list[tuple[int, float]]:
        """The candidates FROLS adds to ``model`` (up to ``max_terms`` terms), cut after the one
        whose model has the least J, with the J of each model on the way; empty unless that J
        is below ``ceiling``.

        One FROLS path and one QR of its columns: the fit of each prefix of the path comes from
        the leading block of that QR's R and Qᵀy."""
        order = [int(j) for j in frols(self.P, self.target, max_terms, scale=self.unit, forced=model).order]
        Q, R = linalg.qr(self.P[:, order], mode="economic")
        z = Q.T @ self.target
        added: list[tuple[int, float]] = []
        for size in range(len(model) + 1, len(order) + 1):
            scaled = _solve(R[:size, :size], z[:size])
            if scaled is None:
                break
            columns = order[:size]
            added.append((order[size - 1], self.judge.error(columns, scaled / self.scale[columns])))
        best = min(range(len(added)), key=lambda i: added[i][1], default=None)
        if best is None or not added[best][1] < ceiling:
            return []
        return added[: best + 1]

    def prune(
        self,
        model: list[int],
        current: float,
        threshold: float,
        path: list[SimulationStep],
        removed: list[int],
    ) -> tuple[list[int], float]:
        """Remove, one at a time, the term whose removal raises J least while J stays within
        (1 + ρ) of ``current`` (the J after the addition).

        Each reduced model's θ comes from the triangular factor R of [P_M | y]: dropping a
        column of R and re-triangularising it (k³) gives the reduced fit without reading P."""
        ceiling = (1 + threshold) * current
        R = np.linalg.qr(np.column_stack([self.P[:, model], self.target]), mode="r")
        while True:
            trials = []
            for position, m in enumerate(model):
                if m in self.fixed:
                    continue
                keep = [i for i in range(len(model)) if i != position]
                reduced = np.linalg.qr(R[:, [*keep, len(model)]], mode="r")
                scaled = _solve(reduced[:-1, :-1], reduced[:-1, -1])
                columns = [model[i] for i in keep]
                error = (
                    float("inf")
                    if scaled is None
                    else self.judge.error(columns, scaled / self.scale[columns])
                )
                trials.append((error, position))
            if not trials:
                return model, current
            error, position = min(trials)
            if not error <= ceiling:
                return model, current
            keep = [i for i in range(len(model)) if i != position]
            R = np.linalg.qr(R[:, [*keep, len(model)]], mode="r")
            removed.append(model[position])
            model = [model[i] for i in keep]
            current = error
            path.append(
                SimulationStep("prune", self.judge.terms[removed[-1]], float(np.sqrt(error)), len(model))
            )


def _solve(R: np.ndarray, z: np.ndarray) -> np.ndarray | None:
    """R⁻¹z, or None when R (of unit columns) is singular to the dependence tolerance."""
    if not R.size:
        return np.zeros(0)
    if not np.min(np.abs(np.diag(R))) > DEFAULT_TOLERANCE:
        return None
    return linalg.solve_triangular(R, z)


def _split(
    records: Iterable[tuple[ArrayLike, ArrayLike]],
    judged: Iterable[tuple[ArrayLike, ArrayLike]] | None,
    share: float,
) -> tuple[list[Record], list[Record], list[int], list[Record]]:
    """Fitting records, judged records, where each judged record starts in the time base of
    sinusoids, and all the records the final model is fitted on."""
    checked = list(checked_records(records, 2))
    if judged is not None:
        judging = list(checked_records(judged, 2))
        return checked, judging, [0] * len(judging), [*checked, *judging]
    if not 0 < share < 1:
        raise InputError(f"the judged share of each record must lie in (0, 1), got {share}")
    fitting, judging, t0s = [], [], []
    for x, y in checked:
        cut = y.size - round(share * y.size)
        fitting.append((x[:cut], y[:cut]))
        judging.append((x[cut:], y[cut:]))
        t0s.append(cut)
    return fitting, judging, t0s, checked


def _positions(index: dict[Term, int], names: Sequence[str | Term], role: str) -> list[int]:
    """Dictionary positions of ``names``, refusing any that is not a candidate."""
    if not names:
        return []
    parsed = parse_terms(names)
    missing = [term.name for term in parsed if term not in index]
    if missing:
        raise InputError(
            f"{role} term {', '.join(missing)} is not among the candidates; add it as an extra term"
        )
    return [index[term] for term in parsed]


def _final_fit(
    chosen: tuple[Term, ...],
    search: _Search,
    columns: list[int],
    fitting: list[Record],
    everything: list[Record],
) -> NARX:
    """The selected terms fitted on all the records, unless that fit's free run diverges on the
    judged records, where the fit on the fitting records (the one judged) is kept."""
    model = fit_narx(everything, chosen)
    if np.isfinite(search.judge.error(columns, model.theta)):
        return model
    return fit_narx(fitting, chosen)
