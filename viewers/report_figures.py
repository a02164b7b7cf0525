"""The figures of ``codearcade report`` (``viewers/report.py``), each a matplotlib figure drawn from the plain data
:func:`viewers.report.collect` reads: the scores per iteration (``score.png``), the lineage of candidates
(``lineage.png``), an eval run's episode returns, the code's size and complexity (``code.png``), the tokens
(``tokens.png``) and the LLM calls over time. Forfeits are drawn as marks, never at a partial return
(``store/scores.py``); every text from the store passes ``viewers.safe_text.plot_text``, and titles and legends
are fitted to the image however long the names in them: :func:`fitted_layout` (compare's figure uses it too) breaks
a title at its spaces, a name without one between its characters (:func:`fit_text`), and cuts it after
:data:`TITLE_LINES` lines; the calls legend cuts a long model name in its middle. Agg canvas: no display;
:func:`save_png` writes a figure with its layout solved once and one draw.
"""

from __future__ import annotations

import functools
import re
import textwrap
from typing import Any, Callable, Sequence

from store.scores import is_forfeit, score_episodes, score_text
from store.statistics import CONFIDENCE, MEAN_METHOD
from viewers.safe_text import (plot_text)


STATUS_STYLE = {  # update_status -> (marker, colour, label)
    "initial": ("s", "#555555", "starting policy"),
    "accepted": ("o", "#2ca02c", "new code accepted"),
    "rejected": ("X", "#d62728", "candidate rejected"),
    "unchanged": ("o", "#999999", "no change"),
    "llm_error": ("^", "#ff7f0e", "LLM call failed"),
}
END_COLOURS = {"terminated": "#1f77b4", "truncated": "#7f7f7f", "policy_error": "#d62728", "timeout": "#d62728",
               "crashed": "#d62728"}


def fit_text(text: str, width: float, measure: Callable[[str], float], *, at_spaces: bool = True) -> str:
    """``text`` broken into lines that ``measure`` (a line's drawn width) finds no wider than ``width``: each line
    too wide at its spaces (``at_spaces``; else where matplotlib's ``wrap=True`` breaks it anyway), and a run of
    characters without a space that alone is too wide between its characters, never inside an escape (``\\$``:
    the two halves would be mathtext). matplotlib breaks lines at spaces only: a long name without one ran past
    the image's edge."""
    def pieces(word: str) -> list[str]:
        if measure(word) <= width:
            return [word]
        units, out = re.findall(r"\\.|.", word, flags=re.S), []
        while units:
            fits = 1  # the most units from the start that fit (at least one: a glyph wider than the line is kept)
            low, high = 2, len(units)
            while low <= high:
                mid = (low + high) // 2
                if measure("".join(units[:mid])) <= width:
                    fits, low = mid, mid + 1
                else:
                    high = mid - 1
            out.append("".join(units[:fits]))
            units = units[fits:]
        return out

    lines = []
    for line in text.split("\n"):
        if measure(line) <= width:
            lines.append(line)
            continue
        if not at_spaces:
            lines.append(" ".join("\n".join(pieces(word)) for word in line.split(" ")))
            continue
        current = ""
        for word in line.split(" "):
            if current and measure(f"{current} {word}") <= width:
                current = f"{current} {word}"
                continue
            if current:
                lines.append(current)
            *done, current = pieces(word)
            lines += done
        lines.append(current)
    return "\n".join(lines)


TITLE_LINES = 5
"""The most lines a title is drawn in: the rest of a longer one (a name of hundreds of characters) is cut, so that the
axes keep their height (constrained layout gives up on axes a title leaves no room for, and draws past the image)."""


def _cut(line: str, width: float, measure: Callable[[str], float]) -> str:
    """``line`` ended by an ellipsis where the rest was cut, no wider than ``width``."""
    while line and measure(line + "…") > width:
        line = line[:-1]
    if (len(line) - len(line.rstrip("\\"))) % 2:  # no half of an escape (``\\$``) left at the cut
        line = line[:-1]
    return line.rstrip() + "…"


