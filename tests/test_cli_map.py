import os
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from sklearn.metrics import roc_auc_score

from skoccmap import MixtureGPOccupancyMap, OccupancyGrid
from skoccmap._cmd_map import log_stem
from skoccmap.cli import main
from skoccmap.datasets import load_carmen


def test_map_writes_a_usable_map(paper_log, tmp_path, capsys):
    log, data = paper_log
    out = tmp_path / "out"
    rc = main(["map", str(log), "--resolution", "0.5", "--out", str(out), "--quiet"])
    assert rc == 0
    stdout = capsys.readouterr().out
    assert "| fit mixture |" in stdout and "| total |" in stdout
    for suffix in (".pgm", ".yaml", ".npz", ".png"):
        assert (out / f"paper{suffix}").is_file()
    grid = OccupancyGrid.load(out / "paper.npz")
    assert grid.resolution == 0.5 and grid.variance is not None
    # The map matches the simulator's walls on the cells the scans observed.
    truth = data.environment.ground_truth_grid(0.5, extent=grid.extent, scans=data.scans)
    assert tuple(truth.shape) == grid.shape
    observed = truth.observed
    auc = roc_auc_score(truth.occupied[observed], grid.probability.ravel()[observed])
    assert auc > 0.85
    reloaded = OccupancyGrid.load_map_server(out / "paper.yaml")
    np.testing.assert_array_equal(reloaded.trinary(), grid.trinary())
    # Cells no training beam reached are unknown (the training scans are the log's scans).
    assert np.all(grid.unknown.ravel()[~observed])


def test_map_every_nth_scan(paper_log, tmp_path, capsys):
    log, _ = paper_log
    rc = main(["map", str(log), "--every-nth-scan", "3", "--resolution", "1.0",
               "--out", str(tmp_path), "--quiet"])  # fmt: skip
    assert rc == 0
    assert "training on 9 scans" in capsys.readouterr().out


def test_evaluate_prints_every_model(paper_log, capsys):
    log, _ = paper_log
    rc = main(["evaluate", str(log), "--holdout-every", "4", "--every-nth-scan", "2", "--quiet"])
    assert rc == 0
    out = capsys.readouterr().out
    names = ["mixture of GP experts", "frequency grid (0.1 m)", "log-odds grid per scan (0.1 m)"]
    pattern = rf"^\| ({'|'.join(map(re.escape, names))}) \| ([0-9.]+)"
    aucs = dict(re.findall(pattern, out, flags=re.M))
    assert set(aucs) == set(names)
    assert all(0.5 < float(v) <= 1.0 for v in aucs.values())


@pytest.mark.parametrize(
    "argv, message",
    [
        (["map", "{log}", "--every-nth-scan", "0"], "--every-nth-scan must be >= 1"),
        (["map", "{log}", "--resolution", "-1"], "--resolution must be a positive finite length"),
        (["map", "{log}", "--resolution", "inf"], "--resolution must be a positive finite length"),
        (["map", "{log}", "--unknown-variance", "big"], "--unknown-variance"),
        (["map", "{log}", "--unknown-variance", "0"], "--unknown-variance must be positive"),
        (["map", "{missing}"], "No such file"),
        # Not "--pose-topic applies only to ROS bags; ... is a CARMEN log".
        (["map", "{missing}", "--pose-topic", "/odom"], "No such file"),
        (["demo", "--out", "{log}", "--quick"], "--out {log} exists and is not a folder"),
        (["evaluate", "{log}", "--holdout-every", "1"], "--holdout-every must be >= 2"),
        # Before the log is read (they used to surface after it, in the estimator's words).
        (["map", "{log}", "--max-expert-size", "0"], "--max-expert-size must be >= 2"),
        (["evaluate", "{log}", "--n-jobs", "0"], "--n-jobs must not be 0"),
        (["map", "{log}", "--seed", "-1"], "--seed must be an integer in [0, 2**32), got -1"),
        (["map", "{log}", "--level-tolerance", "nan"], "--level-tolerance must be >= 0 radians"),
        # Options of the online replay were ignored without --online.
        (["map", "{log}", "--snapshots", "{tmp}/s"], "--snapshots applies only with --online"),
        (
            ["map", "{log}", "--batch-scans", "3", "--refit-fraction", "0"],
            "--batch-scans, --refit-fraction apply only with --online",
        ),
        # A reader's options given to the other reader were ignored.
        (["map", "{log}", "--scan-topic", "/front"], "--scan-topic applies only to ROS bags"),
        # Even at the bag reader's default value (it was ignored without a word).
        (["map", "{log}", "--scan-topic", "/scan"], "--scan-topic applies only to ROS bags"),
        (
            ["map", "{log}", "--map-frame", "map", "--level-tolerance", "0.01"],
            "--map-frame, --level-tolerance apply only to ROS bags",
        ),
        (
            ["evaluate", "{log}", "--map-frame", "odom", "--laser-frame", "laser"],
            "--map-frame, --laser-frame apply only to ROS bags;",
        ),
        # A folder that is not a bag used to say "Is a directory".
        (["map", "{tmp}"], "is a folder but not a ROS 2 bag"),
        # The output folder is checked before the fit, not after it.
        (["map", "{log}", "--out", "{log}"], "exists and is not a folder"),
    ],
)
def test_bad_options_exit_with_a_message(paper_log, tmp_path, capsys, argv, message):
    log, _ = paper_log
    names = dict(log=log, missing=tmp_path / "missing.log", tmp=tmp_path)
    argv = [a.format(**names) for a in argv]
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert message.format(**names) in err
    assert "fitted" not in out and "training on" not in out


