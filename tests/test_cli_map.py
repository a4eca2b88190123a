import re

import numpy as np
import pytest
from sklearn.metrics import roc_auc_score

from skoccmap import OccupancyGrid
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


def test_evaluate_prints_both_models(paper_log, capsys):
    log, _ = paper_log
    rc = main(["evaluate", str(log), "--holdout-every", "4", "--every-nth-scan", "2", "--quiet"])
    assert rc == 0
    out = capsys.readouterr().out
    pattern = r"^\| (mixture of GP experts|counting grid \(0.1 m\)) \| ([0-9.]+)"
    aucs = dict(re.findall(pattern, out, flags=re.M))
    assert set(aucs) == {"mixture of GP experts", "counting grid (0.1 m)"}
    assert all(0.5 < float(v) <= 1.0 for v in aucs.values())


@pytest.mark.parametrize(
    "argv, message",
    [
        (["map", "{log}", "--every-nth-scan", "0"], "--every-nth-scan must be >= 1"),
        (["map", "{log}", "--resolution", "-1"], "--resolution must be positive"),
        (["map", "{log}", "--unknown-variance", "big"], "--unknown-variance"),
        (["map", "{missing}"], "No such file"),
        (["evaluate", "{log}", "--holdout-every", "1"], "--holdout-every must be >= 2"),
    ],
)
def test_bad_options_exit_with_a_message(paper_log, tmp_path, capsys, argv, message):
    log, _ = paper_log
    argv = [a.format(log=log, missing=tmp_path / "missing.log") for a in argv]
    assert main(argv) == 2
    assert message in capsys.readouterr().err


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
    [([], (1.0, 0.5)), (["--max-beam-length", "none", "--beam-end-length", "None"], (None, None))],
)
def test_beam_piece_options_reach_the_mixture(options, expected):
    from skoccmap._cmd_map import make_mixture
    from skoccmap.cli import build_parser

    args = build_parser().parse_args(["map", "log.txt", *options])
    model = make_mixture(args)
    assert (model.max_beam_length, model.beam_end_length) == expected


@pytest.mark.parametrize("value", ["0", "-1", "long"])
def test_bad_beam_piece_option_is_refused(value, capsys):
    from skoccmap.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["map", "log.txt", "--max-beam-length", value])
    assert "--max-beam-length" in capsys.readouterr().err