def _middle_cut(text: str, most: int) -> str:
    """``text`` (a :func:`plot_text`) of at most ``most`` characters, the middle of a longer one cut to an ellipsis:
    model names of an ensemble differ at their ends, and the legend of long ones left the axes no height. Never
    inside an escape (``\\$``)."""
    units = re.findall(r"\\.|.", text, flags=re.S)
    if len(units) <= most:
        return text
    return "".join(units[:most // 2 - 1]) + "…" + "".join(units[-(most // 2):])


def _measure(renderer, text) -> Callable[[str], float]:
    """How wide ``text`` (an artist) would draw a line, in pixels of ``renderer``."""
    prop = text.get_fontproperties()
    return functools.cache(lambda line: renderer.get_text_width_height_descent(line, prop, ismath=False)[0])


def fitted_layout():
    """A figure's layout engine: constrained layout, then the titles given to its ``fit`` fitted to the image. A
    title is centred over its axes (a suptitle over the figure), so its widest line is twice the distance from that
    centre to the nearer edge. matplotlib's ``wrap=True`` breaks lines at spaces to that width; a run of characters
    without a space wider than it (a long run name, model id) is broken here (:func:`fit_text`), once the layout has
    placed the axes, and a title of more than :data:`TITLE_LINES` lines is cut. The layout is solved again only when
    a title changed: an ordinary title, inside the image as drawn, is not measured again and draws as before."""
    return _fitted_layout_class()()


@functools.cache
def _fitted_layout_class():
    """:func:`fitted_layout`'s class, made on first use: importing this module imports no matplotlib."""
    from matplotlib.layout_engine import ConstrainedLayoutEngine

    class FittedLayout(ConstrainedLayoutEngine):
        def __init__(self, **kwargs):
            super().__init__(**kwargs)
            self._titles: list[tuple[Any, str]] = []

        def fit(self, text) -> None:
            """Fit ``text`` (a centred title, ``wrap=True``) to the image whenever the layout is solved."""
            self._titles.append((text, text.get_text()))

        def execute(self, fig):
            super().execute(fig)
            get_renderer = getattr(fig.canvas, "get_renderer", None)  # the Agg canvas save_png and a draw use
            if get_renderer is None or not self._titles:
                return
            renderer, changed = get_renderer(), False
            for text, written in self._titles:
                box = text.get_window_extent(renderer)  # as wrap=True draws it, of the lines the layout measured
                line = text.get_fontsize() * fig.dpi / 72 * 1.2  # matplotlib's spacing of a text's lines
                if (text.get_text() == written and fig.bbox.x0 <= box.x0 and box.x1 <= fig.bbox.x1
                        and box.height < (TITLE_LINES - 0.5) * line):
                    continue  # an ordinary title: inside, and measured no further (a measure costs 2 ms)
                x = text.get_transform().transform(text.get_position())[0]
                width = 2 * min(x - fig.bbox.x0, fig.bbox.x1 - x) - 2  # less a pixel each side for the rounding
                measure = _measure(renderer, text)
                fitted = fit_text(written, width, measure, at_spaces=False)
                lines = fit_text(fitted, width, measure).split("\n")  # as wrap=True draws it: greedy at spaces
                if len(lines) > TITLE_LINES:
                    fitted = "\n".join(lines[:TITLE_LINES - 1] + [_cut(lines[TITLE_LINES - 1], width, measure)])
                if fitted != text.get_text():
                    text.set_text(fitted)
                    changed = True
            if changed:  # a title of more lines: the axes below it lower
                super().execute(fig)

    return FittedLayout


def _figure(rows: int = 1, height: float = 4.4):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.5, height), dpi=110, layout=fitted_layout())
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.spines[["top", "right"]].set_visible(False)
    return fig, axes


