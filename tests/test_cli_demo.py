import contextlib
import io
import re
import sys

import numpy as np
import pytest
from sklearn.metrics import roc_auc_score

from skoccmap import OccupancyGrid
from skoccmap.cli import main
from skoccmap.datasets import make_paper_scans
from skoccmap.observations import HIT, NO_RETURN, RETURN

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
FIGURES = ("figure2_clusters.png", "figure4_maps.png", "figure5_roc.png")
LABELS = {
    "moe": "mixture of GP experts",
    "bcm": "Bayesian committee machine",
    "single": "single GP",
}


def run_demo(argv):
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        rc = main(["demo", *argv])
    return rc, stdout.getvalue(), stderr.getvalue()


def table_rows(text, title):
    """Cells of the markdown table following the line that starts with ``title``."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(title))
    rows = []
    for line in lines[start + 1 :]:
        if not line.strip() and rows:
            break
        if line.startswith("|") and not line.startswith("|---"):
            rows.append([cell.strip() for cell in line.strip("|").split("|")])
    return rows[1:]  # without the header


@pytest.fixture(scope="module")
def quick_demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    rc, stdout, _ = run_demo(["--quick", "--out", str(out)])
    return rc, stdout, out


def check_tables(stdout, methods):
    data = make_paper_scans(random_state=0)
    counts = table_rows(stdout, "Table 1")
    assert counts[-1][0] == "all"
    per_cluster = np.array([[int(c) for c in row[1:]] for row in counts[:-1]])
    expected = [int(np.sum(data.kind == k)) for k in (HIT, RETURN, NO_RETURN)]
    # The clusters share out every observation of the simulated scans, each once.
    assert per_cluster[:, :3].sum(axis=0).tolist() == expected
    assert per_cluster[:, 3].tolist() == per_cluster[:, :3].sum(axis=1).tolist()
    assert [int(c) for c in counts[-1][1:]] == [*expected, len(data.X)]
    assert len(per_cluster) >= 2

    times = table_rows(stdout, "Table 2")
    assert [row[0] for row in times] == [LABELS[m] for m in methods]
    for _, fit_s, predict_s, auc in times:
        assert float(fit_s) > 0 and float(predict_s) > 0
        assert 0.9 < float(auc) <= 1.0
    return {row[0]: float(row[3]) for row in times}


def check_maps(out, methods):
    data = make_paper_scans(random_state=0)
    for method in methods:
        yaml_path = out / f"map_{method}.yaml"
        assert (out / f"map_{method}.pgm").is_file()
        grid = OccupancyGrid.load_map_server(yaml_path)
        assert grid.resolution == 0.2
        # The map read back as map_server reads it matches the simulator's walls: occupied
        # pixels score far above free ones on the cells the scans observed.
        truth = data.environment.ground_truth_grid(0.2, extent=grid.extent, scans=data.scans)
        assert tuple(truth.shape) == grid.shape
        scored = truth.observed & ~grid.unknown.ravel()
        auc = roc_auc_score(truth.occupied[scored], grid.probability.ravel()[scored])
        assert auc > 0.85


def test_quick_demo_prints_tables_and_writes_files(quick_demo):
    rc, stdout, out = quick_demo
    assert rc == 0
    check_tables(stdout, ["moe", "bcm", "single"])
    assert "--quick" in stdout
    # Progress lines: one before and one after each of the three fits.
    assert len(re.findall(r"^\[\d/3\] ", stdout, flags=re.M)) == 6
    check_maps(out, ["moe", "bcm", "single"])
    for name in FIGURES:
        assert f"Saved {out / name}" in stdout
        assert (out / name).read_bytes()[:8] == PNG_MAGIC


def test_demo_without_matplotlib(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    rc, stdout, _ = run_demo(["--methods", "moe", "--quiet", "--out", str(tmp_path)])
    assert rc == 0
    check_tables(stdout, ["moe"])
    assert 'pip install "skoccmap[plot]"' in stdout
    assert "[1/1]" not in stdout  # --quiet
    # The maps are still written; no figures.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map_moe.pgm", "map_moe.yaml"]
    check_maps(tmp_path, ["moe"])


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--methods", "moe,gp"], "--methods"),
        (["--methods", "moe,moe"], "--methods"),
        (["--resolution", "-1"], "--resolution"),
        (["--resolution", "inf"], "--resolution"),
        (["--noise-std", "-0.1"], "--noise-std"),
        (["--noise-std", "nan"], "--noise-std"),
        (["--n-jobs", "0"], "--n-jobs"),
        (["--seed", "-1"], "--seed"),
        (["--seed", str(2**32)], "--seed"),
        # At 5 m every observed cell touches a wall: no AUC, refused before the fits.
        (["--methods", "moe", "--resolution", "5"], "the AUC is undefined"),
        # Noise that leaves no hit, in the option's name.
        (["--methods", "moe", "--noise-std", "1000"], "--noise-std 1000 m hold 0 hit"),
    ],
)
def test_demo_bad_arguments(argv, match, tmp_path):
    rc, stdout, stderr = run_demo([*argv, "--out", str(tmp_path)])
    assert rc == 2
    assert stderr.startswith("skoccmap demo: error:") and match in stderr
    assert not list(tmp_path.iterdir())


def test_refused_demo_removes_the_out_folder_it_made(tmp_path):
    # Refused after --out was made (with its parents): nothing is left behind.
    rc, _, stderr = run_demo(["--n-jobs", "0", "--out", str(tmp_path / "new" / "demo")])
    assert rc == 2 and "--n-jobs" in stderr
    assert not list(tmp_path.iterdir())


def test_demo_out_that_is_a_file(tmp_path):
    taken = tmp_path / "taken"
    taken.write_text("")
    rc, stdout, stderr = run_demo(["--methods", "moe", "--out", str(taken)])
    assert rc == 2 and stderr.startswith("skoccmap demo: error:") and "taken" in stderr
    assert "Table 2" not in stdout  # refused before the fits


@pytest.mark.slow
def test_full_demo(tmp_path):
    """The README's command as it is: the single GP learns its own hyperparameters."""
    pytest.importorskip("matplotlib")
    rc, stdout, _ = run_demo(["--out", str(tmp_path)])
    assert rc == 0 and "--quick" not in stdout
    aucs = check_tables(stdout, ["moe", "bcm", "single"])
    # The paper's finding: the local experts map as well as the single GP.
    assert aucs[LABELS["moe"]] >= aucs[LABELS["single"]] - 0.01
    check_maps(tmp_path, ["moe", "bcm", "single"])
    for name in FIGURES:
        assert (tmp_path / name).read_bytes()[:8] == PNG_MAGIC


