"""What the report's and compare's pictures draw, checked on the figures' plotted data (and pixels for overlap):
a candidate never played is not drawn at its parent's score, legends sit beside the bars, where two runs'
curves coincide both stay visible, no title, label or legend runs past the image's edge however long the names
in it, and ``save_png`` (one layout, one draw) writes the pixels a draw through the figure's layout makes."""

from __future__ import annotations

import copy
import gzip
import io
import shutil

import numpy as np
import pytest

from pipeline.play.evaluate import EvalConfig, evaluate
from pipeline.llm.client import LiteLLMClient
from pipeline.optimizer.config import OptimizeConfig
from pipeline.optimizer.loop import optimize
from store import Store
from tests.conftest import COMPETENT_REPLY, EXAMPLES, ROOT, json_reply
from viewers import compare_report
from viewers.report import collect
from viewers.report_figures import episode_returns_figure, lineage_figure, tokens_figure, unplayed_reason
from viewers import report_figures

KEY_ERROR = json_reply({"select_action": "def select_action(self, predicted_ball_y, obs):\n    return obs['Nope']\n"})
# iteration 1 competent (played), 2 an unusable reply, 3 code that raises on recorded observations: 2 and 3 are
# rejected before any game, and the store gives them their parent's version and score
SCRIPT = [COMPETENT_REPLY, "Sorry, I cannot help with that.", KEY_ERROR]


@pytest.fixture(scope="module")
def pictured(tmp_path_factory):
    from tests.scripted_llm import ScriptedModel

    tmp = tmp_path_factory.mktemp("pictures")
    store = Store(tmp / "p.duckdb", lock_timeout_s=20)
    with ScriptedModel(SCRIPT, tmp / "model") as model:
        client = LiteLLMClient(model.model, api_base=model.api_base, backoff_s=0.05)
        result = optimize(OptimizeConfig(game="pong", iterations=3, rollout_steps=100, eval_max_steps=300,
                                         workers=2, token_budget=8000, rng_key="pictures"), store, client)
    assert result.status == "finished", result.error
    ev = evaluate(EXAMPLES / "pong.py", EvalConfig(episodes=3, max_steps=150, workers=2, rng_key="pictures"), store)
    return collect(store, result.run_id), collect(store, ev.run_id)