def save_png(fig, path) -> None:
    """Write ``fig`` (a constrained-layout figure of this module or ``viewers/compare_report.py``) as a PNG at
    ``path``: its layout solved once, by the Agg renderer that then draws it, and the figure drawn once.

    ``savefig`` on a figure with a layout engine draws it twice: once with rendering off to run the layout, then
    for the pixels. Solving the layout first and taking the engine off leaves one draw, the same pixels (measured
    2026-12-06: a report's five figures 1.22 s of CPU, 1.07 s this way). One canvas for both, so the text sizes
    the layout measures are cached for the draw. Compression level 3 of zlib's 9 (matplotlib's default, PIL's,
    is 6): about 10 ms less per figure, files about 3% larger."""
    from contextlib import suppress

    from matplotlib.backends.backend_agg import FigureCanvasAgg

    if not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    engine = fig.get_layout_engine()
    if engine is not None:
        with suppress(ValueError):  # as Figure.draw does: a layout that cannot be solved leaves the axes as they are
            engine.execute(fig)
        fig.set_layout_engine(None)
    fig.savefig(path, format="png", pil_kwargs={"compress_level": 3})


def _legend_below(fig, handles) -> None:
    """The figure's legend below its axes, in as many columns as fit in its width (three at most): in three, the
    long model names of an ensemble made a legend wider than the image, cut at both sides."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    renderer = FigureCanvasAgg(fig).get_renderer()  # the canvas save_png draws with
    for ncol in (3, 2, 1):
        legend = fig.legend(handles=handles, fontsize=8, loc="outside lower center", ncol=ncol, frameon=False)
        if ncol == 1 or legend.get_window_extent(renderer).width <= fig.bbox.width:
            return
        legend.remove()


def _nan(value: float | None) -> float:
    """A score for a plot: None (a forfeit: no score) is a gap in the line."""
    return float("nan") if value is None else value


def _integer_x(ax, xs: Sequence[int]) -> None:
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    if xs:
        ax.set_xlim(min(xs) - 0.5, max(xs) + 0.5)


def _title(data: dict[str, Any], what: str) -> str:
    run = data["run"]
    model = f", {run['model']}" if run["model"] else ""
    # wrapped at 90 characters; a longer word is broken where it meets the image's edge (fitted_layout)
    named = f" '{run['name']}'" if run.get("name") else ""
    return "\n".join(textwrap.wrap(plot_text(f"{run['game']} · {what}"), 90, break_long_words=False) +
                     textwrap.wrap(plot_text(f"run {run['run_id']}{named} ({run['kind']}{model})"), 90,
                                   break_long_words=False))


def _set_title(ax, data: dict[str, Any], what: str) -> None:
    """The axes' title: :func:`_title`, wrapped at its spaces by matplotlib (``wrap=True``) to stay inside the
    figure, a name without a space broken between its characters (:func:`fitted_layout`). Centred over axes that
    a legend beside them pushes to the left, a title wider than the axes ran off the image's left edge: constrained
    layout leaves a title's width out of the margins it makes."""
    ax.set_title(_title(data, what), fontsize=11, wrap=True)
    ax.figure.get_layout_engine().fit(ax.title)


