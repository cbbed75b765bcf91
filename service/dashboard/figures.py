"""Plotly figures (data and layout as JSON-ready dicts) for the dashboard's charts.

Built here rather than in the browser so that what a chart shows is decided, and tested, in
one place; the page's script only hands each figure to ``Plotly.newPlot``. Times are epoch
milliseconds on date axes.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from models.fnarx import FNARX
from models.validation import OneStepFit
from recordfiles.quantities import SignalDeclaration, signal_label
from service.domain.alarms import CusumSeries
from service.domain.timeline import TimelinePoint
from service.tables import Alarm

Figure = dict[str, Any]
# Above this many points a trace is drawn with WebGL: SVG slows down past a few thousand.
WEBGL_POINTS = 1500
WEBGL_TRACE = "scattergl"
TRAJECTORY_GRID = 65
STATUS_COLOURS = {"healthy": "#2e7d32", "faulty": "#c62828", "unknown_fault": "#ef6c00", "anomaly": "#6a1b9a"}
# The dashboard's stylesheet gives alarm badges the same colours.
ALARM_COLOURS = {"open": "#b71c1c", "acknowledged": "#f9a825", "resolved": "#78909c"}
MODE_COLOURS = ("#1f77b4", "#9467bd", "#17becf", "#8c564b", "#e377c2", "#7f7f7f")
MODE_SYMBOLS = ("circle", "diamond", "square", "triangle-up", "cross", "x")
MARGIN = {"l": 60, "r": 20, "t": 40, "b": 45}
LEGEND_BELOW = {"orientation": "h", "y": -0.2}
CUSUM_AXIS_THRESHOLDS = 3.0  # the CUSUM axis of the k̂ chart reaches this many thresholds
CUSUM_PANEL = 0.3  # the share of the k̂ chart's height its CUSUM panel takes, at the bottom


def _scatter(n: int) -> str:
    return WEBGL_TRACE if n > WEBGL_POINTS else "scatter"


def _ms(moment: dt.datetime) -> float:
    return moment.timestamp() * 1000.0


def _mode_colour(index: int) -> str:
    return MODE_COLOURS[index % len(MODE_COLOURS)]


def k_hat_figure(
    points: Sequence[TimelinePoint],
    interval_label: str,
    cusums: Sequence[CusumSeries] = (),
    alarms: Sequence[Alarm] = (),
) -> Figure:
    """k̂ of each verdict with its interval, one trace per reference mode (Figure 5 over time);
    in a panel below it each fault mode's CUSUM statistic with its threshold, and the alarms: where
    each was raised (a solid line, coloured by its state) and where its drift began (dotted).

    Unknown faults carry no magnitude and are left out. The legend explains the markers'
    colours (the verdict's status) and the alarm lines' (the alarm's state).
    """
    data = _k_hat_traces(points, lambda p: _ms(p.acquired_at))
    data += _status_legend()
    data += _cusum_traces(cusums)
    data += _alarm_traces(alarms, cusums)
    layout = _layout(
        f"Fault magnitude k̂ with its {interval_label} interval",
        "acquired (UTC)",
        "k̂ [%]",
        xaxis={"type": "date"},
        yaxis={"zeroline": True},
        legend=LEGEND_BELOW,
        annotations=[_k_hat_zero()],
    )
    if cusums:
        # The threshold is drawn on the CUSUM's axis, whose zero is not k̂'s: named where it runs.
        threshold = cusums[0].threshold
        layout["annotations"].append(
            _line_label(_threshold_name(threshold), threshold, ALARM_COLOURS["open"], yref="y2")
        )
    if cusums or alarms:
        # The CUSUM and the alarms in a panel of their own below k̂, sharing its time axis: drawn
        # over k̂ on a second scale, the threshold lay wherever k̂'s scale put it, sometimes on k̂ = 0.
        # Up to a few thresholds: a fault's statistic can run to hundreds of σ, and what
        # matters is where it crossed the threshold; beyond the top it leaves the chart.
        layout["yaxis"] |= {"domain": [CUSUM_PANEL + 0.08, 1.0]}
        layout["xaxis"] |= {"anchor": "y2"}
        layout["yaxis2"] = {
            "title": {"text": "CUSUM [σ]" if cusums else ""},
            "showticklabels": bool(cusums),
            "domain": [0.0, CUSUM_PANEL],
            "anchor": "x",
            "range": [0.0, _alarm_axis_top(cusums)],
            "zeroline": False,
            "tickmode": "auto",
            "nticks": 4,
        }
        # Room below the plot for the legend's three groups.
        layout |= {
            "margin": MARGIN | {"b": 60},
            "height": 600,
            "legend": LEGEND_BELOW | {"y": -0.15, "yanchor": "top"},
        }
    return {"data": data, "layout": layout}


def k_hat_condition_figure(
    points: Sequence[TimelinePoint], name: str, unit: str | None, interval_label: str
) -> Figure:
    """k̂ of each verdict against the operating condition ``name`` its record was acquired under,
    with its interval, one trace per reference mode: a magnitude that follows the condition is
    its effect the models miss, a fault one that stands apart whatever the condition.
    Verdicts whose records do not state the condition are left out, as are unknown faults."""
    stated = [p for p in points if name in p.conditions]
    data = _k_hat_traces(stated, lambda p: p.conditions[name]) + _status_legend()
    axis = f"{name} [{unit}]" if unit else name
    layout = _layout(
        f"Fault magnitude k̂ with its {interval_label} interval against {name}",
        axis,
        "k̂ [%]",
        yaxis={"zeroline": True},
        legend=LEGEND_BELOW,
        annotations=[_k_hat_zero()],
    )
    return {"data": data, "layout": layout}


def _k_hat_traces(
    points: Sequence[TimelinePoint], x: Callable[[TimelinePoint], float]
) -> list[dict[str, Any]]:
    """k̂ with its interval at ``x`` of each point, one trace per reference mode, coloured by status."""
    modes = sorted({p.reference_mode for p in points if p.k_hat is not None and p.reference_mode})
    data = []
    for index, mode in enumerate(modes):
        chosen = [p for p in points if p.reference_mode == mode and p.k_hat is not None]
        data.append(
            {
                "type": _scatter(len(chosen)),
                "mode": "markers",
                "name": f"k̂ ({mode} model)",
                "x": [x(p) for p in chosen],
                "y": [p.k_hat for p in chosen],
                "customdata": [p.record_id for p in chosen],
                "marker": {
                    "color": [STATUS_COLOURS[p.status] for p in chosen],
                    "symbol": MODE_SYMBOLS[index % len(MODE_SYMBOLS)],
                    "size": 7,
                },
                "error_y": {
                    "type": "data",
                    "symmetric": False,
                    "array": [_gap(p.interval_high, p.k_hat) for p in chosen],
                    "arrayminus": [_gap(p.k_hat, p.interval_low) for p in chosen],
                    "color": _mode_colour(index),
                    "thickness": 1,
                    "width": 0,
                },
                "hovertemplate": "k̂ %{y:.2f} %<br>record %{customdata}<extra>" + mode + "</extra>",
            }
        )
    return data


def _alarm_axis_top(cusums: Sequence[CusumSeries]) -> float:
    return CUSUM_AXIS_THRESHOLDS * cusums[0].threshold if cusums else 1.0


def _status_legend() -> list[dict[str, Any]]:
    """Legend entries (no points) saying what a marker's colour means."""
    return [
        {
            "type": "scatter",
            "mode": "markers",
            "x": [None],
            "y": [None],
            "name": status.replace("_", " "),
            "marker": {"color": colour, "size": 7},
            "legendgroup": "status",
            "legendgrouptitle": {"text": "verdict (marker colour)"},
            "hoverinfo": "skip",
        }
        for status, colour in STATUS_COLOURS.items()
    ]


def _cusum_traces(cusums: Sequence[CusumSeries]) -> list[dict[str, Any]]:
    data = []
    for index, series in enumerate(cusums):
        x = [_ms(moment) for moment in series.acquired_at]
        data.append(
            _lines(
                x,
                series.statistic,
                name=f"CUSUM ({series.fault_mode})",
                yaxis="y2",
                line={"color": _mode_colour(index), "width": 1.5, "shape": "hv"},
                legendgroup="cusum",
                legendgrouptitle={"text": "sequential test"},
                hovertemplate="CUSUM %{y:.2f} σ<extra>" + series.fault_mode + "</extra>",
            )
        )
    if cusums:
        first, last = min(s.acquired_at[0] for s in cusums), max(s.acquired_at[-1] for s in cusums)
        threshold = cusums[0].threshold
        data.append(
            _lines(
                [_ms(first), _ms(last)],
                [threshold, threshold],
                name=_threshold_name(threshold),
                yaxis="y2",
                line={"color": ALARM_COLOURS["open"], "dash": "dash", "width": 1},
                legendgroup="cusum",
                hoverinfo="skip",
            )
        )
    return data


def _alarm_traces(alarms: Sequence[Alarm], cusums: Sequence[CusumSeries]) -> list[dict[str, Any]]:
    """A vertical line (on the CUSUM axis, up to the threshold or the statistic's top) where each
    alarm was raised, one trace per state; and a dotted one where each CUSUM alarm's drift began."""
    top = _alarm_axis_top(cusums)
    data = []

    def vertical(moments: list[dt.datetime]) -> dict[str, list[float | None]]:
        x: list[float | None] = []
        y: list[float | None] = []
        for moment in moments:
            x += [_ms(moment), _ms(moment), None]
            y += [0.0, top, None]
        return {"x": x, "y": y}

    for state, colour in ALARM_COLOURS.items():
        chosen = [a for a in alarms if a.state == state]
        if chosen:
            data.append(
                {
                    "type": "scatter",
                    "mode": "lines",
                    **vertical([a.triggered_at for a in chosen]),
                    "name": f"alarm raised ({state})",
                    "yaxis": "y2",
                    "line": {"color": colour, "width": 2},
                    "legendgroup": "alarms",
                    "legendgrouptitle": {"text": "alarms (line colour: state)"},
                    "hoverinfo": "x+name",
                }
            )
    drifts = [a.drift_started_at for a in alarms if a.drift_started_at is not None]
    if drifts:
        data.append(
            {
                "type": "scatter",
                "mode": "lines",
                **vertical(drifts),
                "name": "drift began (CUSUM)",
                "yaxis": "y2",
                "line": {"color": ALARM_COLOURS["open"], "width": 1, "dash": "dot"},
                "legendgroup": "alarms",
                "hoverinfo": "x+name",
            }
        )
    return data


def _threshold_name(threshold: float) -> str:
    return f"CUSUM threshold h = {threshold:.2f} σ"


def _line_label(text: str, y: float, colour: str, yref: str = "y", side: str = "right") -> dict[str, Any]:
    """An annotation naming the horizontal reference line at ``y`` (on axis ``yref``), written just
    above it at the plot's ``side``: in the chart itself, so that no line reads as a data value
    whatever the legend shows."""
    return {
        "text": text,
        "xref": "paper",
        "x": 0.0 if side == "left" else 1.0,
        "xanchor": side,
        "yref": yref,
        "y": y,
        "yanchor": "bottom",
        "showarrow": False,
        "font": {"size": 11, "color": colour},
        "bgcolor": "rgba(255,255,255,0.7)",
    }


def _k_hat_zero() -> dict[str, Any]:
    """The k̂ axis's zero line named: no fault, where a healthy record's k̂ scatters about."""
    return _line_label("k̂ = 0 (no fault)", 0.0, "#555", side="left")


def _lines(x: Any, y: Any, **style: Any) -> dict[str, Any]:
    """A line trace (``x`` and ``y`` sequences or arrays) with plotly attributes ``style`` (which may
    set ``type`` to "scattergl")."""
    return {
        "type": "scatter",
        "mode": "lines",
        "x": np.asarray(x).tolist(),
        "y": np.asarray(y).tolist(),
        **style,
    }


def _level(x: Sequence[float], level: float, name: str, colour: str, hover: str) -> dict[str, Any]:
    """A dashed line at ``level`` across the span of ``x`` (none for no points), hovered as ``hover``."""
    ends = [x[0], x[-1]] if x else []
    return _lines(
        ends,
        [level] * len(ends),
        name=name,
        line={"color": colour, "dash": "dash", "width": 1.5},
        hovertemplate=hover + "<extra></extra>",
    )


def _over_time(title: str, y_title: str, **yaxis: Any) -> dict[str, Any]:
    """The layout of a chart over acquisition time, its legend below."""
    return _layout(title, "acquired (UTC)", y_title, xaxis={"type": "date"}, yaxis=yaxis, legend=LEGEND_BELOW)


def _layout(title: str, x_title: str, y_title: str, **extra: Any) -> dict[str, Any]:
    """A single chart's layout: its title, axis titles and the common margins; ``extra`` adds to
    or replaces entries (``xaxis``/``yaxis`` keys merge into the axes)."""
    layout = {
        "title": {"text": title},
        "xaxis": {"title": {"text": x_title}} | extra.pop("xaxis", {}),
        "yaxis": {"title": {"text": y_title}} | extra.pop("yaxis", {}),
        "margin": MARGIN,
    }
    return layout | extra


def _gap(high: float | None, low: float | None) -> float | None:
    return None if high is None or low is None else high - low


def q_figure(points: Sequence[TimelinePoint], alpha: float) -> Figure:
    """The Ljung–Box Q of each fault mode's residual per verdict against its critical value at
    level ``alpha`` (the newest verdict's), each critical value named in the chart (Figure 6).
    Modes whose critical values agree (the same lags) share one line: drawn once per mode, the
    lines and their names would lie on top of each other."""
    names = sorted({m["name"] for p in points for m in p.modes})
    data = []
    criticals: dict[float, list[str]] = {}
    for index, name in enumerate(names):
        pairs = [(p, m) for p in points for m in p.modes if m["name"] == name]
        data.append(
            {
                "type": _scatter(len(pairs)),
                "mode": "markers",
                "name": f"Q ({name} model)",
                "x": [_ms(p.acquired_at) for p, _ in pairs],
                "y": [m["q"] for _, m in pairs],
                "customdata": [p.record_id for p, _ in pairs],
                "marker": {"color": _mode_colour(index), "size": 5},
                "hovertemplate": "Q %{y:.1f}<br>record %{customdata}<extra>" + name + "</extra>",
            }
        )
        criticals.setdefault(pairs[-1][1]["q_critical"], []).append(name)
    judged = [_ms(p.acquired_at) for p in points if p.modes]
    span = [judged[0], judged[-1]] if judged else []
    annotations = []
    for critical, modes in criticals.items():
        label = f"Q critical (α = {alpha:g})" + (f", {', '.join(modes)}" if len(criticals) > 1 else "")
        colour = _mode_colour(names.index(modes[0])) if len(modes) == 1 else "#555"
        data.append(_level(span, critical, label, colour, "χ² critical %{y:.1f}"))
        # On a log axis an annotation's y is the exponent.
        annotations.append(_line_label(label, float(np.log10(critical)), colour))
    layout = _over_time(
        "Residual whiteness: Ljung–Box Q per fault-mode model", "Ljung–Box Q (log scale)", type="log"
    )
    return {"data": data, "layout": layout | {"annotations": annotations}}


def severity_figure(points: Sequence[TimelinePoint], alarms: Sequence[Alarm] = ()) -> Figure:
    """A healthy baseline's severity per verdict, coloured by status, against the healthy level 1:
    how many times a healthy record's free-run error variance each record's is, the figure to
    trend for a structure judged by its baseline alone. A diverged free run has none. Where each
    alarm was raised is marked as on the k̂ chart, which such a structure has not."""
    chosen = [p for p in points if p.severity is not None]
    x = [_ms(p.acquired_at) for p in chosen]
    data = [
        {
            "type": _scatter(len(chosen)),
            "mode": "markers",
            "name": "severity",
            "x": x,
            "y": [p.severity for p in chosen],
            "customdata": [p.record_id for p in chosen],
            "marker": {"color": [STATUS_COLOURS[p.status] for p in chosen], "size": 7},
            "hovertemplate": "severity %{y:.3f}<br>record %{customdata}<extra></extra>",
        },
        _level(x, 1.0, "healthy level (1)", STATUS_COLOURS["healthy"], "healthy level 1"),
        *_status_legend(),
        *_alarm_traces(alarms, ()),
    ]
    title = "Severity: the record's free-run error variance over a healthy record's"
    layout = _over_time(title, "severity (healthy: 1)", rangemode="tozero")
    layout["annotations"] = [_line_label("healthy level (1)", 1.0, STATUS_COLOURS["healthy"])]
    if alarms:  # the alarm lines' own axis, from the bottom of the plot to its top
        layout["yaxis2"] = {"overlaying": "y", "range": [0.0, 1.0], "visible": False}
    # The legend's groups below the axis title, not over it.
    layout |= {
        "legend": LEGEND_BELOW | {"y": -0.15, "yanchor": "top"},
        "margin": MARGIN | {"b": 60},
        "height": 480,
    }
    return {"data": data, "layout": layout}


def trajectories_figure(model: FNARX, level: float = 0.95) -> Figure:
    """Each coefficient θ_i(k) over the model's magnitude range with its pointwise interval (Figure 4)."""
    k = np.linspace(model.basis.k_min, model.basis.k_max, TRAJECTORY_GRID)
    trajectories = model.trajectories(k, level)
    columns = min(4, len(model.terms))
    rows = -(-len(model.terms) // columns)
    data: list[dict[str, Any]] = []
    annotations = []
    for index, name in enumerate(trajectories.term_names):
        axis = "" if index == 0 else str(index + 1)
        axes = {"xaxis": f"x{axis}", "yaxis": f"y{axis}", "showlegend": index == 0}
        band = {"line": {"width": 0}, "hoverinfo": "skip", **axes}
        data.append(_lines(k, trajectories.high[:, index], name="upper", **band) | {"showlegend": False})
        data.append(
            _lines(k, trajectories.low[:, index], name=f"{level:.0%} interval", **band)
            | {"fill": "tonexty", "fillcolor": "rgba(31,119,180,0.25)"}
        )
        data.append(_lines(k, trajectories.values[:, index], name="θ(k)", line={"color": "#1f77b4"}, **axes))
        annotations.append(
            {
                "text": name,
                "xref": f"x{axis} domain",
                "yref": f"y{axis} domain",
                "x": 0.5,
                "y": 1.12,
                "showarrow": False,
                "font": {"size": 11},
            }
        )
    layout = {
        "title": {"text": f"Coefficients of fault mode {model.name} against its magnitude k [%]"},
        "grid": {"rows": rows, "columns": columns, "pattern": "independent"},
        "annotations": annotations,
        "margin": {"l": 60, "r": 20, "t": 70, "b": 40},
        "height": 260 * rows + 80,
        "legend": {"orientation": "h", "y": -0.08},
    }
    return {"data": data, "layout": layout}


def record_figures(
    fit: OneStepFit, fs: float, max_lag: int, shown: int, label: str, y: SignalDeclaration | None
) -> dict[str, Figure]:
    """Measured vs one-step predicted response, the residual, and its autocorrelation with bands
    (Figure 3), y and e labelled as the structure declares its response ``y``. The first ``shown``
    samples are drawn; the autocorrelation is of the whole residual."""
    t = (np.arange(min(shown, fit.measured.size)) + max_lag) / fs
    n = len(t)
    kind = _scatter(n)
    legend = {"orientation": "h", "y": -0.25}
    response = {
        "data": [
            _lines(t, fit.measured[:n], type=kind, name="measured y", line={"color": "#222", "width": 1.5}),
            _lines(
                t,
                fit.predicted[:n],
                type=kind,
                name=f"one-step predicted ({label})",
                line={"color": "#e4572e", "width": 1.2, "dash": "dash"},
            ),
        ],
        "layout": _layout(
            "Response: measured and one-step predicted",
            "time [s]",
            signal_label("y", y),
            yaxis={"exponentformat": "e"},
            legend=legend,
        ),
    }
    residual = {
        "data": [
            _lines(
                t,
                fit.residual[:n],
                type=kind,
                name="residual e = y − ŷ",
                line={"color": "#1f77b4", "width": 1},
            )
        ],
        "layout": _layout(
            "One-step prediction error",
            "time [s]",
            signal_label("e", y, quantity=False),
            yaxis={"exponentformat": "e"},
        ),
    }
    test = fit.autocorrelation
    band_line = {"color": "#c62828", "dash": "dash", "width": 1}
    autocorrelation = {
        "data": [
            {
                "type": "bar",
                "name": "φ_ee(τ)",
                "x": test.lags.tolist(),
                "y": test.values.tolist(),
                "marker": {"color": "#1f77b4"},
            },
            _lines(test.lags, test.pointwise_band, name=f"±{1 - test.alpha:.0%} band", line=band_line),
            _lines(test.lags, -test.pointwise_band, showlegend=False, line=band_line, hoverinfo="skip"),
        ],
        "layout": _layout("Residual autocorrelation", "lag τ [samples]", "φ_ee(τ)", legend=legend),
    }
    return {"response": response, "residual": residual, "autocorrelation": autocorrelation}


def channel_figures(
    residual: np.ndarray,
    channels: list[str],
    fs: float,
    lags: int,
    shown: int,
    label: str,
    y: SignalDeclaration | None,
) -> dict[str, Figure]:
    """A vector mode's one-step residual on each channel (``residual`` (n, K), columns named by
    ``channels``), each with its RMS over the whole record, in the unit the structure declares its
    response ``y`` (every channel) in; the first ``shown`` samples are drawn."""
    unit = f" {y.unit}" if y and y.unit else ""
    n = min(shown, len(residual))
    t = (np.arange(n) + lags) / fs
    kind = _scatter(n)
    out = {}
    for j, name in enumerate(channels):
        rms = float(np.sqrt(np.mean(residual[:, j] ** 2)))
        out[f"residual-{name}"] = {
            "data": [
                _lines(t, residual[:n, j], type=kind, name=f"e_{name}", line={"color": "#1f77b4", "width": 1})
            ],
            "layout": _layout(
                f"Channel {name}: one-step residual of the {label} (RMS {rms:.3g}{unit})",
                "time [s]",
                signal_label(f"e_{name}", y, quantity=False),
                yaxis={"exponentformat": "e"},
            ),
        }
    return out


def refinement_figure(before: dict[str, Any], after: dict[str, Any], y: SignalDeclaration | None) -> Figure:
    """Held-out one-step and free-run RMS error of the declared and the refined model, in the unit
    the structure declares its response ``y`` in."""
    measures = [("one_step_rms", "one-step RMS"), ("free_run_rms", "free-run RMS")]
    labels = [label for _, label in measures]
    data = [
        {
            "type": "bar",
            "name": name,
            "x": labels,
            "y": [figures.get(key) for key, _ in measures],
            "marker": {"color": colour},
            "texttemplate": "%{y:.3g}",
            "textposition": "outside",
        }
        for name, figures, colour in (("declared", before, "#9e9e9e"), ("refined", after, "#2e7d32"))
    ]
    layout = {
        "title": {"text": "Error on held-out data, before and after"},
        "barmode": "group",
        "yaxis": {
            "title": {"text": signal_label("RMS error of y", y, quantity=False)},
            "type": "log",
            "exponentformat": "e",
        },
        "margin": MARGIN,
    }
    return {"data": data, "layout": layout}