def test_a_log_without_returns_says_so(tmp_path, capsys):
    # It used to end in scikit-learn's "Only binary classification is supported".
    log = tmp_path / "nohits.log"
    lines = [f"FLASER 3 8.0 8.0 8.0 {t} 0 0 {t} 0 0 {t}.0 h {t}.0\n" for t in range(3)]
    log.write_text("".join(lines))
    out = tmp_path / "o"
    assert main(["map", str(log), "--max-range", "8", "--quiet", "--out", str(out)]) == 2
    assert "0 beam(s) of the 3 training scans return a hit (the others" in capsys.readouterr().err
    assert not out.exists()
    # Zeros (no measurement) are no hit either, and the message counts them.
    log.write_text("".join(line.replace(" 8.0 8.0 ", " 0.0 8.0 ", 1) for line in lines))
    assert main(["map", str(log), "--max-range", "8", "--quiet", "--out", str(out)]) == 2
    assert "return a hit, 3 read 0 (no measurement)" in capsys.readouterr().err


def test_a_failed_map_removes_the_folders_it_made(tmp_path, capsys):
    # Every folder the run made, parents included; it used to leave a/ and a/b/ behind.
    log = tmp_path / "nohits.log"
    log.write_text("FLASER 3 8.0 8.0 8.0 0 0 0 0 0 0 0.0 h 0.0\n")
    out, snaps = tmp_path / "a" / "b" / "c", tmp_path / "o" / "snaps"
    argv = ["map", str(log), "--max-range", "8", "--out", str(out), "--online",
            "--snapshots", str(snaps)]  # fmt: skip
    assert main(argv) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["nohits.log"]
    # evaluate refuses the same log in its terms (it ended in scikit-learn's words).
    assert main(["evaluate", str(log), "--max-range", "8"]) == 2
    assert "0 beam(s) of the 1 scans return a hit" in capsys.readouterr().err


@pytest.mark.parametrize(
    "log, stem",
    [("intel.gfs.log", "intel"), ("aces.log.gz", "aces"), ("lab.2024-06-01.log", "lab.2024-06-01"),
     ("run.bag", "run"), (".scan.log", "scan"), (".log", "log"), ("bagdir", "bagdir"),
     ("INTEL.GFS.LOG", "INTEL"), ("Aces.Log.Gz", "Aces"), ("run.BAG", "run")],
)  # fmt: skip
def test_log_stem(log, stem):
    assert log_stem(log) == stem


def test_map_names_its_files_after_the_whole_log_name(paper_log, tmp_path, capsys):
    # Cut at the first dot, the maps of lab.2024-06-01.log and lab.2024-06-02.log shared a
    # name and the second overwrote the first without a word.
    log, _ = paper_log
    options = ["--resolution", "1.0", "--every-nth-scan", "4", "--n-jobs", "1"]
    options += ["--out", str(tmp_path), "--quiet"]
    for day in ("01", "02"):
        dated = tmp_path / f"lab.2024-06-{day}.log"
        dated.write_bytes(log.read_bytes())
        assert main(["map", str(dated), *options]) == 0
    for day in ("01", "02"):
        for suffix in (".pgm", ".yaml", ".npz", ".png"):
            assert (tmp_path / f"lab.2024-06-{day}{suffix}").is_file()
    assert "overwriting" not in capsys.readouterr().err
    assert main(["map", str(dated), *options]) == 0
    assert "overwriting the map" in capsys.readouterr().err


