"""Functionally pooled NARX models: coefficients as functions of operating conditions (and of k).

A structure's dynamics move with its operating conditions (a bridge's natural frequencies by
about 5 % over a year with temperature), enough to swamp a small stiffness fault. A functionally
pooled model (Sakellariou & Fassois 2016; Kopsaftopoulos & Fassois 2013) makes each NARX
coefficient a function of the arguments ξ = (w_1, …, w_V[, k]) — the named operating variables w
(temperature in °C, excitation level, …) and, for a fault mode, the fault magnitude k in percent —
expanded on a tensor product of the functional bases of :mod:`models.basis`:

    θ_i(ξ) = Σ_j θ_ij·g_j(ξ),    g(ξ) = g_1(ξ_1) ⊗ g_2(ξ_2) ⊗ … ⊗ g_A(ξ_A),
    y_m[t] = [φ_m[t] ⊗ g(ξ_m)]ᵀ·θ + e_m[t],

each g_a of d_a + 1 functions of ξ_a normalised over the range of ξ_a the training experiments
span (so P = Π(d_a + 1) functions in all), θ = vec(θ_ij) row-major (term i, then the multi-index
j, the last argument's index fastest; k is the last argument of a fault mode). θ is estimated by
OLS over the M experiments stacked, each at its own conditions ξ_m. A pooled *baseline* has the
operating variables alone; a pooled *fault mode* has them and k.

Estimation. The stacked regression has Σ N_m rows but only M distinct g(ξ_m), so each
experiment is compressed first: with Φ_m = Q_m·R_m (thin QR), c_m = Q_mᵀ·y_m and
r_m = ‖y_m − Q_m·c_m‖², its sum of squares is r_m + ‖c_m − (R_m ⊗ g(ξ_m)ᵀ)·θ‖². The OLS
estimate, its residual sum of squares and (XᵀX)⁻¹ = Σ R_mᵀR_m ⊗ g_m g_mᵀ are those of the whole
stacked problem, at a cost that does not grow with N_m for every candidate degree.

Degrees. Each d_a ∈ {0, …, ``max_degree``} is chosen by the Bayesian information criterion over
the whole grid of degree vectors, BIC = n·ln σ̂² + n_θ·ln n (n stacked equations, n_θ = n_terms·P
parameters); the table of every candidate is kept with the model. A candidate needs P < M
(with P = M the model passes through every experiment and nothing checks its form) and a design
[g(ξ_1) … g(ξ_M)] of full rank P.

Residual variance. ln σ²(ξ) is expanded on the same basis, fitted by weighted least squares to
the experiments' ln σ̂²_m (made unbiased, ·n/(n − n_θ)), whose variance is 2/N_m for Gaussian
residuals; the covariance of
that fit is scaled up by its reduced χ² when the experiments scatter more. The variance of
ln σ̂²(ξ), v(ξ), gives the reference an equivalent number of degrees of freedom 2/v(ξ) for the
residual-variance test of :func:`check_baseline`.

Evaluation. At measured conditions w the pooled baseline is an ordinary NARX (:meth:`narx_at`)
with θ(w) = Θ·g(w) and Cov θ(w) = (I ⊗ g(w))ᵀ·Cov vec(θ)·(I ⊗ g(w)); the pooled fault mode is
an FNARX in k (:meth:`fnarx_at`), Θ_w = Θ·(g_w(w) ⊗ I), so the inspection chain of
:mod:`models.inspection` runs on it unchanged. A record outside the trained range of any
variable (beyond :data:`RANGE_TOLERANCE` of its span) or without a variable the model needs is
refused: a polynomial in w says nothing reliable outside the conditions it was fitted on.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import linalg, special

from models.basis import BasisFamily, FunctionalBasis
from models.diagnostics import ljung_box
from models.errors import InputError
from models.fnarx import FNARX
from models.inspection import ADEQUACY_SHARE, Status, Verdict, inspect
from models.narx import NARX, check_document
from models.regression import least_squares
from models.signals import checked_record, minimum_samples
from models.terms import OverTerms, Term, max_degree, max_lag, parse_terms, regressor_matrix

MAGNITUDE = "k"  # the fault magnitude's name among a fault mode's arguments
MAX_DEGREE = 4  # the highest degree the criterion may choose for any argument
MAX_VARIABLES = 3  # operating variables of one model: (MAX_DEGREE + 1)^(V + 1) candidates at most
# A record's condition may lie this share of the trained span beyond either end: a measured
# temperature of 30.1 °C on a model trained up to 30.0 °C is evaluated there (the polynomials
# move by a few percent of their range change at most), one of 35 °C is refused.
RANGE_TOLERANCE = 0.01


@dataclass(frozen=True, eq=False)
class PooledExperiment:
    """One training record: excitation x, response y, its operating ``conditions`` by name
    (e.g. ``{"temperature": 12.5}`` in °C) and, for a fault mode, its fault magnitude ``k`` [%]."""

    x: ArrayLike
    y: ArrayLike
    conditions: Mapping[str, float]
    k: float | None = None


@dataclass(frozen=True)
class DegreeCandidate:
    """One row of the information-criterion table: degrees per argument, in the model's order."""

    degrees: tuple[int, ...]
    parameters: int
    sigma2: float
    bic: float


