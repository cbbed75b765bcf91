"""``narxwatch select``: find a NARX structure from records by FROLS (SPEC §3) or on the simulation
error (SEMP, :mod:`models.semp`)."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Annotated, Any, TypeVar

import numpy as np
import typer
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text

from models.baseline_choice import choose_delay
from models.candidates import candidate_terms
from models.errors import InputError
from models.narx import NARX
from models.output_error import OutputErrorFit, fit_output_error
from models.selection import CRITERIA, NarxSelection, select_narx
from models.semp import (
    DEFAULT_JUDGED_SHARE,
    DEFAULT_PRESELECT,
    DEFAULT_THRESHOLD,
    SimulationSelection,
    select_by_simulation,
)
from models.terms import Term
from models.validation import Validation, validate
from recordfiles.reader import Layout
from service.cli.console import stdout, transient_progress
from service.cli.modelfiles import RECORD_SET_HELP, XName, YName, read_records, signal_layout, write_json
from simulator.client.groups import expanded

Signals = list[tuple[np.ndarray, np.ndarray]]
# The criterion that judges candidates on the free run instead of the one-step error.
SIMULATION = "simulation"
Selected = TypeVar("Selected", NarxSelection, SimulationSelection)


@dataclasses.dataclass(frozen=True)
class CandidateOptions:
    """The options that make the candidate dictionary, as given (each field an option;
    :func:`~simulator.client.groups.expanded`)."""

    degree: Annotated[int, typer.Option(help="Largest total degree of the candidate monomials.")] = 3
    ny: Annotated[int, typer.Option(help="Output lags y[t-1] … y[t-ny].")] = 4
    nx: Annotated[int, typer.Option(help="Input lags x[t-delay] … x[t-delay-nx+1].")] = 4
    delay: Annotated[
        int | None,
        typer.Option(
            help="Input delay d: the smallest lag of x (0 allows x[t]). Default: chosen, 0 or 1, by which "
            "linear ARX(ny, nx) runs free better over held-out parts of the records."
        ),
    ] = None
    constant: Annotated[bool, typer.Option(help="Include the constant term 1.")] = True
    extra: Annotated[
        list[str] | None, typer.Option(help="Extra candidate term beyond the dictionary (repeatable).")
    ] = None

    def dictionary(self, signals: Signals) -> _Dictionary:
        """The candidates, with the input delay given or, without one, chosen on ``signals``
        (:func:`models.baseline_choice.choose_delay`)."""
        extra = self.extra or []
        # Both dictionaries where the delay is to be chosen: a bad one is refused before the choice runs.
        dictionaries = {
            d: candidate_terms(self.degree, self.ny, self.nx, d, constant=self.constant, extra=extra)
            for d in ((0, 1) if self.delay is None else (self.delay,))
        }
        delay, delays = self.delay, None
        if delay is None:
            delay, delays = choose_delay(signals, self.ny, self.nx)
        return _Dictionary(
            self.degree, self.ny, self.nx, delay, delays, self.constant, extra, dictionaries[delay]
        )


@dataclasses.dataclass(frozen=True)
class RuleOptions:
    """Which candidates enter and when the selection stops, as given: the criterion, and the
    one-step error's stopping rules (each field an option)."""

    include: Annotated[
        list[str] | None, typer.Option(help="Candidate taken first and always kept (repeatable).")
    ] = None
    criterion: Annotated[
        str | None,
        typer.Option(
            help=f"On the one-step error, an information criterion minimised along the FROLS path: "
            f"{', '.join(CRITERIA)} (default bic, unless --n-terms or --err-tolerance is given). Or "
            f"'{SIMULATION}': terms judged by the free-run error on the end of each record (SEMP, with "
            "pruning)."
        ),
    ] = None
    n_terms: Annotated[int | None, typer.Option(help="Select exactly this many terms.")] = None
    err_tolerance: Annotated[
        float | None, typer.Option(help="Stop once the unexplained share 1 − ΣERR falls below this.")
    ] = None
    max_terms: Annotated[
        int, typer.Option(help="Longest greedy path (with --criterion simulation: the largest model).")
    ] = 20
    prune: Annotated[
        bool,
        typer.Option(
            help="Then drop terms one at a time while the stopping rule still holds "
            "(--criterion simulation always prunes)."
        ),
    ] = False
    precise: Annotated[
        bool,
        typer.Option(
            help="Explicitly orthogonalised path, exact to rounding level (noise-free data); slower."
        ),
    ] = False

    def by_simulation(self, judged: list[Path] | None) -> bool:
        """Whether the terms are to be judged on the free-run error (``--criterion simulation``);
        refused: an unknown criterion, ``--judged`` records without it, and with it any option of
        the selection on the one-step error."""
        criterion = self.criterion
        if criterion is not None and criterion.lower() not in (*CRITERIA, SIMULATION):
            raise InputError(
                f"unknown criterion {criterion!r}; choose one of {', '.join(CRITERIA)} (one-step error) "
                f"or {SIMULATION} (free-run error)"
            )
        simulation = criterion is not None and criterion.lower() == SIMULATION
        if judged and not simulation:
            raise InputError("--judged records serve --criterion simulation only")
        one_step = {"n_terms": self.n_terms, "err_tolerance": self.err_tolerance, "precise": self.precise}
        given = [
            f"--{name.replace('_', '-')}" for name, value in one_step.items() if value not in (None, False)
        ]
        if simulation and given:
            raise InputError(
                f"--criterion simulation chooses the terms by their free run: drop {' and '.join(given)}"
            )
        return simulation

    def frols(self, signals: Signals, candidates: Sequence[Term]) -> NarxSelection:
        """FROLS's selection (:func:`models.selection.select_narx`, whose options these fields
        are) with a progress bar, which counts the terms asked for or the longest path."""
        options = dataclasses.asdict(self) | {"include": self.include or ()}
        return _with_progress(
            self.n_terms or min(self.max_terms, len(candidates)),
            lambda progress: select_narx(signals, candidates, progress=progress, **options),
        )


