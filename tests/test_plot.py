"""nasa plot on synthetic eval.csv files: figures, one panel per task, a table that matches the inputs."""

from __future__ import annotations

import errno
import json
import statistics
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

from nasa.plot import (
    PAPER_FINAL,
    SeedCurve,
    align,
    find_runs,
    plot,
    plot_curves,
    results_table,
    summarize,
    with_frames,
)
from shared.envs import PAPER_TASKS
from shared.runlog import TRAIN_FIELDS, CsvLog, eval_fields

TASKS = ("cartpole-balance", "cheetah-run")
ALGOS = ("nasa_td3", "td3_ae")
SEEDS = (0, 1, 2)
STEPS = [0, 10, 20, 30, 40]


def write_eval(folder: Path, steps: list[int], means: list[float]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    log = CsvLog(folder / "eval.csv", eval_fields(2))
    for step, mean in zip(steps, means, strict=True):
        log.append({"step": step, "mean": mean, "std": 1.0, "return_0": mean - 1, "return_1": mean + 1})


@pytest.fixture
def results(tmp_path: Path) -> tuple[Path, dict]:
    """2 tasks x 2 algos x 3 seeds; returns the folder and {(task, algo, seed): (steps, means)}."""
    rng = np.random.default_rng(0)
    root = tmp_path / "results"
    data = {}
    for task in TASKS:
        for algo in ALGOS:
            for seed in SEEDS:
                steps = list(STEPS)
                if (task, algo, seed) == ("cartpole-balance", "nasa_td3", 2):
                    steps = steps[:-1]  # a seed that stopped one evaluation early
                means = [round(float(x), 3) for x in rng.uniform(0, 1000, len(steps))]
                data[task, algo, seed] = (steps, means)
                if task == "cheetah-run":
                    # Named by config.json only, in a folder of another layout.
                    folder = root / "other" / f"{algo}-{seed}"
                    config = {"algo": algo, "seed": seed, "steps": 40,
                              "env": {"task": task, "action_repeat": 4}}
                    folder.mkdir(parents=True)
                    (folder / "config.json").write_text(json.dumps(config))
                else:
                    folder = root / task / algo / f"seed{seed}"
                write_eval(folder, steps, means)
    return root, data


def test_find_runs_reads_both_layouts(results: tuple[Path, dict]) -> None:
    root, data = results
    runs = find_runs(root)
    assert {(r.task, r.algo, r.seed) for r in runs} == set(data)
    for r in runs:
        steps, means = data[r.task, r.algo, r.seed]
        assert r.steps.tolist() == steps
        assert r.means.tolist() == means


def test_figure_has_one_panel_per_task(results: tuple[Path, dict]) -> None:
    root, data = results
    fig = plot_curves(find_runs(root))
    assert len(fig.axes) == len(TASKS)
    assert [ax.get_title() for ax in fig.axes] == list(TASKS)
    for ax, task in zip(fig.axes, TASKS, strict=True):
        assert len(ax.get_lines()) == len(ALGOS) + 1  # and the untrained policy's return
        labels = [t.get_text() for t in ax.get_legend().get_texts()]
        base = statistics.mean(data[task, a, s][1][0] for a in ALGOS for s in SEEDS)
        # cartpole's nasa_td3 seed 2 stopped one evaluation early: its series ends where it did
        series = [f"{a} (n=3, to step 30: all seeds' last)" if (task, a) == ("cartpole-balance", "nasa_td3")
                  else f"{a} (n=3)" for a in ALGOS]
        assert labels == [*series, f"untrained ({base:.0f})"]
        assert ax.get_lines()[-1].get_ydata()[0] == pytest.approx(base)
    assert "std over seeds" in fig.get_suptitle()


def test_unused_grid_cells_are_not_panels() -> None:
    # 4 tasks fill 4 cells of a 3 x 2 grid; the 2 empty cells must not count as panels.
    tasks = PAPER_TASKS[:4]
    runs = [SeedCurve(t, "nasa_td3", 0, np.array([0, 10]), np.array([1.0, 2.0]), Path("x")) for t in tasks]
    fig = plot_curves(runs)
    assert [ax.get_title() for ax in fig.axes] == list(tasks)


def test_curve_is_the_mean_on_common_steps(results: tuple[Path, dict]) -> None:
    root, data = results
    runs = [r for r in find_runs(root) if (r.task, r.algo) == ("cartpole-balance", "nasa_td3")]
    steps, values = align(sorted(runs, key=lambda r: r.seed))
    assert steps.tolist() == STEPS[:-1]  # seed 2 has no step 40
    fig = plot_curves(runs)
    x, y = fig.axes[0].get_lines()[0].get_data()
    means = [data["cartpole-balance", "nasa_td3", s][1] for s in SEEDS]
    expected = [statistics.mean(m[i] for m in means) for i in range(4)]
    assert list(x) == STEPS[:-1]
    assert list(y) == pytest.approx(expected)


def test_table_matches_inputs(results: tuple[Path, dict]) -> None:
    root, data = results
    summaries = {(s.task, s.algo): s for s in summarize(find_runs(root))}
    assert set(summaries) == {(t, a) for t in TASKS for a in ALGOS}
    for (task, algo), s in summaries.items():
        finals = [data[task, algo, seed][1][-1] for seed in SEEDS]
        bests = [max(data[task, algo, seed][1]) for seed in SEEDS]
        assert s.seeds == 3
        assert s.final_mean == pytest.approx(statistics.mean(finals))
        assert s.final_std == pytest.approx(statistics.pstdev(finals))
        assert s.best_mean == pytest.approx(statistics.mean(bests))
    assert summaries["cartpole-balance", "nasa_td3"].last_steps == (30, 40)
    assert summaries["cheetah-run", "td3_ae"].last_steps == (40, 40)


def test_plot_command_writes_figures_and_table(
    results: tuple[Path, dict], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root, data = results
    out = tmp_path / "report"
    plot([str(root), "--out", str(out)])
    png, svg = (out / "curves.png").read_bytes(), (out / "curves.svg").read_text()
    assert png.startswith(b"\x89PNG") and len(png) > 10_000
    assert "<svg" in svg and len(svg) > 10_000
    table = (out / "results.md").read_text()
    assert table.count("| cartpole-balance |") == 2 and table.count("| cheetah-run |") == 2
    printed = capsys.readouterr().out
    rows = {}
    for line in table.splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if cells[0] in TASKS:
            rows[cells[0], cells[1]] = cells
            assert line in printed  # the same table is printed
    assert set(rows) == {(t, a) for t in TASKS for a in ALGOS}  # each row read, or none is checked below
    paper = {"cartpole-balance": {"nasa_td3": "~950", "td3_ae": "~950"},
             "cheetah-run": {"nasa_td3": "~570", "td3_ae": "~360"}}
    for (task, algo), (_, _, seeds, repeat, last, frame, final, best, paper_cell) in rows.items():
        finals = [data[task, algo, s][1][-1] for s in SEEDS]
        bests = [max(data[task, algo, s][1]) for s in SEEDS]
        assert seeds == "3"
        assert last == ("30-40" if (task, algo) == ("cartpole-balance", "nasa_td3") else "40")
        # cartpole's runs have no config.json: their action repeat, so their frames, are not known
        assert (repeat, frame) == (("?", "?") if task == "cartpole-balance" else ("4", "160"))
        assert final == f"{statistics.mean(finals):.1f} ± {statistics.pstdev(finals):.1f}"
        assert best == f"{statistics.mean(bests):.1f}"
        assert paper_cell == paper[task][algo]


def test_paper_figures_cover_the_paper_tasks() -> None:
    assert set(PAPER_FINAL) == set(PAPER_TASKS)
    for by_algo in PAPER_FINAL.values():
        assert set(by_algo) == {"nasa_td3", "sac_ae", "td3_ae"}
    assert PAPER_FINAL["reacher-hard"] == {"nasa_td3": 600, "sac_ae": 80, "td3_ae": 80}


def test_no_runs_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        plot([str(tmp_path)])
    assert exc.value.code == 2
    assert "no run with an evaluation" in capsys.readouterr().err


def test_a_distributed_run_is_its_own_curve_and_minutes_come_from_train_csv(tmp_path: Path) -> None:
    """nasa train and nasa up on the same task, algo and seed: two curves, and on the wall-clock axis
    each step sits at the minute its run reached it."""
    root = tmp_path / "runs"
    for runner, minutes in (("train", 1.0), ("up", 2.0)):
        folder = root / runner / "cartpole-balance" / "nasa_td3" / "seed0"
        write_eval(folder, [0, 10, 20], [5.0, 50.0, 500.0])
        log = CsvLog(folder / "train.csv", TRAIN_FIELDS)
        for step in (10, 20):
            log.append({"step": step, "wall_s": 60.0 * minutes * step / 10})
        if runner == "up":
            (folder / "learner").mkdir()  # what the distributed system's learner leaves
    runs = find_runs(root, walls=True)
    assert sorted(r.series for r in runs) == ["nasa_td3", "nasa_td3, nasa up"]
    fig = plot_curves(runs, x="minutes")
    (ax,) = fig.axes
    lines = {line.get_label(): line for line in ax.get_lines()}
    assert lines["nasa_td3 (n=1)"].get_xdata().tolist() == [0.0, 1.0, 2.0]
    assert lines["nasa_td3, nasa up (n=1)"].get_xdata().tolist() == [0.0, 2.0, 4.0]
    assert lines["untrained (5)"].get_ydata()[0] == 5.0
    assert ax.get_xlabel() == "wall-clock minutes"


BAD_TASK = '{"env": {"task": 5}, "algo": "td3", "seed": 1}'
BAD_SEED = '{"env": {"task": "cheetah-run"}, "algo": "td3", "seed": "x"}'
INF_SEED = '{"env": {"task": "cheetah-run"}, "algo": "td3", "seed": 1e400}'


@pytest.mark.parametrize(
    ("spoil", "reason"),
    [
        (lambda f: (f / "eval.csv").write_bytes(b"step,mean\n0,\xff\xfe\n"), "UnicodeDecodeError"),
        (lambda f: (f / "eval.csv").write_text("step,mean\n0,1.0\n10,abc\n"), "ValueError"),
        (lambda f: (f / "eval.csv").write_text("step,mean\n0,1.0\ninf,2.0\n"), "not a finite number"),
        (lambda f: (f / "eval.csv").write_text("step,mean\n0,1.0\n10,inf\n"), "not a finite number"),
        (lambda f: (f / "eval.csv").write_text("step,mean\n0,nan\n10,1.0\n"), "not a finite number"),
        (lambda f: (f / "eval.csv").write_text("step,mean\n0,1.0\n1e20,1.0\n"), "a step out of range"),
        # eval.csv is written in step order: one out of it (merged or edited by hand) was drawn with
        # values interpolated along the file's order, not the evaluations it holds.
        (lambda f: (f / "eval.csv").write_text("step,mean\n0,0.0\n20,500.0\n10,7.0\n30,30.0\n"),
         "steps not in increasing order"),
        (lambda f: (f / "eval.csv").write_text("step,mean\n0,0.0\n10,7.0\n10,500.0\n"),
         "steps not in increasing order"),
        # A field past the csv module's length limit (an unclosed quote, a binary blob).
        (lambda f: (f / "eval.csv").write_text('step,mean\n0,1.0\n"' + "x" * 200_000 + "\n"),
         "not a CSV file this version can read"),
        (lambda f: (f / "config.json").write_text("{not json"), "config.json is unreadable: Expecting"),
        (lambda f: (f / "config.json").write_text("[1, 2]"), "config.json is unreadable: it does not hold"),
        (lambda f: (f / "config.json").write_text(BAD_SEED), "ValueError"),
        (lambda f: (f / "config.json").write_text(INF_SEED), "OverflowError"),
        (lambda f: (f / "config.json").write_text(BAD_TASK), "env.task and algo must be names, got 5"),
    ],
)
def test_a_damaged_run_is_named_and_skipped_and_the_others_still_plot(
    results: tuple[Path, dict], capsys: pytest.CaptureFixture[str], spoil, reason: str
) -> None:
    root, data = results
    damaged = root / "other" / "nasa_td3-1"  # a cheetah-run run named by its config.json
    spoil(damaged)
    runs = find_runs(root)
    assert {(r.task, r.algo, r.seed) for r in runs} == set(data) - {("cheetah-run", "nasa_td3", 1)}
    err = capsys.readouterr().err
    assert f"nasa plot: skipping {damaged / 'eval.csv'}: " in err and reason in err


def test_a_last_row_cut_short_is_left_out(tmp_path: Path) -> None:
    folder = tmp_path / "runs" / "cartpole-balance" / "nasa_td3" / "seed0"
    write_eval(folder, [0, 10], [5.0, 500.0])
    with open(folder / "eval.csv", "a") as f:
        f.write("20,61")  # the row of 20 cut short: its return may be 612.5
    (run,) = find_runs(tmp_path / "runs")
    assert run.steps.tolist() == [0, 10] and run.means.tolist() == [5.0, 500.0]


def test_an_out_folder_that_cannot_be_written_is_a_clear_error(
    results: tuple[Path, dict], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root, _ = results
    (tmp_path / "a-file").write_text("")
    with pytest.raises(SystemExit) as exc:
        plot([str(root), "--out", str(tmp_path / "a-file" / "plots")])
    assert exc.value.code == 2
    assert f"nasa plot: error: cannot write to {tmp_path / 'a-file' / 'plots'}" in capsys.readouterr().err


def test_a_full_disk_leaves_the_last_plots_files_as_they_were(
    results: tuple[Path, dict], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str]
) -> None:
    root, _ = results
    out = tmp_path / "plots"
    plot([str(root), "--out", str(out)])
    names = ("curves.png", "curves.svg", "results.md")
    before = {name: (out / name).read_bytes() for name in names}
    save = Figure.savefig

    def full_disk(self: Figure, path: Path, **kwargs: object) -> None:
        if kwargs.get("format") == "png" or str(path).endswith(".png"):
            return save(self, path, **kwargs)
        with open(path, "wb") as f:  # the disk fills in the middle of the SVG
            f.write(b"<svg")
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(Figure, "savefig", full_disk)
    write_eval(root / "walker-walk" / "nasa_td3" / "seed0", [0, 10], [1.0, 2.0])  # a new run to plot
    with pytest.raises(SystemExit) as exc:
        plot([str(root), "--out", str(out)])
    assert exc.value.code == 2 and "No space left on device" in capsys.readouterr().err
    assert {name: (out / name).read_bytes() for name in names} == before
    assert sorted(p.name for p in out.iterdir()) == sorted(names)  # nothing half-written left


def test_seeds_that_share_one_step_still_show(tmp_path: Path) -> None:
    root = tmp_path / "runs"
    write_eval(root / "cartpole-balance" / "nasa_td3" / "seed0", [0, 10, 20], [5.0, 50.0, 500.0])
    write_eval(root / "cartpole-balance" / "nasa_td3" / "seed1", [0], [7.0])  # just started
    (ax,) = plot_curves(find_runs(root)).axes
    (line,) = [line for line in ax.get_lines() if line.get_label().startswith("nasa_td3")]
    assert line.get_marker() == "o" and line.get_xdata().tolist() == [0]
    assert "to step 0" in line.get_label()


def test_a_damaged_train_csv_hides_only_the_wall_clock_axis(
    results: tuple[Path, dict], capsys: pytest.CaptureFixture[str]
) -> None:
    root, data = results
    damaged = root / "other" / "nasa_td3-1"
    (damaged / "train.csv").write_text("step,wall_s\nten,1.0\n")
    assert {(r.task, r.algo, r.seed) for r in find_runs(root)} == set(data)  # steps need no train.csv
    plot([str(root)])
    assert "nasa plot: 12 runs" in capsys.readouterr().out
    runs = find_runs(root, walls=True)
    assert {(r.task, r.algo, r.seed) for r in runs} == set(data) - {("cheetah-run", "nasa_td3", 1)}
    assert f"nasa plot: skipping {damaged / 'eval.csv'}: unreadable (ValueError" in capsys.readouterr().err


def write_run(folder: Path, task: str, seed: int, repeat: int, steps: list[int], means: list[float],
              algo: str = "nasa_td3") -> None:
    """A run named by its config.json, with its action repeat."""
    write_eval(folder, steps, means)
    config = {"algo": algo, "seed": seed, "env": {"task": task, "action_repeat": repeat}}
    (folder / "config.json").write_text(json.dumps(config))


def test_runs_of_different_action_repeats_are_separate_series_and_meet_on_frames(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An env step of action repeat 8 is 8 frames: such a run is not averaged with one of action
    repeat 1, and on the frames axis (the paper's and SAC-AE's) its steps sit at 8x."""
    root = tmp_path / "runs"
    write_run(root / "a", "cheetah-run", 0, 1, [0, 800, 1600], [1.0, 100.0, 200.0])
    write_run(root / "b", "cheetah-run", 1, 8, [0, 100, 200], [2.0, 150.0, 300.0])
    write_eval(root / "cheetah-run" / "nasa_td3" / "seed2", [0, 100], [3.0, 4.0])  # no config.json
    runs = find_runs(root)
    (ax,) = plot_curves(runs, x="steps").axes
    assert ax.get_xlabel().startswith("env steps (action repeat differs")
    (ax,) = plot_curves(with_frames(runs), x="frames").axes
    lines = {line.get_label(): line for line in ax.get_lines()}
    assert lines["nasa_td3, action repeat 1 (n=1)"].get_xdata().tolist() == [0, 800, 1600]
    assert lines["nasa_td3, action repeat 8 (n=1)"].get_xdata().tolist() == [0, 800, 1600]
    assert ax.get_xlabel() == "frames (env steps x action repeat)"
    assert "skipping" in capsys.readouterr().err  # the run of unknown action repeat, named
    out = tmp_path / "out"
    plot([str(root), "--x", "frames", "--out", str(out)])
    table = (out / "results.md").read_text()
    assert "| cheetah-run | nasa_td3, action repeat 8 | 1 | 8 | 200 | 1600 |" in table
    assert "| cheetah-run | nasa_td3, action repeat 1 | 1 | 1 | 1600 | 1600 |" in table
    assert "nasa_td3, action repeat ?" not in table
    write_run(root / "c", "cheetah-run", 2, 2, [0, 800], [1.0, 2.0])
    write_run(root / "d", "cheetah-run", 3, 1, [0, 800], [1.0, 2.0], algo="td3_ae")
    (ax,) = plot_curves(with_frames(find_runs(root)), x="frames").axes
    # The paper's algorithm order, then the action repeat in numeric order.
    assert [ln.get_label().split(" (n")[0] for ln in ax.get_lines()] == [
        "nasa_td3, action repeat 1", "nasa_td3, action repeat 2", "nasa_td3, action repeat 8",
        "td3_ae, action repeat 1", "untrained (1)"]
    assert "1M frames" in table


def test_the_env_steps_axis_names_the_action_repeat(tmp_path: Path) -> None:
    write_run(tmp_path / "a", "cartpole-balance", 0, 8, [0, 10], [1.0, 2.0])
    (ax,) = plot_curves(find_runs(tmp_path), x="steps").axes
    assert ax.get_xlabel() == "env steps (action repeat 8: 8 frames each)"
    assert ax.get_lines()[0].get_label() == "nasa_td3 (n=1)"  # one action repeat: no split


def test_seeds_evaluated_at_different_steps_meet_on_a_common_grid(tmp_path: Path) -> None:
    """One seed's evaluator skipped steps the other evaluated: both are interpolated onto every
    step either evaluated, rather than kept only where both did."""
    root = tmp_path / "runs"
    write_eval(root / "cartpole-balance" / "nasa_td3" / "seed0", [0, 10, 20, 30], [0.0, 10.0, 20.0, 30.0])
    write_eval(root / "cartpole-balance" / "nasa_td3" / "seed1", [0, 15, 30, 40], [0.0, 30.0, 60.0, 70.0])
    runs = find_runs(root)
    steps, values = align(runs)
    assert steps.tolist() == [0, 10, 15, 20, 30]  # to the shorter seed's last
    assert values.tolist() == [[0.0, 10.0, 15.0, 20.0, 30.0], [0.0, 20.0, 30.0, 40.0, 60.0]]
    fig = plot_curves(runs)
    (line,) = [ln for ln in fig.axes[0].get_lines() if ln.get_label().startswith("nasa_td3")]
    assert line.get_ydata().tolist() == pytest.approx([0.0, 15.0, 22.5, 30.0, 45.0])
    assert "interpolated" in fig.get_suptitle()


def test_seeds_that_start_at_different_steps_are_aligned_not_interpolated(tmp_path: Path) -> None:
    """One seed has no step-0 evaluation: the curve starts at the step both have, and every point
    drawn is one both seeds were evaluated at, so the caption says no interpolation."""
    root = tmp_path / "runs"
    write_eval(root / "cartpole-balance" / "nasa_td3" / "seed0", [0, 10, 20], [0.0, 10.0, 20.0])
    write_eval(root / "cartpole-balance" / "nasa_td3" / "seed1", [10, 20], [30.0, 40.0])
    runs = find_runs(root)
    assert align(runs)[0].tolist() == [10, 20]
    fig = plot_curves(runs)
    assert "interpolated" not in fig.get_suptitle() and "aligned" in fig.get_suptitle()


def test_one_seed_shows_no_spread_over_seeds(tmp_path: Path) -> None:
    write_eval(tmp_path / "cartpole-balance" / "nasa_td3" / "seed0", [0, 10], [5.0, 500.0])
    table = results_table(summarize(find_runs(tmp_path)))
    assert "| 500.0 | 500.0 |" in table and "±" not in table


def test_seeds_at_different_steps_also_meet_on_the_wall_clock_axis(tmp_path: Path) -> None:
    root = tmp_path / "runs"
    for seed, steps in ((0, [0, 10, 20]), (1, [0, 20])):
        folder = root / "cartpole-balance" / "nasa_td3" / f"seed{seed}"
        write_eval(folder, steps, [float(s) for s in steps])
        log = CsvLog(folder / "train.csv", TRAIN_FIELDS)
        for step in (10, 20):
            log.append({"step": step, "wall_s": 6.0 * step})  # a minute a step of 10
    (ax,) = plot_curves(find_runs(root, walls=True), x="minutes").axes
    (line,) = [ln for ln in ax.get_lines() if ln.get_label().startswith("nasa_td3")]
    assert line.get_xdata().tolist() == pytest.approx([0.0, 1.0, 2.0])


@pytest.mark.parametrize("content", [b"", b"step,upd", b"step,updates,mean,std,min,max,return_0\r\n"])
def test_an_empty_or_header_only_eval_csv_is_a_run_not_evaluated_yet(tmp_path: Path, content: bytes) -> None:
    write_eval(tmp_path / "cartpole-balance" / "nasa_td3" / "seed0", [0, 10], [5.0, 500.0])
    empty = tmp_path / "cartpole-balance" / "nasa_td3" / "seed1"
    empty.mkdir(parents=True)
    (empty / "eval.csv").write_bytes(content)  # made, killed before or while writing its header
    assert [r.seed for r in find_runs(tmp_path)] == [0]