def scores_figure(data: dict[str, Any]):
    """Score per iteration with the best so far (optimize runs); return per episode (eval runs)."""
    if data["run"]["kind"] == "eval":
        return episode_returns_figure(data)
    curve = data["curve"]
    if not curve:
        return None
    fig, (ax,) = _figure()
    xs = [r["iteration"] for r in curve]
    evals = [e for e in data["episodes"] if e["kind"] == "eval"]
    n_eval = max((sum(1 for e in evals if e["iteration"] == x) for x in xs), default=1)
    kept = [e for e in evals if e["iteration"] in xs and not is_forfeit(e["end_reason"])]  # a forfeit: below
    if n_eval > 1 and kept:
        ax.scatter([e["iteration"] for e in kept], [e["return"] for e in kept],
                   s=12, color="#1f77b4", alpha=0.25, linewidths=0, label="one evaluation episode played out",
                   zorder=2)
    # store/scores.py's interval over the episodes that scored each iteration (store/showing.py)
    band = [(r["iteration"], r["score_low"], r["score_high"]) for r in curve if r.get("score_low") is not None]
    if band:
        counts = "/".join(str(n) for n in sorted({r["score_n"] for r in curve if r.get("score_low") is not None}))
        ax.fill_between([b[0] for b in band], [b[1] for b in band], [b[2] for b in band], color="#1f77b4",
                        alpha=0.15, linewidth=0, zorder=1,
                        label=f"{CONFIDENCE * 100:g}% {MEAN_METHOD} interval, n={counts} episodes")
    ax.plot(xs, [_nan(r["score"]) for r in curve], "-", color="#1f77b4", linewidth=1.8, zorder=3,
            label=f"score (mean return of {n_eval} evaluation episode{'s' * (n_eval != 1)})")
    served = data["run"]["kind"] == "serve"  # its curve is the training scores; validation picks its best
    ax.step(xs, [_nan(r["best_score"]) for r in curve], where="post", color="#ff7f0e", linestyle="--",
            linewidth=1.6, label="best training score so far" if served else "best so far", zorder=3)
    forfeits = [r["iteration"] for r in curve if r.get("forfeit")]
    if forfeits:  # a forfeit has no score (store/scores.py): a marker on the axes' floor, at no return
        _forfeit_marks(ax, forfeits, "forfeited a game: no score")
    for status, (marker, colour, label) in STATUS_STYLE.items():
        pts = [(r["iteration"], r["score"]) for r in curve if r["update_status"] == status and r["score"] is not None]
        if pts:
            ax.scatter(*zip(*pts), marker=marker, s=46, color=colour, label=label, zorder=4,
                       edgecolors="white", linewidths=0.6)
    repaired = [(r["iteration"], r["score"]) for r in curve
                if r.get("repairs") and r["update_status"] == "accepted" and r["score"] is not None]
    if repaired:  # updates a repair turn saved: without it these iterations would have been rejections
        ax.scatter(*zip(*repaired), marker="o", s=140, facecolors="none", edgecolors="#2ca02c", linewidths=1.4,
                   zorder=5, label="accepted after a repair turn (--repairs)")
    backs = [r["iteration"] for r in curve if r["rolled_back"]]
    for i, x in enumerate(backs):
        ax.axvline(x, color="#9467bd", linestyle=":", linewidth=1.2,
                   label="regression: rolled back" if i == 0 else None)
    _integer_x(ax, xs)
    ax.set_xlabel("iteration (0 = starting policy; k = after the k-th LLM update)")
    ax.set_ylabel("evaluation return")
    scored = [r for r in curve if r["best_score"] is not None]
    summary = data.get("summary") or {}
    if summary.get("best_by") == "validation":  # the run's best (view run_best), at its training score
        picked = next((r for r in curve if r["iteration"] == summary["best_iteration"] and r["score"] is not None),
                      None)
        if picked is not None:
            ax.annotate(f"best by validation {score_text(summary['best_score'])}\n(iteration {picked['iteration']})",
                        (picked["iteration"], picked["score"]), textcoords="offset points", xytext=(0, 10),
                        ha="center", va="bottom", fontsize=8, color="#ff7f0e")
    elif scored:
        best = max(scored, key=lambda r: (r["best_score"], -r["iteration"]))
        ax.annotate(f"best {score_text(best['best_score'])}\n(iteration {best['best_iteration']})",
                    (best["best_iteration"], best["best_score"]), textcoords="offset points", xytext=(0, 10),
                    ha="center", va="bottom", fontsize=8, color="#ff7f0e")
    ax.margins(y=0.15)
    _set_title(ax, data, "score per iteration")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    return fig


DECISION_STYLE = {  # candidates.decision -> (marker, colour, label)
    "best": ("*", "#ff7f0e", "new best"),
    "kept": ("o", "#1f77b4", "kept"),
    "discarded": ("o", "#aaaaaa", "discarded"),
    "rolled_back": ("v", "#9467bd", "regressed: rolled back"),
    "rejected": ("X", "#d62728", "rejected"),
}


