import re

import numpy as np
import pytest

from skoccmap.cli import main


def _table(out):
    """Rows of the results table: model name -> list of numbers."""
    names = r"mixture of GP experts|frequency grid \(0.1 m\)|log-odds grid per scan \(0.1 m\)"
    rows = re.findall(rf"^\| ({names}) \|(.*)\|$", out, re.M)
    return {name: [float(v) for v in cells.split("|")] for name, cells in rows}


def test_evaluate_blocks_protocol_several_seeds(paper_log, capsys):
    argv = ["evaluate", str(paper_log[0]), "--protocol", "blocks", "--block-size", "4",
            "--train-every", "2", "--seeds", "0", "1", "--n-jobs", "1", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    out = capsys.readouterr().out
    # 26 scans: one block of 4 held out, every 2nd of the other 22 trained on
    assert len(re.findall(r"^seed [01]: training on 11 scans .* testing on 4 held-out", out, re.M))
    assert "| model | AUC seed 0 | AUC seed 1 | mean AUC | fit s | predict s |" in out
    table = _table(out)
    assert set(table) == {
        "mixture of GP experts",
        "frequency grid (0.1 m)",
        "log-odds grid per scan (0.1 m)",
    }
    for auc0, auc1, mean, _, _ in table.values():
        assert 0.5 < auc0 <= 1 and 0.5 < auc1 <= 1
        assert abs(mean - (auc0 + auc1) / 2) <= 1e-4


def test_evaluate_every_nth_is_the_default(paper_log, capsys):
    argv = ["evaluate", str(paper_log[0]), "--holdout-every", "4", "--train-every", "3",
            "--n-jobs", "1", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "protocol every-nth" in out
    # scans 2, 6, ..., 22 held out; every 3rd of the other 20 trained on
    assert "training on 7 scans" in out and "testing on 6 held-out scans" in out
    assert "| model | held-out AUC | fit s | predict s |" in out
    assert all(0.5 < row[0] <= 1 for row in _table(out).values())


@pytest.mark.parametrize(
    "options, message",
    [
        (["--protocol", "blocks"], "--block-size 40 leaves no training scan of the log's 26"),
        (["--holdout-every", "60"], "--holdout-every 60 holds out no scan of the log's 26"),
        (["--protocol", "blocks", "--holdout-every", "5"], "--holdout-every does not apply"),
        (["--protocol", "blocks", "--free-per-beam", "2"], "--free-per-beam does not apply"),
        (["--block-size", "4"], "--block-size does not apply to --protocol every-nth"),
        (["--protocol", "blocks", "--block-size", "0"], "--block-size must be >= 1"),
        (["--train-every", "0"], "--train-every must be >= 1"),
        (["--every-nth-scan", "0"], "--train-every must be >= 1"),
        (["--holdout-every", "1"], "--holdout-every must be >= 2"),
        (["--seeds", "-1"], "--seeds must be non-negative"),
        (["--seed", "-1"], "--seed must be non-negative"),
        (["--seeds", "1", "1", "2"], "--seeds must be distinct, got 1 1 2"),
        # It was numpy's "Seed must be between 0 and 2**32 - 1", after the log was read.
        (["--seeds", "0", "4294967296"], "--seeds must be below 2**32, got 4294967296"),
        (["--grid-resolution", "0"], "--grid-resolution must be a positive finite length"),
        (["--grid-resolution", "nan"], "--grid-resolution must be a positive finite length"),
        # It was refused only after the log was read and the mixture fitted, in the
        # counting grid's words.
        (
            ["--grid-resolution", "inf"],
            "--grid-resolution must be a positive finite length, got inf",
        ),
        (["--free-per-beam", "0"], "--free-per-beam must be >= 1"),
        # It was a MemoryError traceback from numpy.
        (
            ["--free-per-beam", "10000000000000"],
            "--free-per-beam 10000000000000 would draw",
        ),
    ],
)
def test_evaluate_bad_options(paper_log, capsys, options, message):
    assert main(["evaluate", str(paper_log[0]), *options, "--quiet"]) == 2
    assert message in capsys.readouterr().err


def _damaged_log(log, tmp_path):
    """The paper log with a FLASER line whose pose is not a number after its 2nd scan."""
    lines = log.read_text().splitlines(keepends=True)
    bad = lines[1].split()
    bad[19] = "nan"  # x of the laser pose (FLASER 17, 17 readings, then x y theta)
    damaged = tmp_path / "damaged.log"
    damaged.write_text("".join(lines[:3] + [" ".join(bad) + "\n"] + lines[3:]))
    return damaged


def test_evaluate_malformed_line_suggests_the_option(paper_log, tmp_path, capsys):
    damaged = _damaged_log(paper_log[0], tmp_path)
    assert main(["evaluate", str(damaged), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("skoccmap evaluate: error: ")
    assert "line 4: malformed FLASER message: non-finite pose or timestamp" in err
    assert "Pass --skip-bad-lines" in err and "errors=" not in err


def test_evaluate_skip_bad_lines(paper_log, tmp_path, capsys):
    damaged = _damaged_log(paper_log[0], tmp_path)
    argv = ["evaluate", str(damaged), "--skip-bad-lines", "--holdout-every", "4",
            "--train-every", "3", "--n-jobs", "1", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "skoccmap evaluate: warning:" in captured.err
    assert "skipped 1 malformed laser line(s): line 4 (non-finite pose or timestamp)" in (
        captured.err
    )
    # The same split as the undamaged log: the bad line is not a scan.
    assert "26 scans x 17 beams" in captured.out
    assert "training on 7 scans" in captured.out and "testing on 6 held-out scans" in captured.out
    assert all(0.5 < row[0] <= 1 for row in _table(captured.out).values())


def test_evaluate_help_names_bags():
    from skoccmap.cli import build_parser

    parser = build_parser()
    evaluate = parser._subparsers._group_actions[0].choices["evaluate"]
    log = next(a for a in evaluate._actions if a.dest == "log")
    assert "ROS bag" in log.help and ".bag" in log.help and "CARMEN" in log.help
    assert "--skip-bad-lines" in evaluate.format_help()


def _parsed(paper_log, *options):
    from skoccmap._cmd_evaluate import _check_options
    from skoccmap.cli import build_parser

    args = build_parser().parse_args(["evaluate", str(paper_log[0]), *options])
    _check_options(args)
    return args


@pytest.mark.parametrize(
    "protocol", [["--holdout-every", "4"], ["--protocol", "blocks", "--block-size", "4"]]
)
def test_evaluate_each_seed_draws_its_own_split_points_and_mixture(paper_log, protocol):
    # Each seed repeats the whole run: the same seed draws the same test points, and the
    # seeds between them draw different ones (and seed the mixture).
    from skoccmap._cmd_evaluate import _models, _split
    from skoccmap.datasets import load_carmen

    scans = load_carmen(paper_log[0])
    args = _parsed(paper_log, *protocol)
    points = [_split(scans, args, seed)[2] for seed in (0, 1, 2, 0)]
    np.testing.assert_array_equal(points[0], points[3])
    assert not all(p.shape == points[0].shape and np.array_equal(p, points[0])
                   for p in points[1:3])  # fmt: skip
    assert _models(args, 5)["mixture of GP experts"].random_state == 5


def _numbered_scans(n_scans):
    """Scans whose pose x is their index, each with two 2 m beams (returns)."""
    from skoccmap.observations import Scans

    poses = np.c_[np.arange(n_scans, dtype=float), np.zeros((n_scans, 2))]
    return Scans(poses, np.full((n_scans, 2), 2.0), [-0.5, 0.5], max_range=8.0)


def test_evaluate_every_nth_defaults_split(paper_log):
    # Held out: every 10th scan from the 5th (between training scans); trained on: every
    # 10th of the others; one free point per held-out beam.
    from skoccmap._cmd_evaluate import _split

    args = _parsed(paper_log)
    assert (args.holdout_every, args.train_every, args.free_per_beam) == (10, 10, 1)
    train, test, points, labels = _split(_numbered_scans(26), args, 0)
    assert test.poses[:, 0].tolist() == [5, 15, 25]
    remaining = [i for i in range(26) if i % 10 != 5]
    assert train.poses[:, 0].tolist() == remaining[::10]
    assert (int(labels.sum()), int((labels == 0).sum())) == (6, 6)  # 3 scans x 2 beams
    args = _parsed(paper_log, "--free-per-beam", "3")
    assert int((_split(_numbered_scans(26), args, 0)[3] == 0).sum()) == 18


@pytest.mark.parametrize(
    "options, n_scans, message",
    [
        ([], 5, "--holdout-every 10 holds out no scan of the log's 5"),
        (["--protocol", "blocks", "--block-size", "4"], 4,
         "--block-size 4 leaves no training scan of the log's 4"),
    ],
)  # fmt: skip
def test_evaluate_split_refuses_a_log_too_short(paper_log, options, n_scans, message):
    from skoccmap._cmd_evaluate import _split

    with pytest.raises(ValueError, match=re.escape(message)):
        _split(_numbered_scans(n_scans), _parsed(paper_log, *options), 0)
    _split(_numbered_scans(n_scans + 1), _parsed(paper_log, *options), 0)


def test_evaluate_grid_resolution_reaches_the_counting_grid(paper_log):
    from skoccmap._cmd_evaluate import _models

    models = _models(_parsed(paper_log, "--grid-resolution", "0.3"), 0)
    assert models["frequency grid (0.3 m)"].resolution == 0.3
    assert models["log-odds grid per scan (0.3 m)"].resolution == 0.3


def test_evaluate_scores_the_log_odds_grid_updated_scan_by_scan(paper_log, capsys):
    # The baselines as benchmarks/README.md's B4 has them: the log-odds grid clamped after
    # every scan (OctoMap), not after its evidence was summed, and the frequency grid.
    from sklearn.metrics import roc_auc_score

    from skoccmap._cmd_evaluate import _split
    from skoccmap.baselines import FrequencyGridMap, OccupancyGridMap
    from skoccmap.datasets import load_carmen
    from skoccmap.observations import as_segments

    options = ["--holdout-every", "4", "--train-every", "1", "--seed", "3"]
    argv = ["evaluate", str(paper_log[0]), *options, "--n-jobs", "1", "--quiet"]
    assert main(argv) == 0
    table = _table(capsys.readouterr().out)
    train, _, points, labels = _split(load_carmen(paper_log[0]), _parsed(paper_log, *options), 3)
    X, y, _, scan = train.to_observations(return_scan_index=True)
    queries = as_segments(points)
    # On this log the summed grid ranks them 0.9365, the grid per scan 0.9359.
    expected = {
        "log-odds grid per scan (0.1 m)": OccupancyGridMap(0.1).fit(X, y, scan_index=scan),
        "frequency grid (0.1 m)": FrequencyGridMap(0.1).fit(X, y),
    }
    for name, grid in expected.items():
        auc = roc_auc_score(labels, grid.predict_proba(queries)[:, 1])
        assert table[name][0] == pytest.approx(auc, abs=5e-5)  # printed to 4 digits


def test_evaluate_table_times_the_fit_and_the_prediction(paper_log, monkeypatch, capsys):
    # A model whose fit takes 0.3 s and whose prediction takes none: the table says so.
    import time

    from skoccmap import _cmd_evaluate

    class SlowFit:
        classes_ = np.array([0, 1])

        def fit(self, X, y):
            time.sleep(0.3)
            return self

        def predict_proba(self, X):
            return np.c_[np.full(len(X), 0.5), np.full(len(X), 0.5)]

    monkeypatch.setattr(_cmd_evaluate, "_models", lambda args, seed: {"slow": SlowFit()})
    argv = ["evaluate", str(paper_log[0]), "--holdout-every", "4", "--quiet"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    header, separator, row = out[out.index("| model |") :].splitlines()[:3]
    assert separator.count("|") == header.count("|") == 5
    name, auc, fit_s, predict_s = [cell.strip() for cell in row.strip("|").split("|")]
    assert (name, auc) == ("slow", "0.5000")
    assert float(fit_s) >= 0.3 > float(predict_s)


@pytest.mark.parametrize(
    "options, expected",
    [
        (
            ["--holdout-every", "4", "--free-per-beam", "3"],
            "protocol every-nth: 1 in 4 scans held out from scan 2, 3 free point(s) per "
            "held-out beam, 0.05 m short of the hit; training on 1 in 5 of the remaining "
            "scans, seeds 7",
        ),
        (
            ["--protocol", "blocks", "--block-size", "4"],
            "protocol blocks: 10% of the scans held out in blocks of 4 consecutive scans (the "
            "protocol's: 40), floor(r / 2) free points (at least one) per held-out beam of "
            "range r <= 40 m, 0.1 m short of the hit; training on 1 in 5 of the remaining "
            "scans, seeds 7",
        ),
    ],
)
def test_evaluate_output_states_the_test_set_it_scored(paper_log, options, expected):
    # The table's numbers are published with the definition of their test set: the held-out
    # scans, the free points and their margin. It used to say "protocol every-nth" only.
    from skoccmap._cmd_evaluate import _protocol_line, _split

    args = _parsed(paper_log, *options, "--train-every", "5", "--seed", "7")
    assert _protocol_line(args) == expected
    # What the line says is what the split does: scans 2, 6, 10, ... held out, three free
    # points per beam within the free margin of the hit.
    if args.protocol == "every-nth":
        scans = _numbered_scans(26)
        _, test, points, labels = _split(scans, args, 7)
        assert test.poses[:, 0].tolist() == list(range(2, 26, 4))
        assert np.count_nonzero(labels == 0) == 3 * test.ranges.size
        free = (
            points[labels == 0]
            - np.repeat(test.poses[:, :2], 2, axis=0)[np.tile(np.arange(test.ranges.size), 3)]
        )
        assert np.linalg.norm(free, axis=1).max() <= 2.0 - 0.05


def test_evaluate_missing_log(tmp_path, capsys):
    assert main(["evaluate", str(tmp_path / "missing.log")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("skoccmap evaluate: error: ") and "No such file" in err


def test_evaluate_refuses_held_out_scans_without_a_hit(tmp_path, capsys):
    # Odd scans see nothing within the 8 m sentinel: held out every 2nd from the 1st, they
    # leave no hit to score, and the fits are not paid for.
    lines = []
    for t in range(6):
        ranges = "8.0 8.0 8.0" if t % 2 else "1.0 2.0 1.5"
        lines.append(f"FLASER 3 {ranges} {0.1 * t} 0 0 {0.1 * t} 0 0 {t}.0 sim {t}.0\n")
    log = tmp_path / "blind.log"
    log.write_text("".join(lines))
    argv = ["evaluate", str(log), "--max-range", "8", "--holdout-every", "2", "--quiet"]
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert "every held-out point is free: the AUC is undefined" in err
    assert "seed 0: training on" not in out