@dataclass(frozen=True)
class PooledModel(OverTerms):
    """A functionally pooled NARX model (module docstring).

    Attributes
    ----------
    name : ``"baseline"`` or the fault mode, e.g. ``"k2"``.
    terms : the regressors φ.
    arguments : the argument names: the operating variables, then ``"k"`` for a fault mode.
    bases : one functional basis per argument, over the range trained on.
    theta : projection coefficients, shape (n_terms, P).
    covariance : covariance of vec(θ), shape (n_terms·P, n_terms·P).
    log_variance, log_variance_covariance : coefficients of ln σ²(ξ) on g(ξ), and their covariance.
    experiment_arguments : ξ_m of each experiment, shape (M, len(arguments)).
    experiment_sigma2 : residual variance of each experiment.
    n_obs : number of stacked equations.
    criterion : the BIC table the degrees were chosen from (one row when they were given).
    """

    name: str
    terms: tuple[Term, ...]
    arguments: tuple[str, ...]
    bases: tuple[FunctionalBasis, ...]
    theta: np.ndarray
    covariance: np.ndarray
    log_variance: np.ndarray
    log_variance_covariance: np.ndarray
    experiment_arguments: np.ndarray
    experiment_sigma2: np.ndarray
    n_obs: int
    criterion: tuple[DegreeCandidate, ...]

    @property
    def is_fault_mode(self) -> bool:
        return self.arguments[-1] == MAGNITUDE

    @property
    def variables(self) -> tuple[str, ...]:
        """The operating variables a record must carry."""
        return self.arguments[:-1] if self.is_fault_mode else self.arguments

    @property
    def degrees(self) -> dict[str, int]:
        """The degree of the basis of each argument."""
        return {name: basis.size - 1 for name, basis in zip(self.arguments, self.bases, strict=True)}

    @property
    def ranges(self) -> dict[str, tuple[float, float]]:
        """The trained range of each argument."""
        return {name: (b.k_min, b.k_max) for name, b in zip(self.arguments, self.bases, strict=True)}

    def check_conditions(self, conditions: Mapping[str, float]) -> np.ndarray:
        """The values of :attr:`variables` in ``conditions``, refused when one is missing, not a
        finite number, or outside its trained range (beyond :data:`RANGE_TOLERANCE`). Other
        variables the record carries are not used by this model and are ignored."""
        values = []
        for name, basis in zip(self.variables, self.bases, strict=False):
            if name not in conditions:
                carried = ", ".join(sorted(conditions)) or "none"
                raise InputError(
                    f"pooled model {self.name!r} needs operating variable {name!r} (trained over "
                    f"[{basis.k_min:g}, {basis.k_max:g}]); the record carries {carried}"
                )
            value = _finite(conditions[name], f"operating variable {name!r}")
            margin = RANGE_TOLERANCE * (basis.k_max - basis.k_min)
            if not basis.k_min - margin <= value <= basis.k_max + margin:
                raise InputError(
                    f"operating variable {name!r} = {value:g} lies outside the range "
                    f"[{basis.k_min:g}, {basis.k_max:g}] pooled model {self.name!r} was trained on; "
                    "train it with experiments that reach this condition"
                )
            values.append(value)
        return np.array(values)

    def narx_at(self, conditions: Mapping[str, float]) -> NARX:
        """The baseline NARX at the measured ``conditions``, with Cov θ(w) and σ²(w)."""
        if self.is_fault_mode:
            raise InputError(f"{self.name!r} is a pooled fault mode; evaluate it with fnarx_at")
        w = self.check_conditions(conditions)
        g = tensor_values(self.bases, w)
        selector = np.kron(np.eye(len(self.terms)), g[:, None])
        variance = float(np.exp(self._log_variance(w)[0]))
        return NARX(self.terms, self.theta @ g, selector.T @ self.covariance @ selector, variance, self.n_obs)

    def fnarx_at(self, conditions: Mapping[str, float]) -> FNARX:
        """The fault-mode model in k at the measured ``conditions``: Θ_w = Θ·(g_w(w) ⊗ I)."""
        if not self.is_fault_mode:
            raise InputError(f"{self.name!r} is a pooled baseline; evaluate it with narx_at")
        w = self.check_conditions(conditions)
        magnitude = self.bases[-1]
        collapse = np.kron(tensor_values(self.bases[:-1], w)[:, None], np.eye(magnitude.size))
        selector = np.kron(np.eye(len(self.terms)), collapse)
        k = np.unique(self.experiment_arguments[:, -1])
        sigma2 = np.exp([self._log_variance(np.append(w, kk))[0] for kk in k])
        return FNARX(
            self.name,
            self.terms,
            magnitude,
            self.theta @ collapse,
            selector.T @ self.covariance @ selector,
            k,
            sigma2,
            self.n_obs,
        )

    def variance_at(self, conditions: Mapping[str, float]) -> tuple[float, float]:
        """σ²(w) of a baseline and its equivalent degrees of freedom 2/Var ln σ̂²(w)."""
        if self.is_fault_mode:
            raise InputError(f"{self.name!r} is a pooled fault mode; its variance depends on k too")
        log_variance, spread = self._log_variance(self.check_conditions(conditions))
        return float(np.exp(log_variance)), 2.0 / spread

    def _log_variance(self, xi: np.ndarray) -> tuple[float, float]:
        g = tensor_values(self.bases, xi)
        return float(g @ self.log_variance), float(g @ self.log_variance_covariance @ g)

    def to_document(self) -> dict[str, Any]:
        return {
            "kind": "pooled",
            "schema_version": 1,
            "name": self.name,
            "terms": [term.name for term in self.terms],
            "arguments": [
                {"name": name, "basis": basis.to_document()}
                for name, basis in zip(self.arguments, self.bases, strict=True)
            ],
            "theta": self.theta.tolist(),
            "covariance": self.covariance.tolist(),
            "log_variance": self.log_variance.tolist(),
            "log_variance_covariance": self.log_variance_covariance.tolist(),
            "experiment_arguments": self.experiment_arguments.tolist(),
            "experiment_sigma2": self.experiment_sigma2.tolist(),
            "n_obs": self.n_obs,
            "criterion": [
                {
                    "degrees": list(row.degrees),
                    "parameters": row.parameters,
                    "sigma2": row.sigma2,
                    "bic": row.bic,
                }
                for row in self.criterion
            ],
        }

    @classmethod
    def from_document(cls, document: dict[str, Any]) -> PooledModel:
        check_document(document, "pooled")
        try:
            terms = parse_terms(document["terms"])
            arguments = tuple(str(item["name"]) for item in document["arguments"])
            bases = tuple(FunctionalBasis.from_document(item["basis"]) for item in document["arguments"])
            model = cls(
                str(document["name"]),
                terms,
                arguments,
                bases,
                np.asarray(document["theta"], dtype=np.float64),
                np.asarray(document["covariance"], dtype=np.float64),
                np.asarray(document["log_variance"], dtype=np.float64),
                np.asarray(document["log_variance_covariance"], dtype=np.float64),
                np.asarray(document["experiment_arguments"], dtype=np.float64),
                np.asarray(document["experiment_sigma2"], dtype=np.float64),
                int(document["n_obs"]),
                tuple(
                    DegreeCandidate(
                        tuple(int(d) for d in row["degrees"]),
                        int(row["parameters"]),
                        float(row["sigma2"]),
                        float(row["bic"]),
                    )
                    for row in document["criterion"]
                ),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"pooled model document: {exc}") from None
        size = int(np.prod([basis.size for basis in bases]))
        shapes = {
            "theta": (model.theta.shape, (len(terms), size)),
            "covariance": (model.covariance.shape, (len(terms) * size,) * 2),
            "log_variance": (model.log_variance.shape, (size,)),
            "log_variance_covariance": (model.log_variance_covariance.shape, (size, size)),
            "experiment_arguments": (model.experiment_arguments.shape[1:], (len(arguments),)),
        }
        for field, (shape, expected) in shapes.items():
            if shape != expected:
                raise InputError(f"pooled model document: {field} has shape {shape}, expected {expected}")
        return model