FORFEIT_STYLE = ("X", "#8c564b", "forfeited a game: no score")
"""How a candidate that forfeited is drawn on the lineage's lane (marker, colour, label)."""

UNPLAYED_STYLE = {  # how a candidate that was never played is drawn on the "not played" lane: hollow markers
    "screened": ("D", "#9467bd", "not played: screened out"),
    "llm_error": ("^", "#ff7f0e", "not played: LLM call failed"),
    "rejected": ("X", "#d62728", "not played: rejected code"),
}


def unplayed_reason(node: dict[str, Any]) -> str | None:
    """Why a lineage row's score is not its own (a key of :data:`UNPLAYED_STYLE`), or None when its code was played.

    A candidate whose reply was rejected (no usable code, invalid code, screened out by the cascade) or whose LLM
    call failed is assessed as its parent: the store gives it its parent's version and score, which say nothing
    of what it proposed. A candidate caught tampering was played (its proposed version is the assessed one)."""
    if node["update_status"] not in ("rejected", "llm_error"):
        return None
    if node["proposed_version_id"] is not None and node["proposed_version_id"] == node["policy_version_id"]:
        return None
    if node.get("evaluation") == "screened":
        return "screened"
    return "llm_error" if node["update_status"] == "llm_error" else "rejected"


def _lane(node: dict[str, Any]) -> str | None:
    """Why a lineage row is drawn on the lane below every score: :func:`unplayed_reason`, or ``forfeited`` for a
    candidate that was played but forfeited a game (no score: ``store/scores.py``); None: at its score."""
    return unplayed_reason(node) or ("forfeited" if node["score"] is None else None)


def lineage_figure(data: dict[str, Any]):
    """Every candidate at (iteration, score), an edge to the candidate it improved; the standard-protocol score
    beside each one when the run measured it. None when there is nothing to draw.

    Candidates that were never played are drawn hollow on a "not played" lane below every score, with a dotted
    edge from their parent: at their parent's score they would claim a result they never had. A candidate that
    forfeited a game has no score and is drawn on that lane too, as a forfeit."""
    nodes = [n for n in data.get("lineage") or [] if n["score"] is not None or n.get("forfeit")
             or unplayed_reason(n) is not None]
    if data["run"]["kind"] == "eval" or len(nodes) < 2:
        return None
    fig, (ax,) = _figure(height=4.8)
    played = [n for n in nodes if _lane(n) is None]
    scores = [n["score"] for n in played] or [0.0]
    low, high = min(scores), max(scores)
    lane = low - 0.22 * max(high - low, 1.0)
    at = {(n["iteration"], n["candidate"]): n for n in nodes}

    def y(n: dict[str, Any]) -> float:
        return n["score"] if _lane(n) is None else lane

    def anchor(n: dict[str, Any] | None) -> dict[str, Any] | None:
        """Where an edge to a child of ``n`` starts: ``n``, or for one never played the played candidate whose
        code it stands for (its nearest played ancestor: what the child really improved)."""
        seen = set()
        while n is not None and unplayed_reason(n) is not None and id(n) not in seen:
            seen.add(id(n))
            n = at.get((n["parent_iteration"], n["parent_candidate"]))
        return n

    for n in nodes:
        parent = anchor(at.get((n["parent_iteration"], n["parent_candidate"])))
        if parent is not None:
            ax.plot([parent["iteration"], n["iteration"]], [y(parent), y(n)],
                    ":" if _lane(n) else "-", color="#bbbbbb", linewidth=0.9, zorder=1)
    for decision, (marker, colour, label) in DECISION_STYLE.items():
        pts = [(n["iteration"], n["score"]) for n in played if n["decision"] == decision]
        if pts:  # the best above the rest: a candidate of its iteration with the same score hid it
            ax.scatter(*zip(*pts), marker=marker, s=70 if marker == "*" else 36, color=colour, label=label,
                       zorder=4 if decision == "best" else 3, edgecolors="white", linewidths=0.5)
    for reason, (marker, colour, label) in {**UNPLAYED_STYLE, "forfeited": FORFEIT_STYLE}.items():
        pts = [(n["iteration"], lane) for n in nodes if _lane(n) == reason]
        if pts:
            ax.scatter(*zip(*pts), marker=marker, s=40, facecolors="none", edgecolors=colour, linewidths=1.2,
                       label=label, zorder=3)
    forfeited = sum(1 for n in nodes if _lane(n) == "forfeited")
    if len(played) < len(nodes):
        ax.axhline(lane, color="#dddddd", linewidth=6, zorder=0)
        ax.annotate("not played" if not forfeited else "no score: not played or forfeited", (0, lane),
                    xycoords=("axes fraction", "data"), xytext=(4, 5),
                    textcoords="offset points", fontsize=8, color="#777777", va="bottom")
    robust = [(n["iteration"], n["standard_score"]) for n in played if n.get("standard_score") is not None]
    if robust:
        ax.scatter(*zip(*robust), marker="_", s=60, color="#2ca02c", zorder=2,
                   label="score under the standard protocol (sticky actions)")
    _integer_x(ax, [n["iteration"] for n in nodes])
    strategy = nodes[-1]["strategy"]
    ax.set_xlabel("iteration (each dot one candidate; lines to the candidate it improved)")
    ax.set_ylabel("evaluation return")
    ax.margins(y=0.12)
    if len(played) < len(nodes):  # no score ticks at the lane: its height is no score
        bottom, top = ax.get_ylim()
        ax.set_yticks([t for t in ax.get_yticks() if (low + lane) / 2 <= t <= top])
        ax.set_ylim(bottom, top)
    unplayed = len(nodes) - len(played) - forfeited
    _set_title(ax, data, f"lineage ({strategy}: {len(nodes)} candidates, {unplayed} not played"
               + (f", {forfeited} forfeited" if forfeited else "") + ")")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    return fig