def test_a_map_too_large_is_refused_before_the_fit(paper_log, capsys):
    log, _ = paper_log
    assert main(["map", str(log), "--resolution", "1e-6", "--quiet"]) == 2
    out, err = capsys.readouterr()
    assert "too large" in err and "use a coarser resolution" in err
    assert "fitted" not in out


@pytest.mark.slow
def test_map_intel_every_10th_scan(shared_data, tmp_path, capsys):
    rc = main(["map", str(shared_data / "intel.gfs.log"), "--every-nth-scan", "10",
               "--out", str(tmp_path), "--quiet"])  # fmt: skip
    assert rc == 0
    grid = OccupancyGrid.load(tmp_path / "intel.npz")
    # The map covers every training hit (every 10th scan spans 29.2 m x 29.1 m).
    hits = load_carmen(shared_data / "intel.gfs.log")[::10].hit_points()
    xmin, xmax, ymin, ymax = grid.extent
    assert xmin <= hits[:, 0].min() and hits[:, 0].max() <= xmax
    assert ymin <= hits[:, 1].min() and hits[:, 1].max() <= ymax
    # ... and not much more: the bounding box snapped outwards to whole cells.
    span = np.ptp(hits, axis=0) / grid.resolution
    assert np.all(np.asarray(grid.shape[::-1]) <= np.ceil(span) + 2)


@pytest.mark.parametrize(
    "options, expected",
    [
        ([], (1.0, 0.35, 4, 0.2, 1.0)),
        (["--max-beam-length", "none", "--beam-end-length", "None"], (None, None, 4, 0.2, 1.0)),
        (["--max-pieces-per-cell", "none"], (1.0, 0.35, None, 0.2, 1.0)),
        (["--max-pieces-per-cell", "2"], (1.0, 0.35, 2, 0.2, 1.0)),
        (["--min-hit-frequency", "none"], (1.0, 0.35, 4, None, 1.0)),
        (["--min-hit-frequency", "0.4"], (1.0, 0.35, 4, 0.4, 1.0)),
        (["--hyperparameter-beam-length", "none"], (1.0, 0.35, 4, 0.2, None)),
        (["--hyperparameter-beam-length", "2"], (1.0, 0.35, 4, 0.2, 2.0)),
    ],
)
def test_beam_piece_options_reach_the_mixture(options, expected):
    from skoccmap._cmd_map import make_mixture
    from skoccmap.cli import build_parser

    args = build_parser().parse_args(["map", "log.txt", *options])
    model = make_mixture(args)
    settings = (
        model.max_beam_length,
        model.beam_end_length,
        model.max_pieces_per_cell,
        model.min_hit_frequency,
        model.hyperparameter_beam_length,
    )
    assert settings == expected


@pytest.mark.parametrize(
    "option, value",
    [("--max-beam-length", v) for v in ["0", "-1", "long", "inf"]]
    + [("--hyperparameter-beam-length", v) for v in ["0", "-1", "long", "inf"]]
    + [("--beam-end-length", v) for v in ["0", "inf"]]
    + [("--max-pieces-per-cell", v) for v in ["0", "1.5", "many"]]
    + [("--min-hit-frequency", v) for v in ["-0.1", "2", "often"]],
)
def test_bad_beam_piece_option_is_refused(option, value, capsys):
    from skoccmap.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["map", "log.txt", option, value])
    assert option in capsys.readouterr().err


def _damaged_log(log, tmp_path):
    """The paper log with a truncated FLASER line after its 3rd scan (file line 5)."""
    lines = log.read_text().splitlines(keepends=True)
    damaged = tmp_path / "damaged.log"
    damaged.write_text("".join(lines[:4] + ["FLASER 17 1.0 2.0\n"] + lines[4:]))
    return damaged