def tensor_values(bases: Sequence[FunctionalBasis], xi: ArrayLike) -> np.ndarray:
    """g(ξ) = g_1(ξ_1) ⊗ … ⊗ g_A(ξ_A), the last argument's index fastest; shape (Π sizes,)."""
    values = np.ones(1)
    for basis, value in zip(bases, np.atleast_1d(np.asarray(xi, dtype=np.float64)), strict=True):
        values = np.kron(values, basis.values(value))
    return values


@dataclass(frozen=True)
class _Compressed:
    """The experiments reduced to what every candidate's OLS needs (module docstring)."""

    R: list[np.ndarray]
    c: list[np.ndarray]
    r: np.ndarray
    lengths: np.ndarray


def fit_pooled(
    experiments: Iterable[PooledExperiment],
    terms: Sequence[str | Term],
    *,
    name: str = "baseline",
    variables: Sequence[str] | None = None,
    family: BasisFamily = "chebyshev2",
    max_degree: int = MAX_DEGREE,
    degrees: Mapping[str, int] | None = None,
    lag: int | None = None,
) -> PooledModel:
    """Estimate a pooled baseline (no experiment has a k) or fault mode (every one has) by OLS.

    Parameters
    ----------
    experiments : the training records, spread over the conditions (and magnitudes).
    terms : the regressors φ, as for :func:`models.narx.fit_narx`.
    name : the model's name: ``"baseline"``, or the fault mode's.
    variables : the operating variables to pool over; by default every variable the first
        experiment carries. Each experiment must carry each of them.
    family : the functional basis of every argument.
    max_degree : the highest degree per argument the BIC search considers (≤ 4).
    degrees : the degree of each argument, by name, instead of the search.
    lag : the first equation of each experiment, as for :func:`models.fnarx.fit_fnarx`.

    Each candidate costs one QR of a (M·(n_terms + 1)) × (n_terms·P) matrix, P < M; the
    experiments' own QRs are computed once.

    Returns
    -------
    PooledModel
        with its BIC table in ``criterion``.
    """
    runs = list(experiments)
    if not runs:
        raise InputError("a pooled model needs experiments")
    names = _variables(runs, variables)
    fault = _is_fault_mode(runs)
    arguments = (*names, MAGNITUDE) if fault else names
    xi = _argument_values(runs, names, fault, arguments)
    if not (int(max_degree) == max_degree and 0 <= max_degree <= MAX_DEGREE):
        raise InputError(f"max_degree must be a whole number from 0 to {MAX_DEGREE}, got {max_degree}")
    parsed = parse_terms(terms)
    compressed = _compress(runs, parsed, lag)
    n = int(compressed.lengths.sum())
    if degrees is not None:
        choices = [_given_degrees(degrees, arguments)]
    else:
        choices = [list(c) for c in itertools.product(range(int(max_degree) + 1), repeat=len(arguments))]
    table, fits = _degree_fits(compressed, parsed, xi, arguments, family, choices, degrees is not None)
    best = min(table, key=lambda row: row.bic)
    bases, G, theta, per_experiment, covariance = fits[best.degrees]
    sigma2 = per_experiment / compressed.lengths
    # The residuals of the fit fall short of the noise by the n_θ dimensions the fit used up:
    # E Σe² = (n − n_θ)·σ². The variance model is fitted on the unbiased σ̂²_m·n/(n − n_θ).
    unbiased = sigma2 * n / (n - theta.size)
    log_variance, log_variance_covariance = _log_variance_fit(G, unbiased, compressed.lengths)
    return PooledModel(
        name=name,
        terms=parsed,
        arguments=tuple(arguments),
        bases=bases,
        theta=theta,
        covariance=covariance,
        log_variance=log_variance,
        log_variance_covariance=log_variance_covariance,
        experiment_arguments=xi,
        experiment_sigma2=sigma2,
        n_obs=n,
        criterion=tuple(table),
    )