def _forfeit_marks(ax, xs: Sequence[float], label: str) -> None:
    """Forfeits at ``xs``: red crosses on the axes' floor (a height in the axes, not a return: a forfeit has no
    score, ``store/scores.py``), whatever the y scale."""
    from matplotlib.transforms import blended_transform_factory

    ax.plot(list(xs), [0.04] * len(xs), linestyle="none", marker="X", markersize=8, markerfacecolor="none",
            markeredgecolor="#d62728", markeredgewidth=1.3, zorder=5, label=label, clip_on=False,
            transform=blended_transform_factory(ax.transData, ax.transAxes))


def episode_returns_figure(data: dict[str, Any]):
    """Return per evaluation episode (eval runs) played out, coloured by how it ended, with the score (the mean of
    store/scores.py, with its interval); a forfeited episode is a marker, not a bar, and a set with one has no
    score, so no mean is drawn and the title says so."""
    episodes = [e for e in data["episodes"] if e["kind"] == "eval"]
    if not episodes:
        return None
    fig, (ax,) = _figure()
    xs = list(range(len(episodes)))
    score = score_episodes(episodes)
    played = [(x, e) for x, e in zip(xs, episodes) if not is_forfeit(e["end_reason"])]
    bars = ax.bar([x for x, _ in played], [e["return"] for _, e in played],
                  color=[END_COLOURS.get(e["end_reason"], "#1f77b4") for _, e in played], width=0.7, zorder=2)
    if len(xs) <= 30:
        ax.bar_label(bars, fmt="%g", padding=2, fontsize=8)
    forfeits = [x for x, e in zip(xs, episodes) if is_forfeit(e["end_reason"])]
    if forfeits:
        _forfeit_marks(ax, forfeits, f"forfeited: ended by the policy\n(no return counted), {len(forfeits)} of "
                                     f"{len(episodes)}")
    if score.ranked is not None:
        ax.axhline(score.ranked, color="#ff7f0e", linestyle="--", linewidth=1.5,
                   label=plot_text(f"score: mean {score.interval.text()}"))
    ax.axhline(0, color="black", linewidth=0.8)
    from matplotlib.patches import Patch

    seen = dict.fromkeys(e["end_reason"] for _, e in played)
    handles = [Patch(color=END_COLOURS.get(r, "#1f77b4"), label=plot_text(f"ended: {r}")) for r in seen]
    # beside the axes, never over a bar
    ax.legend(handles=ax.get_legend_handles_labels()[0] + handles, fontsize=8, loc="upper left",
              bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.set_xticks(xs, [f"{e['episode_index']}\nseed {e['seed']}" for e in episodes] if len(xs) <= 12 else None)
    _integer_x(ax, xs)
    caps = sorted({e["max_steps"] for e in episodes if e.get("max_steps")})
    ax.set_xlabel("evaluation episode" + (f" (cut off after {caps[0]:,} steps)" if len(caps) == 1 else ""))
    ax.set_ylabel("return (sum of rewards)")
    no_score = f" · no score: {len(forfeits)} of {len(episodes)} forfeited" if score.forfeits else ""
    _set_title(ax, data, "return per episode" + no_score)
    return fig


def code_figure(data: dict[str, Any]):
    """Lines of code and complexity of the version each iteration evaluated."""
    code = [r for r in data["code"] if r["loc"] is not None]
    if not code:
        return None
    fig, (top, bottom) = _figure(rows=2, height=6.2)
    xs = [r["iteration"] for r in code]
    for key, label, style in (("loc", "all lines of the file", "o-"), ("sloc", "source lines", "s-"),
                              ("trainable_sloc", "source lines, trainable methods", "^-")):
        top.plot(xs, [r[key] for r in code], style, markersize=4, linewidth=1.5, label=label)
    top.set_ylabel("lines of code")
    _set_title(top, data, "code size and complexity of the evaluated version")
    for key, label, style in (("complexity", "cyclomatic complexity, Policy class", "o-"),
                              ("trainable_complexity", "cyclomatic complexity, trainable methods", "^-"),
                              ("max_if_depth", "max nested-if depth", "s--")):
        bottom.plot(xs, [r[key] for r in code], style, markersize=4, linewidth=1.5, label=label)
    bottom.set_ylabel("complexity / depth")
    for ax in (top, bottom):
        ax.set_ylim(0, max(max(line.get_ydata()) for line in ax.get_lines()) * 1.3 + 1)
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    bottom.set_xlabel("iteration")
    _integer_x(bottom, xs)
    return fig


def tokens_figure(data: dict[str, Any]):
    """Input and output tokens of the LLM calls of each iteration, and their running total."""
    curve = data["curve"]
    if not curve or not any(r["total_tokens"] for r in curve):
        return None
    fig, (ax,) = _figure()
    xs = [r["iteration"] for r in curve]
    inputs = [r["input_tokens"] for r in curve]
    ax.bar(xs, inputs, width=0.7, color="#1f77b4", label="input (prompt) tokens", zorder=2)
    ax.bar(xs, [r["output_tokens"] for r in curve], bottom=inputs, width=0.7, color="#ff7f0e",
           label="output (reply) tokens", zorder=2)
    ax.set_ylabel("tokens in the iteration")
    ax.set_ylim(0, max(r["total_tokens"] for r in curve) * 1.3)
    ax.set_xlabel("iteration")
    _integer_x(ax, xs)
    right = ax.twinx()
    right.plot(xs, [r["cumulative_tokens"] for r in curve], "k.-", linewidth=1.2, label="cumulative (right axis)")
    right.set_ylabel("cumulative tokens")
    right.set_ylim(0, max(r["cumulative_tokens"] for r in curve) * 1.3)
    right.spines[["top"]].set_visible(False)
    handles = ax.get_legend_handles_labels()[0] + right.get_legend_handles_labels()[0]
    # below the axes, never over a bar (the right axis's labels take the space beside them)
    _legend_below(fig, handles)
    _set_title(ax, data, "LLM tokens per iteration")
    return fig


CALL_OUTCOME_STYLE = {  # outcome -> (edge colour, edge line style, label); the fill is the model's colour
    "accepted": ("#2ca02c", "solid", "accepted"),
    "rejected": ("#d62728", "solid", "rejected"),
    "repaired": ("#d62728", "dashed", "rejected, then repaired (the next bar of its candidate)"),
    "unchanged": ("#999999", "solid", "no change"),
    "failed": ("#ff7f0e", "dotted", "call failed"),
}


def calls_figure(data: dict[str, Any]):
    """The run's LLM calls over time: each call a bar from its start to its reply, coloured by model and edged by
    what came of it (a repair turn hatched), on lanes so that calls in flight together stand apart; below, how
    many were in flight."""
    calls = [c for c in data.get("calls") or [] if c["started_at"] is not None]
    if not calls:
        return None
    from matplotlib.patches import Patch
    from matplotlib.ticker import MaxNLocator

    t0 = min(c["started_at"] for c in calls)
    spans = [((c["started_at"] - t0).total_seconds(), (c["ended_at"] - t0).total_seconds()) for c in calls]
    lanes: list[float] = []  # each lane's end: a call takes the first lane free when it starts
    placed = []
    for start, end in spans:
        lane = next((k for k, free_at in enumerate(lanes) if free_at <= start), len(lanes))
        if lane == len(lanes):
            lanes.append(end)
        else:
            lanes[lane] = end
        placed.append(lane)
    models = list(dict.fromkeys(c["request_model"] or "?" for c in calls))
    palette = ("#1f77b4", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#7f7f7f")
    colour = {m: palette[i % len(palette)] for i, m in enumerate(models)}
    fig, (ax, flight) = _figure(rows=2, height=5.4)
    for c, (start, end), lane in zip(calls, spans, placed):
        edge, style, _ = CALL_OUTCOME_STYLE.get(c["outcome"], ("#555555", "solid", c["outcome"]))
        ax.barh(lane, max(end - start, 1e-3), left=start, height=0.7, color=colour[c["request_model"] or "?"],
                edgecolor=edge, linewidth=1.8, linestyle=style, zorder=2)
        ax.text(start, lane, f" {c['iteration']}.{c['candidate'] or 0}" + ("r" if c["purpose"] == "repair" else ""),
                va="center", ha="left", fontsize=6.5, color="white", zorder=3, clip_on=True)
    ax.set_ylabel("call lane")
    ax.set_ylim(-0.6, len(lanes) - 0.4)
    ax.invert_yaxis()
    ax.yaxis.set_major_locator(MaxNLocator(integer=True, min_n_ticks=1))  # one lane: tick 0, not 0.15 steps
    edges = sorted({t for span in spans for t in span})
    in_flight = [sum(1 for start, end in spans if start <= t < end) for t in edges]
    flight.step(edges, in_flight, where="post", color="#333333", linewidth=1.4)
    flight.set_ylabel("calls in flight")
    flight.set_xlabel("seconds since the run's first call")
    flight.set_ylim(0, max(in_flight, default=1) + 0.5)
    flight.yaxis.set_major_locator(MaxNLocator(integer=True, min_n_ticks=1))  # a count of calls: no 1.5
    handles = [Patch(facecolor=colour[m], label=textwrap.fill(_middle_cut(plot_text(m), 120), 60)) for m in models]
    used = dict.fromkeys(c["outcome"] for c in calls)
    handles += [Patch(facecolor="white", edgecolor=CALL_OUTCOME_STYLE[o][0], linestyle=CALL_OUTCOME_STYLE[o][1],
                      linewidth=1.8, label=CALL_OUTCOME_STYLE[o][2]) for o in used if o in CALL_OUTCOME_STYLE]
    _legend_below(fig, handles)
    _set_title(ax, data, "LLM calls over time (label: iteration.candidate, r = repair turn)")
    return fig


# ------------------------------------------------------------------------------------------------ markdown