@dataclasses.dataclass(frozen=True)
class FreeRunOptions:
    """How ``--criterion simulation`` judges candidates on the free run, as given (each field an
    option)."""

    judged: Annotated[
        list[Path] | None,
        typer.Option(
            help="With --criterion simulation: record the free run is judged on (repeatable); without, "
            "the end of each record (--judged-share)."
        ),
    ] = None
    judged_share: Annotated[
        float,
        typer.Option(
            help="With --criterion simulation: share of each record's end the free run is judged on."
        ),
    ] = DEFAULT_JUDGED_SHARE
    threshold: Annotated[
        float,
        typer.Option(
            help="With --criterion simulation: relative drop of the mean-square free-run error a term must "
            "bring to enter, and keep to stay."
        ),
    ] = DEFAULT_THRESHOLD
    preselect: Annotated[
        int, typer.Option(help="With --criterion simulation: candidates tried per step, the first by ERR.")
    ] = DEFAULT_PRESELECT

    def semp(
        self, signals: Signals, candidates: Sequence[Term], judged: Signals | None, rule: RuleOptions
    ) -> SimulationSelection:
        """SEMP's selection (:func:`models.semp.select_by_simulation`) with a progress bar, which
        counts iterations against their bound: the selection usually stops well before."""
        return _with_progress(
            2 * rule.max_terms,
            lambda progress: select_by_simulation(
                signals,
                candidates,
                judged=judged,
                judged_share=self.judged_share,
                include=rule.include or (),
                max_terms=rule.max_terms,
                preselect=self.preselect,
                threshold=self.threshold,
                progress=progress,
            ),
        )


@dataclasses.dataclass(frozen=True)
class ValidationOptions:
    """What the selected model is validated on, as given (each field an option)."""

    holdout: Annotated[
        list[Path] | None, typer.Option(help="Held-out record for the validation errors (repeatable).")
    ] = None
    split: Annotated[
        float,
        typer.Option(help="Without --holdout: share of each record's end held out for validation (0: none)."),
    ] = 0.25
    steps: Annotated[int, typer.Option(help="Horizon k of the k-step prediction errors.")] = 10