def _argument_values(
    runs: list[PooledExperiment], names: Sequence[str], fault: bool, arguments: Sequence[str]
) -> np.ndarray:
    """ξ: each experiment's operating variables (and fault magnitude), a row an experiment;
    refused where an argument does not vary across the experiments."""
    xi = np.array(
        [
            [_finite(run.conditions[v], f"experiment {i + 1}: operating variable {v!r}") for v in names]
            + ([_finite(run.k, f"experiment {i + 1}: fault magnitude k")] if fault else [])
            for i, run in enumerate(runs)
        ]
    )
    for column, argument in enumerate(arguments):
        if np.ptp(xi[:, column]) == 0:
            what = "fault magnitude" if argument == MAGNITUDE else "operating variable"
            raise InputError(
                f"every experiment has {what} {argument!r} = {xi[0, column]:g}: a pooled model cannot "
                "learn how the dynamics change with it; spread the experiments over its range"
            )
    return xi


def _degree_fits(
    compressed: _Compressed,
    parsed: tuple[Term, ...],
    xi: np.ndarray,
    arguments: Sequence[str],
    family: BasisFamily,
    choices: list[list[int]],
    given: bool,
) -> tuple[list[DegreeCandidate], dict[tuple[int, ...], tuple]]:
    """The fit and BIC row of each choice of degrees the experiments can tell apart (a
    ``given`` choice they cannot is refused): the BIC table, and each choice's bases, G, θ,
    residual sums per experiment and covariance."""
    n = int(compressed.lengths.sum())
    spans = [(float(column.min()), float(column.max())) for column in xi.T]
    table, fits = [], {}
    for choice in choices:
        bases = tuple(FunctionalBasis(family, d + 1, *span) for d, span in zip(choice, spans, strict=True))
        G = np.array([tensor_values(bases, row) for row in xi])
        if G.shape[1] >= len(xi) or np.linalg.matrix_rank(G) < G.shape[1]:
            if given:
                raise InputError(
                    f"degrees {dict(zip(arguments, choice, strict=True))} make {G.shape[1]} basis functions, "
                    f"which need more than {G.shape[1]} experiments at conditions that tell them apart; "
                    f"there are {len(xi)}"
                )
            continue
        theta, per_experiment, covariance = _solve(compressed, G, parsed)
        sigma2 = float(np.sum(per_experiment) / n)
        table.append(
            DegreeCandidate(
                tuple(choice), theta.size, sigma2, float(n * np.log(sigma2) + theta.size * np.log(n))
            )
        )
        fits[tuple(choice)] = (bases, G, theta, per_experiment, covariance)
    return table, fits


