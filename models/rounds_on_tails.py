"""The rounds' models judged against each other on the held-out tails (:mod:`models.held_out`).

The gate compares the loop's final model with the start, and a round that made the model worse
passes it whenever the rounds before it had gained enough: the check blocks chose that round's
effect as the best of many, the same upward bias the tails are held out against. So, where the
tails approve the final model, the model the first k rounds grew is made for each earlier k
(the final structure without the later rounds' terms, fitted by least squares on the heads, as
the rounds fitted it) and run free over the tails as well; the model, final or earlier, whose one
free run over them is lowest is the one judged against the start, the later rounds' effects set
aside. A later round must earn its place on the data no choice saw, as Piroddi and Spinelli's
pruning makes each term earn it on the simulation error (Int. J. Control 76, 2003). Only where the
final model passed: the tails already showed that refining helps, and choosing among nested
models then gives the comparison with the start no second chance it did not have. And only over
tails of ``MIN_BLOCK`` samples or more (:func:`models.refinement.refine`'s short records): one
free run over a hundred samples tells nested models apart by chance.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from models.checking import CheckSplit, Segments, Structure, free_run_rms
from models.growing import Grown
from models.round_criteria import fitted_on_all
from models.scoring import Records
from models.terms import parse_terms


def earlier_rounds(grown: Grown) -> list[tuple[tuple[int, ...], Structure]]:
    """For each round k whose effect the refined structure holds, but the last, the rounds after
    it (their indices in the rounds' reports) and the structure the rounds up to k grew: the
    refined structure (as pruned) without the later rounds' terms, and with the noise order the
    rounds up to k reached. None where the structure grew across folds or the final check took
    the rounds back, nor before a round that added limits or a rectifier rather than terms."""
    result = grown.refinement
    if grown.folded is not None or result.withdrawn:
        return []
    rounds = result.rounds
    kept = [i for i, step in enumerate(rounds) if step.added is not None and not step.pruned_whole]
    final = grown.structure
    added = [rounds[i].added for i in kept]
    earlier = []
    for position in range(len(kept) - 1):
        later = [score for score in added[position + 1 :] if score is not None]
        if any(not score.terms and not score.noise_lags for score in later):
            continue
        dropped = {term for score in later if not score.noise_lags for term in parse_terms(score.terms)}
        noise_lags = final.noise_lags
        if any(score.noise_lags for score in later):
            noise_lags = max((score.noise_lags for score in added[: position + 1] if score), default=0)
        terms = tuple(term for term in final.terms if term not in dropped)
        earlier.append((tuple(kept[position + 1 :]), replace(final, terms=terms, noise_lags=noise_lags)))
    return earlier


def best_rounds_on_tails(grown: Grown, heads: Records, tails: Segments, refined_rms: float) -> Grown | None:
    """``grown`` with the rounds after the k-th set aside, where the model the first k grew ran
    free over the ``tails`` (each continuing its record's head in ``heads``) lower than the
    refined model, whose run over them was ``refined_rms`` (the comparison's,
    :attr:`models.held_out.HeldOut.refined_rms`), and every model between them
    (:func:`earlier_rounds`, the earliest of equals); None where the refined model ran lowest. Its
    parameters by least squares on the heads (the loop's records: the fits its rounds made there
    are ``grown.fits``), its check blocks' figure read again."""
    lowest, best = refined_rms, None
    for later, structure in earlier_rounds(grown):
        model, noise = fitted_on_all(heads, structure, grown.fits)
        rms = free_run_rms(model, tails, heads)
        if np.isfinite(rms) and rms < lowest:
            lowest, best = rms, (later, structure, model, noise)
    if best is None:
        return None
    later, structure, model, noise = best
    result = grown.refinement
    rounds = tuple(
        replace(step, set_aside=True) if i in later else step for i, step in enumerate(result.rounds)
    )
    refinement = replace(
        result,
        refined=model,
        noise=noise,
        rounds=rounds,
        estimator="least squares",
        check_rms=CheckSplit.of(heads).error(structure),
    )
    return grown._replace(refinement=refinement, structure=structure, least_squares=model)