def _drawn(fig):
    """The figure drawn on an Agg canvas (as savefig draws it); the canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return canvas


def _points(ax) -> list[tuple[tuple[float, float], bool]]:
    """Every scatter point of an axes: ((x, y), filled)."""
    out = []
    for collection in ax.collections:
        filled = len(collection.get_facecolors()) > 0 and collection.get_facecolors()[0][3] > 0
        out += [((float(x), float(y)), filled) for x, y in collection.get_offsets()]
    return out


@pytest.mark.slow
def test_lineage_draws_a_candidate_never_played_apart_from_its_parents_score(pictured):
    data, _ = pictured
    nodes = {n["iteration"]: n for n in data["lineage"]}
    assert [unplayed_reason(nodes[i]) for i in (0, 1, 2, 3)] == [None, None, "rejected", "rejected"]
    assert nodes[2]["score"] == nodes[1]["score"], "the store gives a rejected candidate its parent's score"
    fig = lineage_figure(data)
    (ax,) = fig.axes
    points = _points(ax)
    for i in (2, 3):
        at_parent = (float(i), float(nodes[i]["score"]))
        assert at_parent not in [p for p, _ in points], f"iteration {i} drawn at its parent's score"
    lane = [p for p, filled in points if p[0] in (2.0, 3.0)]
    assert len(lane) == 2 and lane[0][1] == lane[1][1] < min(nodes[i]["score"] for i in (0, 1)), "on a lane below"
    assert not any(filled for p, filled in points if p[0] in (2.0, 3.0)), "hollow markers"
    played = sorted((p, filled) for p, filled in points if p[0] in (0.0, 1.0))
    assert played == [((0.0, float(nodes[0]["score"])), True), ((1.0, float(nodes[1]["score"])), True)]
    assert any(t.get_text() == "not played" for t in ax.texts)


def _overlaps(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


@pytest.mark.parametrize("which", ["tokens", "episode returns", "equal episode returns"])
def test_legends_never_cover_a_bar(pictured, which):
    data = pictured[0] if which == "tokens" else pictured[1]
    if which == "equal episode returns":  # bars of one height across the plot: no corner of it is free
        data = {**data, "episodes": [{**e, "return": 4.0} for e in data["episodes"]]}
    fig = tokens_figure(data) if which == "tokens" else episode_returns_figure(data)
    renderer = _drawn(fig).get_renderer()
    legends = [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None] + list(fig.legends)
    bars = [patch for ax in fig.axes for patch in ax.patches if patch.get_height() != 0]
    assert legends and bars
    for legend in legends:
        box = legend.get_window_extent(renderer)
        for bar in bars:
            assert not _overlaps(box, bar.get_window_extent(renderer)), f"the {which} legend covers a bar"


def _curves_data(shift_b: float = 0.0) -> dict:
    """Two runs whose curves coincide (``shift_b`` moves B's scores)."""
    curve = [{"iteration": i, "score": s, "best_score": b, "update_status": "accepted", "llm_calls": i,
              "tokens": 1500 * i, "elapsed_s": 20.0 * i}
             for i, (s, b) in enumerate([(-21, -21), (-15, -15), (-18, -15), (-9, -9), (-9, -9)])]
    moved = [{**p, "score": p["score"] + shift_b, "best_score": p["best_score"] + shift_b} for p in curve]
    runs = [{"label": label, "run_id": run_id, "model": "openai/scripted"}
            for label, run_id in (("A", "01JDX3K2AB7Q000000000000A1"), ("B", "01JDX3K2AC1M000000000000B2"))]
    return {"mode": "runs", "game": "pong", "runs": runs, "curves": {"A": curve, "B": moved}}


def _pixels_of(fig, colour: str) -> int:
    """Pixels inside the axes close to ``colour`` (in hue: either run's colour, drawn lighter or darker)."""
    for ax in fig.axes:
        if ax.get_legend() is not None:
            ax.get_legend().remove()
    image = np.asarray(_drawn(fig).buffer_rgba())[..., :3].astype(float) / 255
    target = np.array([int(colour[i:i + 2], 16) / 255 for i in (1, 3, 5)])
    direction = (target - target.mean()) / np.linalg.norm(target - target.mean())
    chroma = image - image.mean(axis=-1, keepdims=True)
    strength = np.linalg.norm(chroma, axis=-1)
    along = (chroma @ direction) / np.maximum(strength, 1e-9)
    return int(((strength > 0.08) & (along > 0.97)).sum())


def test_compare_curves_that_coincide_both_show(tmp_path):
    apart = compare_report.curves_figure(_curves_data(shift_b=4.0))
    same = compare_report.curves_figure(_curves_data())
    a_apart, a_same = _pixels_of(apart, compare_report.COLOURS["A"]), _pixels_of(same, compare_report.COLOURS["A"])
    b_apart, b_same = _pixels_of(apart, compare_report.COLOURS["B"]), _pixels_of(same, compare_report.COLOURS["B"])
    assert a_apart > 1000 and b_apart > 1000
    assert a_same > 0.4 * a_apart, f"A's curve is hidden where it meets B's ({a_same} of {a_apart} pixels show)"
    assert b_same > 0.4 * b_apart, f"B's curve is hidden where it meets A's ({b_same} of {b_apart} pixels show)"
    compare_report.curves_figure(_curves_data()).savefig(tmp_path / "curves.png")
    assert (tmp_path / "curves.png").stat().st_size > 20_000


LONG_MODEL = "openrouter/meta-llama/llama-3.1-405b-instruct-turbo"
REPORT_FIGURES = ("scores_figure", "code_figure", "tokens_figure", "lineage_figure", "calls_figure")


@pytest.fixture(scope="module")
def greedy(tmp_path_factory) -> dict:
    """The report's data of tests/fixtures/greedy_run.duckdb.gz (five iterations of Pong, every figure drawn)."""
    path = tmp_path_factory.mktemp("greedy") / "greedy.duckdb"
    with gzip.open(ROOT / "tests" / "fixtures" / "greedy_run.duckdb.gz") as packed, open(path, "wb") as out:
        shutil.copyfileobj(packed, out)
    store = Store(path)
    return collect(store, store.query("SELECT run_id FROM runs")[0][0])


def _long_named(data: dict) -> dict:
    """``data`` with a long run name, a long model name, and its calls spread over three long model names."""
    data = copy.deepcopy(data)
    data["run"].update(name="a run whose name says at length what it tried " * 2, model=LONG_MODEL)
    for i, call in enumerate(data["calls"]):
        call["request_model"] = f"{LONG_MODEL}-with-a-suffix-{i % 3}"
    return data


def _as_eval_run(data: dict) -> dict:
    """``data`` as an eval run's (episode_returns_figure): its evaluation episodes, ended every way one ends."""
    data = copy.deepcopy(data)
    data["run"]["kind"] = "eval"
    data["episodes"] = [e for e in data["episodes"] if e["kind"] == "eval"]
    reasons = ("terminated", "truncated", "policy_error", "timeout", "crashed", "tampered")
    for i, episode in enumerate(data["episodes"]):
        episode.update(episode_index=i, end_reason=reasons[i % len(reasons)])
    return data


def _figure_of(which: str, data: dict, model: str):
    """Figure ``which`` (a report figure, ``episode_returns_figure``, or ``compare``: two runs of ``model``)."""
    if which == "compare":
        curves = _curves_data()
        curves["runs"] = [{**run, "model": f"{model}-{run['label']}"} for run in curves["runs"]]
        return compare_report.curves_figure(curves)
    if which == "episode_returns_figure":
        return report_figures.episode_returns_figure(_as_eval_run(data))
    return getattr(report_figures, which)(data)


def _assert_inside(fig, which: str) -> None:
    inside = fig.bbox_inches
    drawn = fig.get_tightbbox(_drawn(fig).get_renderer())  # every artist drawn, in inches
    assert drawn.x0 >= inside.x0 and drawn.y0 >= inside.y0 and drawn.x1 <= inside.x1 and drawn.y1 <= inside.y1, \
        f"{which}: drawn over {drawn.bounds}, the image is {inside.bounds} (inches)"


ALL_FIGURES = REPORT_FIGURES + ("episode_returns_figure", "compare")


@pytest.mark.parametrize("which", ALL_FIGURES)
def test_no_title_label_or_legend_runs_past_the_image(greedy, which):
    _assert_inside(_figure_of(which, _long_named(greedy), LONG_MODEL), which)


HOSTILE_NAMES = {  # legal names (a run's name, a model id) that matplotlib's wrap, at spaces only, cannot fit
    "no space": ("abcdefghijklmnopqrstuvwxyz0123456789-_" * 8)[:300],
    "wide letters": "W" * 300,
    "CJK": "强化学习策略优化实验" * 12,
    "newlines and tabs": "first line\nsecond\tline\r\n" * 6 + "x" * 120,
}


def _hostile_named(data: dict, name: str) -> dict:
    """``data`` whose run and model are named ``name``, its calls spread over eight long model ids ending so."""
    data = copy.deepcopy(data)
    data["run"].update(name=name, model=name)
    calls = data["calls"]
    calls += [copy.deepcopy(calls[i % len(calls)]) for i in range(8 - len(calls))]
    for i, call in enumerate(calls):
        call["request_model"] = f"{LONG_MODEL}-{name}-{i}"
    return data


@pytest.mark.parametrize("which", ALL_FIGURES)
@pytest.mark.parametrize("name", list(HOSTILE_NAMES))
def test_no_text_runs_past_the_image_whatever_the_names(greedy, which, name):
    """A name of 300 characters without a space ran about an inch past the image's edge (matplotlib wraps at
    spaces only), one of wide letters or CJK characters several inches; its title, cut to five lines, and the
    legend's eight models, cut in the middle, leave the axes their height."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the fonts here have no CJK glyph: drawn as boxes, of a glyph's width
        _assert_inside(_figure_of(which, _hostile_named(greedy, HOSTILE_NAMES[name]), HOSTILE_NAMES[name]), which)


def test_a_hostile_name_is_broken_between_its_characters_and_an_ordinary_title_left_as_it_was(greedy):
    fig = report_figures.scores_figure(_hostile_named(greedy, HOSTILE_NAMES["no space"]))
    _drawn(fig)
    lines = fig.axes[0].title.get_text().split("\n")
    assert lines[-1].endswith("…") and len(lines) == report_figures.TITLE_LINES, lines
    assert any(line.startswith("'abcdefghij") for line in lines), "the name starts a line of its own"
    ordinary = report_figures.scores_figure(_long_named(greedy))
    written = ordinary.axes[0].title.get_text()
    _drawn(ordinary)
    assert ordinary.axes[0].title.get_text() == written, "an ordinary title is left to matplotlib's wrap"


def test_save_png_writes_what_a_draw_through_the_layout_makes(greedy):
    from PIL import Image

    for which in ("scores_figure", "calls_figure"):  # a legend beside the axes; one below two axes
        drawn = np.asarray(_drawn(getattr(report_figures, which)(greedy)).buffer_rgba())
        saved = io.BytesIO()
        report_figures.save_png(getattr(report_figures, which)(greedy), saved)
        written = np.asarray(Image.open(io.BytesIO(saved.getvalue())).convert("RGBA"))
        assert written.shape == drawn.shape and np.array_equal(written, drawn), f"{which} saved differs"


def test_the_lineage_shows_the_best_above_a_candidate_of_its_score(greedy):
    """Best-of-n: iteration 1's best and a discarded candidate of the same iteration both scored 0; the best's star
    was drawn under the discarded grey dot (seen in a best-of-n run of 8 iterations of 4 candidates)."""
    data = copy.deepcopy(greedy)
    best = next(n for n in data["lineage"] if n["iteration"] == 1 and n["decision"] == "best")
    data["lineage"].append({**best, "candidate": 1, "decision": "discarded"})
    fig = lineage_figure(data)
    canvas = _drawn(fig)
    x, y = fig.axes[0].transData.transform((best["iteration"], best["score"]))
    image = np.asarray(canvas.buffer_rgba())
    centre = image[int(round(image.shape[0] - y)), int(round(x)), :3].astype(int)
    assert np.abs(centre - (0xFF, 0x7F, 0x0E)).max() < 40, f"the best's point is drawn {centre}, not the star's orange"