def _finite(value: object, label: str) -> float:
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"{label} must be a number, got {value!r}") from None
    if not np.isfinite(number):
        raise InputError(f"{label} must be a finite number, got {number}")
    return number


def _variables(runs: list[PooledExperiment], variables: Sequence[str] | None) -> tuple[str, ...]:
    carried = set(runs[0].conditions)
    names = tuple(sorted(carried)) if variables is None else tuple(variables)
    if not names:
        raise InputError("a pooled model needs at least one operating variable; the experiments carry none")
    if len(names) > MAX_VARIABLES or len(set(names)) != len(names):
        raise InputError(
            f"a pooled model takes 1 to {MAX_VARIABLES} distinct operating variables, got {names}"
        )
    known = set().union(*(run.conditions for run in runs))
    for name in names:
        if name == MAGNITUDE:
            raise InputError(
                f"{MAGNITUDE!r} names the fault magnitude; call the operating variable otherwise"
            )
        if name not in known:
            raise InputError(
                f"unknown operating variable {name!r}: no experiment carries it; they carry "
                f"{', '.join(sorted(known)) or 'none'}"
            )
    for index, run in enumerate(runs):
        missing = [name for name in names if name not in run.conditions]
        if missing:
            raise InputError(f"experiment {index + 1} carries no operating variable {missing[0]!r}")
    return names