@pytest.fixture
def experiment_arguments(monkeypatch, tmp_path):
    """The arguments the demo passes to the experiment, which then stops (exit code 2), and
    what ``tmp_path`` held when it was called (``"made"``)."""
    seen = {}

    def fake(methods, **kwargs):
        made = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*"))
        seen.update(kwargs, methods=methods, made=made)
        raise ValueError("stop here")

    monkeypatch.setattr("skoccmap.experiment.run_paper_experiment", fake)
    return seen


def test_demo_options_reach_the_experiment(tmp_path, experiment_arguments):
    seen = experiment_arguments
    argv = ["--methods", "moe, bcm", "--resolution", "0.5", "--noise-std", "0.05", "--seed", "7",
            "--n-jobs", "2", "--quiet", "--out", str(tmp_path)]  # fmt: skip
    rc, _, stderr = run_demo(argv)
    assert rc == 2 and "stop here" in stderr
    assert seen == {"methods": ["moe", "bcm"], "resolution": 0.5, "noise_std": 0.05,
                    "single_hyperparameters": "learn", "random_state": 7, "n_jobs": 2,
                    "verbose": 0, "made": []}  # fmt: skip
    run_demo([*argv, "--quick"])
    assert seen["single_hyperparameters"] == "from_mixture"


def test_demo_defaults_reach_the_experiment(tmp_path, experiment_arguments):
    # The help's defaults; a missing --out is made with its parents before the fits, and
    # removed when the run fails having written nothing into it.
    seen = experiment_arguments
    out = tmp_path / "new" / "demo"
    rc, _, stderr = run_demo(["--out", str(out)])
    assert rc == 2 and "stop here" in stderr
    assert seen == {"methods": ["moe", "bcm", "single"], "resolution": 0.2, "noise_std": 0.0,
                    "single_hyperparameters": "learn", "random_state": 0, "n_jobs": 1,
                    "verbose": 1, "made": ["new", "new/demo"]}  # fmt: skip
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("methods, note", [(["moe", "single"], True), (["moe", "bcm"], False)])
def test_demo_quick_note_only_with_the_single_gp(methods, note, tmp_path, monkeypatch):
    # --quick changes only the single GP: without it the note would misdescribe the run.
    from types import SimpleNamespace

    from skoccmap import experiment

    monkeypatch.setattr(experiment, "run_paper_experiment",
                        lambda m, **kwargs: SimpleNamespace(methods=m))  # fmt: skip
    monkeypatch.setattr(experiment, "format_tables", lambda result: "tables")
    monkeypatch.setattr(experiment, "save_maps", lambda result, out: [])
    monkeypatch.setattr(experiment, "save_figures", lambda result, out: [])
    rc, stdout, _ = run_demo(["--quick", "--methods", ",".join(methods), "--out", str(tmp_path)])
    assert rc == 0
    assert ("--quick: the single GP used the mixture's kernel" in stdout) == note