def test_map_malformed_line_suggests_the_option(paper_log, tmp_path, capsys):
    damaged = _damaged_log(paper_log[0], tmp_path)
    assert main(["map", str(damaged), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("skoccmap map: error: ")
    assert "line 5: malformed FLASER message" in err
    assert "Pass --skip-bad-lines to skip malformed lines" in err
    assert "errors=" not in err  # the library's keyword means nothing on the command line
    assert not (tmp_path / "out").exists()


def test_map_skip_bad_lines(paper_log, tmp_path, capsys):
    damaged = _damaged_log(paper_log[0], tmp_path)
    argv = ["map", str(damaged), "--skip-bad-lines", "--resolution", "1.0", "--n-jobs", "1",
            "--out", str(tmp_path / "out"), "--quiet"]  # fmt: skip
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "skoccmap map: warning:" in captured.err
    assert "skipped 1 malformed laser line(s): line 5" in captured.err
    # All 26 scans of the paper log are read: only the damaged line is left out.
    assert "26 scans x 17 beams" in captured.out
    assert (tmp_path / "out" / "damaged.npz").is_file()


def test_skip_bad_lines_reaches_the_reader(monkeypatch, tmp_path):
    from skoccmap import _cmd_map
    from skoccmap.cli import build_parser

    seen = []

    def fake_load_carmen(path, *, max_range=None, errors="raise"):
        seen.append(errors)
        raise ValueError("stop here")

    monkeypatch.setattr("skoccmap.datasets.load_carmen", fake_load_carmen)
    (tmp_path / "x.log").write_text("")
    for options, expected in [([], "raise"), (["--skip-bad-lines"], "skip")]:
        args = build_parser().parse_args(["map", str(tmp_path / "x.log"), *options])
        with pytest.raises(ValueError, match="stop here"):
            _cmd_map.load_scans(args)
        assert seen[-1] == expected


def test_help_names_bags_as_well_as_carmen_logs(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    assert "map       build an occupancy map from a CARMEN laser log or a ROS bag" in out
    assert "evaluate  score a map on held-out scans of a CARMEN log or a ROS bag" in out
    for command in ("map", "evaluate"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "CARMEN log (plain text or gzip) or ROS bag: a path ending in .bag (ROS 1)" in text
        assert ".db3 or .mcap (ROS 2 storage), or a ROS 2 bag directory" in text
        assert "--skip-bad-lines" in text


def test_map_help_names_the_files_it_writes(capsys):
    with pytest.raises(SystemExit):
        main(["map", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for name in ("<name>.pgm + <name>.yaml", "<name>.npz", "<name>.png"):
        assert name in text


def test_map_warns_of_a_max_range_above_the_logs_sentinel(tmp_path, capsys):
    lines = [f"FLASER 4 1.5 40.0 2.0 40.0 {i} 0 0 {i} 0 0 {i} host {i}\n" for i in range(6)]
    log = tmp_path / "sentinel.log"
    log.write_text("".join(lines))
    argv = ["map", str(log), "--max-range", "100", "--resolution", "1.0", "--n-jobs", "1"]
    argv += ["--out", str(tmp_path / "out"), "--quiet"]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "12 readings equal 40 m" in err
    assert "with --max-range 100 they are hits" in err
    assert "Pass --max-range 40, or leave it out" in err


def test_map_announces_its_grid_before_the_fit(paper_log, tmp_path, capsys, monkeypatch):
    from skoccmap import _cmd_map

    log, _ = paper_log
    argv = ["map", str(log), "--resolution", "1.0", "--every-nth-scan", "4", "--n-jobs", "1"]
    argv += ["--out", str(tmp_path), "--quiet"]
    assert main(argv) == 0
    captured = capsys.readouterr()
    grid = OccupancyGrid.load(tmp_path / "paper.npz")
    announced = f"map grid: {grid.shape[1]} x {grid.shape[0]} cells at 1 m"
    assert announced in captured.out
    assert captured.out.index(announced) < captured.out.index("fitted")
    assert "warning" not in captured.err
    # A map above the bound warns before its fit, with its size.
    monkeypatch.setattr(_cmd_map, "_LARGE_MAP_CELLS", grid.probability.size - 1)
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert f"skoccmap map: warning: the map has {grid.probability.size:,} cells" in err
    assert "--max-range" in err and "--resolution" in err


def test_model_options_reach_the_mixture():
    from skoccmap._cmd_map import make_mixture
    from skoccmap.cli import build_parser

    argv = ["map", "log.txt", "--combiner", "poe", "--max-expert-size", "50",
            "--learn-all-hyperparameters", "--seed", "7", "--n-jobs", "1"]  # fmt: skip
    model = make_mixture(build_parser().parse_args(argv))
    assert (model.combiner, model.max_expert_size, model.share_hyperparameters) == (
        "poe", 50, False)  # fmt: skip
    assert (model.random_state, model.n_jobs) == (7, 1)
    default = make_mixture(build_parser().parse_args(["map", "log.txt"]))
    assert default.share_hyperparameters is True and default.random_state == 0


class _AtThePrior:
    """P(occupied) 1/2 and variance 10 everywhere: every cell at the prior."""

    def predict_proba(self, X):
        return np.full((len(X), 2), 0.5)

    def predict_var(self, X):
        return np.full(len(X), 10.0)


def test_unknown_cell_options_reach_the_map():
    from skoccmap._cmd_map import _grid, _unknown_variance
    from skoccmap.cli import build_parser
    from skoccmap.observations import Scans

    # Two beams from (0.1, 0.1), along +x and +y: the cells between them are unseen.
    train = Scans([[0.1, 0.1, 0.0]], [[2.0, 2.0]], [0.0, np.pi / 2], max_range=5.0)

    def unknown(*options):
        args = build_parser().parse_args(["map", "log.txt", "--resolution", "0.5", *options])
        grid = _grid(args, _AtThePrior(), train, _unknown_variance(args.unknown_variance), False)
        if grid.unknown is None:
            return lambda x, y: False
        cell = lambda x, y: grid.unknown[  # noqa: E731
            int((y - grid.origin[1]) // 0.5), int((x - grid.origin[0]) // 0.5)
        ]
        return cell

    # Every cell at the prior variance: 'auto' (90 % of it) and 5 call them all unknown.
    for options in ([], ["--unknown-variance", "5"], ["--keep-unobserved"]):
        cell = unknown(*options)
        assert cell(1.0, 0.1) and cell(1.5, 1.5)
    # No variance rule (or one no cell exceeds): only the cells no beam crossed.
    for value in ("none", "NONE", "20"):
        cell = unknown("--unknown-variance", value)
        assert not cell(1.0, 0.1) and not cell(0.1, 1.0) and cell(1.5, 1.5)
    # Neither rule: no cell is unknown.
    cell = unknown("--unknown-variance", "none", "--keep-unobserved")
    assert not cell(1.0, 0.1) and not cell(1.5, 1.5)


def test_a_log_with_a_single_hit_is_refused(tmp_path, capsys):
    # One hit cannot be clustered: the map needs two.
    log = tmp_path / "onehit.log"
    lines = [f"FLASER 3 8.0 8.0 8.0 {t} 0 0 {t} 0 0 {t}.0 h {t}.0\n" for t in range(3)]
    lines[1] = lines[1].replace(" 8.0 8.0 ", " 2.0 8.0 ", 1)
    log.write_text("".join(lines))
    out = tmp_path / "o"
    assert main(["map", str(log), "--max-range", "8", "--quiet", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "1 beam(s) of the 3 training scans return a hit" in err
    assert "a map needs at least 2 hits" in err
    assert not out.exists()


def test_no_command_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([])
    assert exit_info.value.code == 2
    assert "COMMAND" in capsys.readouterr().err


def test_usage_errors_name_the_skoccmap_command(capsys):
    # Run as python -m skoccmap, argparse would name the program after __main__.py; the
    # usage errors carry the prefix of the commands' own errors.
    with pytest.raises(SystemExit):
        main(["map"])
    err = capsys.readouterr().err
    assert err.startswith("usage: skoccmap map ")
    assert "skoccmap map: error: the following arguments are required: LOG" in err


def test_the_console_command_prints_warnings_without_the_launcher_line(monkeypatch, capsys):
    import warnings

    from skoccmap.cli import console_main

    monkeypatch.setattr(warnings, "showwarning", warnings.showwarning)  # restored after
    with pytest.raises(SystemExit):
        console_main(["--version"])
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.warn("ranges in millimetres?", UserWarning, stacklevel=1)
    assert capsys.readouterr().err == "skoccmap: UserWarning: ranges in millimetres?\n"


def test_version(capsys):
    import skoccmap

    with pytest.raises(SystemExit):
        main(["--version"])
    assert capsys.readouterr().out.strip() == f"skoccmap {skoccmap.__version__}"


@pytest.mark.parametrize("module", ["skoccmap", "skoccmap.cli"])
def test_module_run_exits_with_the_commands_status(tmp_path, module):
    # python -m skoccmap (or skoccmap.cli): a refused run must not exit 0.
    import subprocess
    import sys

    import skoccmap

    env = {**os.environ, "PYTHONPATH": str(Path(skoccmap.__file__).parents[1])}
    argv = [sys.executable, "-m", module, "map", str(tmp_path / "missing.log")]
    done = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True)
    assert done.returncode == 2
    assert "skoccmap map: error:" in done.stderr and "No such file" in done.stderr


# A corridor the tests can map in about a second: the laser drives along +x from (0.1 t, 0),
# its five FLASER beams at -90, -45, 0, 45 and 90 degrees. A wall 0.95 m to its right;
# ahead, an end wall at x = 4 (the first scan sees through a door to x = 6); at 45 degrees
# nothing within the 8 m sentinel; at 90 degrees no reading (0).
_WALL_Y = -0.95


def _corridor_readings(t):
    ahead = 6.0 if t == 0 else 4.0 - 0.1 * t
    return [-_WALL_Y, -_WALL_Y * np.sqrt(2), ahead, 8.0, 0.0]


def _corridor_log(path, n_scans=23, readings=_corridor_readings):
    lines = []
    for t in range(n_scans):
        ranges = " ".join(f"{r:.6f}" for r in readings(t))
        pose = f"{0.1 * t:.6f} 0 0"
        lines.append(f"FLASER 5 {ranges} {pose} {pose} {t}.0 sim {t}.0\n")
    path.write_text("".join(lines))
    return path


def _corridor_hits(n_scans=23):
    """The hit points of the corridor log, from its geometry."""
    hits = []
    for t in range(n_scans):
        x = 0.1 * t
        hits += [(x, _WALL_Y), (x - _WALL_Y, _WALL_Y), (6.0 if t == 0 else 4.0, 0.0)]
    return np.array(hits)


def _read_map_server(yaml_path):
    """resolution, origin and pixel rows (top row first) of a map_server pair, parsed here."""
    fields = dict(line.split(": ", 1) for line in yaml_path.read_text().splitlines())
    origin = [float(v) for v in fields["origin"].strip("[]").split(",")]
    data = (yaml_path.parent / fields["image"]).read_bytes()
    magic, size, maxval, pixels = data.split(b"\n", 3)
    width, height = map(int, size.split())
    assert (magic, maxval, len(pixels)) == (b"P5", b"255", width * height)
    image = np.frombuffer(pixels, dtype=np.uint8).reshape(height, width)
    return float(fields["resolution"]), origin, image


def test_map_defaults_on_a_small_log(tmp_path, monkeypatch, capsys):
    # Every scan, 0.1 m cells, files in ./<log name>_map: the defaults the help states.
    _corridor_log(tmp_path / "corridor.log")
    monkeypatch.chdir(tmp_path)
    argv = ["map", "corridor.log", "--max-range", "8", "--n-jobs", "1", "--quiet"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    # Per scan 3 hits (each with its return beam), 1 no-return beam and 1 beam without reading.
    assert "training on 23 scans: 161 observations (69 hits, 69 return beams, 23 no-return" in out
    folder = tmp_path / "corridor_map"
    for suffix in (".yaml", ".pgm", ".npz", ".png"):
        assert (folder / f"corridor{suffix}").is_file()
        assert f"wrote {Path('corridor_map') / f'corridor{suffix}'}" in out
    grid = OccupancyGrid.load(folder / "corridor.npz")
    assert grid.resolution == 0.1
    # The map covers every hit, the first scan's through the door included.
    hits = _corridor_hits()
    xmin, xmax, ymin, ymax = grid.extent
    assert xmin <= hits[:, 0].min() and hits[:, 0].max() <= xmax
    assert ymin <= hits[:, 1].min() and hits[:, 1].max() <= ymax
    # The PNG: probability and uncertainty panels side by side.
    width, height = struct.unpack(">II", (folder / "corridor.png").read_bytes()[16:24])
    assert width > 1.5 * height


def test_map_server_files_put_the_walls_where_the_log_saw_them(tmp_path, capsys):
    # The PGM read as map_server reads it: origin at the lower-left corner, top row first.
    log = _corridor_log(tmp_path / "corridor.log")
    argv = ["map", str(log), "--max-range", "8", "--n-jobs", "1", "--quiet",
            "--resolution", "0.2", "--out", str(tmp_path)]  # fmt: skip
    assert main(argv) == 0
    resolution, origin, image = _read_map_server(tmp_path / "corridor.yaml")
    assert resolution == 0.2

    def pixel(x, y):
        row = image.shape[0] - 1 - int((y - origin[1]) // resolution)
        return image[row, int((x - origin[0]) // resolution)]

    # Occupied (0): the right wall, hit at every step; free (254): the corridor the beams
    # to it crossed.
    for x in (0.5, 1.1, 1.7):
        assert pixel(x, _WALL_Y - 0.05) == 0
        assert pixel(x, -0.5) == 254


def test_online_defaults_batches_and_snapshots(tmp_path, capsys):
    # Default 10 scans per batch, a snapshot every 10 batches and after the last.
    log = _corridor_log(tmp_path / "corridor.log")
    snaps = tmp_path / "new" / "snaps"
    argv = ["map", str(log), "--max-range", "8", "--n-jobs", "1", "--quiet", "--online",
            "--snapshots", str(snaps), "--out", str(tmp_path)]  # fmt: skip
    assert main(argv) == 0
    rows = re.findall(r"^\| (\d+) \| (\d+) \| (\d+) \|", capsys.readouterr().out, re.M)
    # batch, scans seen, observations (7 per scan)
    assert rows == [("1", "10", "70"), ("2", "20", "70"), ("3", "23", "21")]
    assert sorted(p.name for p in snaps.iterdir()) == ["batch_00003.npz", "batch_00003.png"]
    snapshot = OccupancyGrid.load(snaps / "batch_00003.npz")
    final = OccupancyGrid.load(tmp_path / "corridor.npz")
    np.testing.assert_allclose(snapshot.probability, final.probability)


def test_online_snapshot_lines_name_every_file_written(tmp_path, capsys):
    # The line named the .npz alone while the .png was written beside it.
    log = _corridor_log(tmp_path / "corridor.log", n_scans=6)
    snaps = tmp_path / "snaps"
    argv = ["map", str(log), "--max-range", "8", "--n-jobs", "1", "--quiet", "--online",
            "--batch-scans", "3", "--snapshot-every", "1", "--snapshots", str(snaps),
            "--out", str(tmp_path)]  # fmt: skip
    assert main(argv) == 0
    lines = [
        line for line in capsys.readouterr().out.splitlines() if line.startswith("wrote snapshot")
    ]
    files = sorted(snaps.iterdir())
    assert [p.name for p in files] == [
        "batch_00001.npz", "batch_00001.png", "batch_00002.npz", "batch_00002.png"
    ]  # fmt: skip
    assert len(lines) == 2
    for line, stem in zip(lines, ("batch_00001", "batch_00002"), strict=True):
        for path in files:
            assert (str(path) in line) == (path.stem == stem), (line, path)


def test_online_waits_for_two_hits_holding_the_batches_before(tmp_path, capsys):
    # The first scan has a single hit (it cannot be clustered): it waits for the second
    # and enters the model with it.
    def readings(t):
        return [8.0, 8.0, 3.0, 8.0, 8.0] if t == 0 else _corridor_readings(t)

    log = _corridor_log(tmp_path / "corridor.log", n_scans=4, readings=readings)
    argv = ["map", str(log), "--max-range", "8", "--n-jobs", "1", "--quiet", "--online",
            "--batch-scans", "1", "--out", str(tmp_path)]  # fmt: skip
    assert main(argv) == 0
    rows = re.findall(r"^\| (\d+) \| (\d+) \| (\d+) \|", capsys.readouterr().out, re.M)
    # Scan 0: 1 hit, 1 return beam, 4 no-return beams; each later scan 7 rows.
    assert rows == [("2", "2", "13"), ("3", "3", "7"), ("4", "4", "7")]


def _online_args(*options):
    from skoccmap._cmd_map import _check_online_options
    from skoccmap.cli import build_parser

    args = build_parser().parse_args(["map", "log.txt", *options])
    _check_online_options(args)
    return args


def test_online_options_given_are_kept_and_checked():
    args = _online_args("--online", "--batch-scans", "3", "--refit-fraction", "0",
                        "--snapshot-every", "2")  # fmt: skip
    assert (args.batch_scans, args.refit_fraction, args.snapshot_every) == (3, 0.0, 2)
    args = _online_args("--online")
    assert (args.batch_scans, args.refit_fraction, args.snapshot_every) == (10, None, 10)
    for option, value, message in [
        ("--batch-scans", "0", "--batch-scans must be >= 1"),
        ("--refit-fraction", "-0.5", "--refit-fraction must be >= 0"),
        ("--refit-fraction", "nan", "--refit-fraction must be >= 0"),
        ("--snapshot-every", "0", "--snapshot-every must be >= 1"),
    ]:
        with pytest.raises(ValueError, match=message):
            _online_args("--online", option, value)


def test_refit_fraction_reaches_the_online_mixture(tmp_path):
    from skoccmap._cmd_map import _replay

    train = load_carmen(_corridor_log(tmp_path / "corridor.log", n_scans=4), max_range=8.0)
    for options, expected in [([], MixtureGPOccupancyMap().refit_fraction),
                              (["--refit-fraction", "0.25"], 0.25)]:  # fmt: skip
        args = _online_args("--online", "--n-jobs", "1", "--quiet", *options)
        model = _replay(args, train, None)
        assert model.refit_fraction == expected and model.n_experts_ >= 1


def test_map_option_defaults_are_the_documented_ones():
    from skoccmap._cmd_map import make_mixture
    from skoccmap.cli import build_parser

    model = make_mixture(build_parser().parse_args(["map", "log.txt"]))
    defaults = MixtureGPOccupancyMap()
    assert model.max_expert_size == defaults.max_expert_size == 400
    assert model.combiner == defaults.combiner == "rbcm"
    assert model.n_jobs == -1  # all cores
    assert model.verbose == 1  # progress messages unless --quiet
    assert make_mixture(build_parser().parse_args(["map", "log.txt", "--quiet"])).verbose == 0


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--max-expert-size", "1"], "--max-expert-size must be >= 2, got 1"),
        (["--seed", "4294967296"], "--seed must be an integer in [0, 2**32), got 4294967296"),
        (["--resolution", "0"], "--resolution must be a positive finite length, got 0"),
        (["--resolution", "nan"], "--resolution must be a positive finite length"),
        (["--max-range", "0"], "--max-range must be a positive finite length, got 0"),
        (["--max-range", "inf"], "--max-range must be a positive finite length, got inf"),
    ],
)
def test_bad_option_at_its_bound_is_refused(argv, message, tmp_path, capsys):
    log = _corridor_log(tmp_path / "corridor.log", n_scans=2)
    assert main(["map", str(log), *argv, "--out", str(tmp_path / "out")]) == 2
    out, err = capsys.readouterr()
    assert message in err and "scans x" not in out  # before the log is read
    assert not (tmp_path / "out").exists()


def test_min_hit_frequency_takes_both_ends():
    from skoccmap.cli import build_parser

    for value in ("0", "1"):
        args = build_parser().parse_args(["map", "log.txt", "--min-hit-frequency", value])
        assert args.min_hit_frequency == float(value)


def test_stopwatch_table_totals_its_rows():
    from skoccmap._cmd_map import Stopwatch

    watch = Stopwatch()
    watch.rows = [("read log", 1.25), ("fit mixture", 2.5)]
    assert watch.table().splitlines()[-1] == "| total | 3.8 |"


def test_a_bag_without_the_ros_extra_is_a_clear_error(tmp_path, monkeypatch, capsys):
    # Without rosbags, the reader's advice to install it, not a traceback.
    def without_rosbags(*args, **kwargs):
        raise ImportError("reading ROS bags needs the rosbags package")

    monkeypatch.setattr("skoccmap.datasets.load_rosbag", without_rosbags)
    bag = tmp_path / "run.bag"
    bag.write_bytes(b"")
    assert main(["map", str(bag), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err == "skoccmap map: error: reading ROS bags needs the rosbags package\n"
    assert not (tmp_path / "out").exists()