def _is_fault_mode(runs: list[PooledExperiment]) -> bool:
    with_k = [run.k is not None for run in runs]
    if any(with_k) and not all(with_k):
        missing = with_k.index(False) + 1
        raise InputError(
            f"experiment {missing} has no fault magnitude k while others have one: a pooled fault mode "
            "needs k on every experiment, a pooled baseline on none"
        )
    return all(with_k)


def _given_degrees(degrees: Mapping[str, int], arguments: Sequence[str]) -> list[int]:
    if set(degrees) != set(arguments):
        given = ", ".join(sorted(degrees)) or "none"
        raise InputError(f"degrees must name each of {', '.join(arguments)} once; got {given}")
    choice = [degrees[name] for name in arguments]
    for name, d in zip(arguments, choice, strict=True):
        if not (int(d) == d and 0 <= d <= MAX_DEGREE):
            raise InputError(f"the degree of {name!r} must be a whole number from 0 to {MAX_DEGREE}, got {d}")
    return [int(d) for d in choice]


def _compress(runs: list[PooledExperiment], terms: tuple[Term, ...], lag: int | None) -> _Compressed:
    L = max_lag(terms) if lag is None else max(lag, max_lag(terms))
    R, c, r, lengths = [], [], [], []
    for index, run in enumerate(runs):
        xa, ya = checked_record(
            run.x, run.y, L + len(terms) + 1, label=f"experiment {index + 1}", degree=max_degree(terms)
        )
        Phi, target = regressor_matrix(terms, xa, ya, L)
        Q, Rm = linalg.qr(Phi, mode="economic")
        cm = Q.T @ target
        R.append(Rm)
        c.append(cm)
        r.append(float(np.sum((target - Q @ cm) ** 2)))
        lengths.append(len(target))
    return _Compressed(R, c, np.array(r), np.array(lengths))