@expanded
def select(
    *,
    records: Annotated[
        list[Path], typer.Argument(help=f"Records to select from (.csv, .npz or .mat). {RECORD_SET_HELP}")
    ],
    x: XName = None,
    y: YName = None,
    candidates: CandidateOptions,
    rule: RuleOptions,
    free_run: FreeRunOptions,
    validation: ValidationOptions,
    out: Annotated[
        Path | None,
        typer.Option("--out", help="Write the result to this .json file (a file `train --terms` reads)."),
    ] = None,
    output_error: Annotated[
        bool,
        typer.Option(
            help="Then refine the selected model's θ by output error (least squares on its free run over "
            "the selection records) instead of the one-step least squares, which noise on the output biases."
        ),
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the result as JSON.")] = False,
) -> None:
    """Select NARX terms from a dictionary of lagged monomials by FROLS with the error reduction ratio,
    or (--criterion simulation) by the free-run error of each candidate model.

    Prints the chosen terms with their ERR (or the simulation path) and parameters (least squares,
    or output error with --output-error), and one-step, k-step and free-run errors on held-out
    data. The JSON (--json or --out) is accepted by `narxwatch train baseline --terms FILE`.
    """
    if out is not None and out.suffix.lower() != ".json":
        raise InputError(f"--out {out}: name a .json file, the kind `train --terms` reads")
    layout = signal_layout(x, y)
    simulation = rule.by_simulation(free_run.judged)
    data = _read_data(records, layout, free_run.judged, validation.holdout, validation.split)
    dictionary = candidates.dictionary(data.signals)
    selection: NarxSelection | SimulationSelection = (
        free_run.semp(data.signals, dictionary.candidates, data.judged, rule)
        if simulation
        else rule.frols(data.signals, dictionary.candidates)
    )
    refined = fit_output_error(selection.model, data.signals) if output_error else None
    if refined is not None:
        selection = dataclasses.replace(selection, model=refined.model)
    held_out = validate(selection.model, data.validation, validation.steps) if data.validation else None
    document = _document(selection, refined, held_out, dictionary, data.fs, records, validation, free_run)
    if out is not None:
        write_json(out, document)
    if as_json:
        print(json.dumps(document, indent=1))
        return
    if dictionary.delays is not None:
        _print_delay(dictionary.delay, dictionary.delays, dictionary.ny, dictionary.nx)
    _print_report(selection, refined, held_out)
    if out is not None:
        stdout.print(f"written to {out}")


@dataclasses.dataclass(frozen=True)
class _Data:
    """The records to select from, those to validate on (the held-out records or each record's
    end), the records the free run is judged on (``--judged``) and their sampling rate."""

    signals: Signals
    validation: Signals
    judged: Signals | None
    fs: float | None


def _read_data(
    records: list[Path], layout: Layout, judged: list[Path] | None, holdout: list[Path] | None, split: float
) -> _Data:
    """The records as the options name them, every other one sampled at the rate of ``records``."""
    loaded, fs = read_records(records, layout)
    signals = [(r.x, r.y) for r in loaded]
    judged_signals = _records_like(judged, fs, "judged", layout) if judged else None
    if holdout:
        validation_signals = _records_like(holdout, fs, "held-out", layout)
    else:
        signals, validation_signals = _split(signals, split)
    return _Data(signals, validation_signals, judged_signals, fs)


@dataclasses.dataclass(frozen=True)
class _Dictionary:
    """The candidate dictionary the terms are selected from: the options that made it, the
    input delay used and, where it was chosen, each delay's held-out free-run RMS."""

    degree: int
    ny: int
    nx: int
    delay: int
    delays: dict[int, float] | None
    constant: bool
    extra: list[str]
    candidates: tuple[Term, ...]

    def to_dict(self) -> dict[str, Any]:
        """The dictionary as the JSON document says it."""
        return {
            "degree": self.degree,
            "ny": self.ny,
            "nx": self.nx,
            "delay": self.delay,
            # How the delay was chosen where --delay did not give it: each one's held-out free run.
            "delay_free_run_rms": None
            if self.delays is None
            else {str(d): _finite(self.delays[d]) for d in (0, 1)},
            "constant": self.constant,
            "extra": self.extra,
        }


def _document(
    selection: NarxSelection | SimulationSelection,
    refined: OutputErrorFit | None,
    held_out: Validation | None,
    dictionary: _Dictionary,
    fs: float | None,
    records: list[Path],
    validation: ValidationOptions,
    free_run: FreeRunOptions,
) -> dict[str, Any]:
    """The result as JSON (``--json``, ``--out``): the selection, its refinement and validation,
    the dictionary and where the records came from (with the judged ones, on the free run)."""
    holdout, judged = validation.holdout, free_run.judged
    document = {
        **selection.to_dict(),
        "output_error": None if refined is None else _output_error_dict(refined),
        "held_out": None if held_out is None else held_out.to_dict(),
        "dictionary": dictionary.to_dict(),
        "records": [str(path) for path in records],
        "holdout": {
            "records": [str(path) for path in holdout or []],
            "split": None if holdout else validation.split,
        },
        "fs": fs,
    }
    if isinstance(selection, SimulationSelection):
        document["judged"] = {
            "records": [str(path) for path in judged or []],
            "share": None if judged else free_run.judged_share,
        }
    return document


def _with_progress(total: int, run: Callable[[Callable[[int], None]], Selected]) -> Selected:
    """``run(progress)`` under a progress bar on the terminal's stderr that counts ``total`` steps."""
    with transient_progress(
        TextColumn("selecting"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()
    ) as bar:
        task = bar.add_task("select", total=total)
        return run(lambda step: bar.update(task, completed=step))


def _print_report(
    selection: NarxSelection | SimulationSelection,
    refined: OutputErrorFit | None,
    held_out: Validation | None,
) -> None:
    if isinstance(selection, SimulationSelection):
        _print_simulation(selection)
    else:
        _print_selection(selection)
    if refined is not None:
        stdout.print(
            f"θ refined by output error: free-run RMS on the selection records {refined.start_rms:.4e} → "
            f"{refined.rms:.4e} ({refined.evaluations} free runs)",
            markup=False,
            highlight=False,
        )
    if held_out is not None:
        _print_held_out(held_out)


def _print_delay(delay: int, delays: dict[int, float], ny: int, nx: int) -> None:
    with_x_t, without = (f"{delays[d]:.4e}" if np.isfinite(delays[d]) else "diverged" for d in (0, 1))
    stdout.print(
        f"input delay {delay} chosen (--delay fixes it): the linear ARX({ny}, {nx}) runs free over "
        f"held-out parts of the records at RMS {with_x_t} with x[t] (delay 0), {without} from x[t-1] "
        "(delay 1), on average over three rotations; x[t] is taken only where it lowers that by "
        "more than the spread of the difference between the rotations",
        markup=False,
        highlight=False,
    )


def _finite(value: float) -> float | None:
    return value if np.isfinite(value) else None


def _output_error_dict(fit: OutputErrorFit) -> dict[str, float | int]:
    return {"start_rms": fit.start_rms, "rms": fit.rms, "evaluations": fit.evaluations, "status": fit.status}


def _records_like(paths: list[Path], fs: float | None, role: str, layout: Layout) -> Signals:
    """The records at ``paths``, refused unless sampled at ``fs`` (when both rates are known)."""
    loaded, loaded_fs = read_records(paths, layout)
    if None not in (fs, loaded_fs) and loaded_fs != fs:
        raise InputError(f"the {role} records are sampled at {loaded_fs:g} Hz, the others at {fs:g} Hz")
    return [(r.x, r.y) for r in loaded]


def _split(signals: Signals, share: float) -> tuple[Signals, Signals]:
    """Each record's first (1 − share) for selection, its last ``share`` for validation."""
    if not 0 <= share < 1:
        raise InputError(f"--split must lie in [0, 1), got {share}")
    if share == 0:
        return signals, []
    fitting, held = [], []
    for x, y in signals:
        cut = len(y) - round(share * len(y))
        fitting.append((x[:cut], y[:cut]))
        held.append((x[cut:], y[cut:]))
    return fitting, held


def _terms_table(model: NARX, title: str, err: Sequence[float] | None = None) -> Table:
    """The model's terms with θ and its standard error, and each term's ERR where given."""
    table = Table("term", *(() if err is None else ("ERR",)), "θ", "s.e.", title=title, title_justify="left")
    rows = zip(model.term_names, model.theta, model.standard_errors(), strict=True)
    for row, (name, theta, se) in enumerate(rows):
        ratio = () if err is None else (f"{err[row]:.4e}",)
        table.add_row(Text(name), *ratio, f"{theta: .6e}", f"{se:.2e}")  # names hold [t-1]
    return table


def _print_selection(selection: NarxSelection) -> None:
    model = selection.model
    stdout.print(
        _terms_table(model, f"{len(model.terms)} of {len(selection.candidates)} candidates", selection.err)
    )
    rule = selection.stopped_by
    stdout.print(
        f"stopped by {rule}; 1 − ΣERR = {selection.esr:.3e} on {model.n_obs} equations"
        + (
            f"; removed by pruning: {', '.join(t.name for t in selection.removed)}"
            if selection.removed
            else ""
        ),
        markup=False,
        highlight=False,
    )


def _print_simulation(selection: SimulationSelection) -> None:
    model = selection.model
    title = f"{len(model.terms)} of {len(selection.candidates)} candidates, on the free-run error"
    stdout.print(_terms_table(model, title))
    path = Table("step", "term", "free-run RMS", "terms", title="simulation path", title_justify="left")
    for step in selection.path:
        path.add_row(
            step.action,
            Text("" if step.term is None else step.term.name),
            f"{step.rms:.4e}",
            str(step.n_terms),
        )
    stdout.print(path)
    notes = [
        f"stopped by {selection.stopped_by}",
        f"{selection.evaluations} free runs on {selection.judged_samples} judged samples",
    ]
    if selection.removed:
        notes.append(f"removed by pruning: {', '.join(t.name for t in selection.removed)}")
    if selection.diverged:
        notes.append(f"refused (free run diverged): {', '.join(t.name for t in selection.diverged)}")
    stdout.print("; ".join(notes), markup=False, highlight=False)


def _print_held_out(held_out: Validation) -> None:
    errors = Table("held out", "RMS", "NRMSE", "samples")
    for label, mode in (
        ("one-step", held_out.one_step),
        (f"{held_out.steps}-step", held_out.k_step),
        ("free run", held_out.free_run),
    ):
        errors.add_row(label, f"{mode.rms:.4e}", f"{mode.nrmse:.4e}", str(mode.samples))
    stdout.print(errors)
