"""README.md quotes what bench/readme_figures.py regenerates (issue 27, item 9: the README's replay
figures were stale, 0.60 % / 0.043 m against the command's 0.52 % / 0.061 m). The cheapest
figure is checked: the kitti-seq1 replay and its evaluation (51 frames)."""

from __future__ import annotations

from types import ModuleType

from tests.support.paths import REPO, load_bench


def _bench() -> ModuleType:
    return load_bench("readme_figures")


def test_the_readme_quotes_the_replay_figures_the_script_produces(shared_data) -> None:
    bench = _bench()
    fig = bench.replay_figure(shared_data("kitti-seq1").parent)
    assert fig["consistent"], fig  # the replay's own summary and `robotd eval` agree
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    assert bench.missing_quotes(readme, fig) == [], (fig["quotes"], "run: python bench/readme_figures.py")


def test_a_stale_figure_is_found() -> None:
    bench = _bench()
    fig = {"quotes": ["# drift 0.52 %, ATE 0.061 m", "gives ATE 0.079 m"]}
    readme = "robotd eval T.txt poses.txt --json     # drift 0.60 %,\n   ATE 0.043 m\nit gives ATE\n0.079 m (8.2 m)"
    assert bench.missing_quotes(readme, fig) == ["# drift 0.52 %, ATE 0.061 m"]