def _solve(
    compressed: _Compressed, G: np.ndarray, terms: tuple[Term, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """θ (n_terms × P), each experiment's residual sum of squares, and Cov vec(θ) = σ̂²(XᵀX)⁻¹.

    Each experiment's block is R_m ⊗ g_mᵀ against c_m, plus one zero row against √r_m: that row
    leaves θ and (XᵀX)⁻¹ alone and carries the part of the residual the compression removed, so
    the compressed residual sum of squares is the stacked one."""
    n_terms, size = len(terms), G.shape[1]
    blocks, targets = [], []
    for Rm, cm, rm, g in zip(compressed.R, compressed.c, compressed.r, G, strict=True):
        blocks.append(np.vstack([np.kron(Rm, g[None, :]), np.zeros((1, n_terms * size))]))
        targets.append(np.append(cm, np.sqrt(rm)))
    names = [f"{t.name}·g{j + 1}" for t in terms for j in range(size)]
    fit = least_squares(np.vstack(blocks), np.concatenate(targets), names)
    per_experiment = np.sum(fit.residuals.reshape(len(G), n_terms + 1) ** 2, axis=1)
    # least_squares divides by its own rows; the stacked problem has Σ N_m equations.
    covariance = fit.covariance * len(fit.residuals) / compressed.lengths.sum()
    return fit.theta.reshape(n_terms, size), per_experiment, covariance


def _log_variance_fit(
    G: np.ndarray, sigma2: np.ndarray, lengths: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """ln σ²(ξ) = g(ξ)ᵀβ by weighted least squares, Var ln σ̂²_m = 2/N_m; Cov β = (AᵀA)⁻¹ with
    A the weighted design, scaled by the fit's reduced χ² when it exceeds 1 (the experiments
    scatter more than their sampling error: the basis misses part of σ²(ξ))."""
    A = G * np.sqrt(lengths / 2.0)[:, None]
    target = np.log(sigma2) * np.sqrt(lengths / 2.0)
    beta = np.linalg.lstsq(A, target, rcond=None)[0]
    chi2 = float(np.sum((target - A @ beta) ** 2))
    return beta, np.linalg.inv(A.T @ A) * max(1.0, chi2 / (len(sigma2) - G.shape[1]))


@dataclass(frozen=True)
class BaselineCheck:
    """A record against a baseline at its conditions: the residual-variance test and whiteness.

    ``variance_ratio`` is F = σ̂²_u/σ̂²_0, the record's mean squared residual over
    ``reference_sigma2``, what a healthy record's is expected to be (:func:`check_baseline`),
    compared with F_{1−α_F}(N_u, ν_0); ``q`` is the Ljung–Box statistic of the residual,
    compared with χ²_{1−α_Q}(h − 1). ``detected_by`` names the tests that fired.
    """

    conditions: dict[str, float]
    residuals: np.ndarray
    sigma2: float
    reference_sigma2: float
    reference_dof: float
    variance_ratio: float
    variance_critical: float
    variance_p: float
    q: float
    q_critical: float
    q_p: float
    alpha: float
    lags: int
    fault_detected: bool
    detected_by: tuple[str, ...]


def check_baseline(
    model: PooledModel | NARX,
    x: ArrayLike,
    y: ArrayLike,
    conditions: Mapping[str, float] | None = None,
    *,
    alpha: float = 0.05,
    lags: int = 40,
    adequacy_share: float = ADEQUACY_SHARE,
) -> BaselineCheck:
    """Test a record against a healthy baseline: a pooled one at the record's measured
    ``conditions``, or a plain NARX (trained at one condition, ``conditions`` unused).

    The residual e[t] = y[t] − φ[t]ᵀθ(w) of a healthy record is white with the reference
    variance σ²(w). Two tests share α by Šidák, as in :mod:`models.inspection`:

    - residual variance (Fassois & Sakellariou 2007): F = mean(e²)/σ̂²_0 against
      F_{1−α_F}(N_u, ν_0), one-sided (a fault adds to the variance), with ν_0 the reference's
      degrees of freedom: its n_obs for a NARX, 2/Var ln σ̂²(w) for a pooled baseline;
    - whiteness: Ljung–Box Q at ``lags`` against χ²_{1−α_Q}(h − 1), α_Q = ``adequacy_share``·α
      (for gross departures, as in the inspection), α_F = 1 − (1 − α)/(1 − α_Q).

    The reference is what a healthy record's mean squared residual is expected to be: the
    noise variance σ²(w) (a NARX's σ̂²·n/(n − n_θ), unbiased; a pooled baseline's is so by
    construction) plus mean_t φ[t]ᵀ·Cov θ(w)·φ[t], the estimation error of θ(w) the record's own
    regressors carry (the record is independent of the training data). Each is about n_θ/n
    (0.1 % with 16 parameters and 18 000 equations): small beside the 3 % standard error of
    mean(e²) over 2000 samples, yet together a tenth of it, enough to raise a 5 % test's size
    to 6 %.
    """
    if not 0 < alpha < 0.5:
        raise InputError(f"alpha must lie in (0, 0.5), got {alpha}")
    if int(lags) != lags or lags < 2:
        raise InputError(f"lags must be a whole number of at least 2, got {lags}")
    if isinstance(model, PooledModel):
        narx = model.narx_at(conditions or {})
        noise, dof = model.variance_at(conditions or {})
        used = {name: float(conditions[name]) for name in model.variables}  # type: ignore[index]
    else:
        narx, dof, used = model, float(model.n_obs), {}
        noise = model.sigma2 * model.n_obs / (model.n_obs - len(model.terms)) if model.n_obs else 0.0
    if not (noise > 0 and dof > 0):
        raise InputError("the baseline has no residual variance to test against (a theoretical model?)")
    xa, ya = checked_record(x, y, minimum_samples(int(lags), narx.max_lag), degree=max_degree(narx.terms))
    residuals = narx.residuals(xa, ya)
    Phi, _ = regressor_matrix(narx.terms, xa, ya)
    reference = noise + float(np.mean(np.einsum("ti,ij,tj->t", Phi, narx.covariance, Phi)))
    whiteness_alpha = adequacy_share * alpha
    variance_alpha = 1 - (1 - alpha) / (1 - whiteness_alpha)
    sigma2 = float(np.mean(residuals**2))
    ratio = sigma2 / reference
    n = len(residuals)
    critical = float(special.fdtri(n, dof, 1 - variance_alpha))
    whiteness = ljung_box(residuals, int(lags), whiteness_alpha)
    detected_by = ("variance",) * (ratio > critical) + ("whiteness",) * (not whiteness.white)
    return BaselineCheck(
        conditions=used,
        residuals=residuals,
        sigma2=sigma2,
        reference_sigma2=reference,
        reference_dof=dof,
        variance_ratio=ratio,
        variance_critical=critical,
        variance_p=float(special.fdtrc(n, dof, ratio)),
        q=whiteness.q,
        q_critical=whiteness.q_critical,
        q_p=whiteness.p_value,
        alpha=alpha,
        lags=int(lags),
        fault_detected=bool(detected_by),
        detected_by=detected_by,
    )


def inspect_pooled(
    x: ArrayLike,
    y: ArrayLike,
    conditions: Mapping[str, float],
    fault_modes: Sequence[PooledModel],
    **options: Any,
) -> Verdict:
    """The inspection chain of :func:`models.inspection.inspect` with pooled fault modes, each
    evaluated at the record's measured ``conditions`` (k̂ and its interval with w fixed there).
    ``options`` are those of :func:`models.inspection.inspect`."""
    return inspect(x, y, [model.fnarx_at(conditions) for model in fault_modes], **options)


def baseline_verdict(check: BaselineCheck, n_samples: int) -> Verdict:
    """A record's verdict from a baseline check alone, for a structure monitored without fault
    modes: healthy, or a fault no model describes (``unknown_fault``: nothing estimates its
    magnitude), detected by the tests ``detected_by`` names. ``n_samples`` is the record's length."""
    status: Status = "unknown_fault" if check.fault_detected else "healthy"
    return Verdict(
        status=status,
        fault_detected=check.fault_detected,
        fault_mode=None,
        reference_mode=None,
        k_hat=None,
        sigma_k=None,
        interval=None,
        alpha=check.alpha,
        lags=check.lags,
        n_samples=n_samples,
        z_critical=None,
        q_critical_detection=check.q_critical,
        detected_by=check.detected_by,
        modes=(),
    )
