"""Ctrl-C mid-training never leaves the old model's files in the variant folder.

Snakemake removes a job's declared outputs (``metrics.json``, ``model/``) when the job is interrupted, not the
files beside them: the training itself removes what an earlier run wrote (by name) before it writes anything,
so an interrupted run leaves only files of the new run, each written atomically, and a completed re-run
leaves exactly what an uninterrupted run leaves.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

import liverforce.learn.train as lt
from liverforce.learn.synthetic import synthetic_arrays

MODEL = {"encoder": "pca", "code_size": 3, "state_vector": True, "grid_size": 6, "hidden": [16],
         "dropout": 0.0, "occlusion": {"radius_mm": 0.0, "mode": "remove"}, "noise_mm": 0.0}
TRAIN = {"test_fraction": 0.25, "epochs": 5, "batch_size": 32, "lr": 3e-3, "weight_decay": 0.0, "seed": 0,
         "repeats": 1, "final_fit": False,
         "interval": {"coverage": 0.9, "calibration_fraction": 0.3, "folds": 2, "scale": "none"}}
NO_TUNE = {"enabled": False, "trials": 1, "folds": 2, "sobol_trials": 1, "epochs": 1}
OLD = b"\n#OLD-MODEL-FILE#"  # appended to every file of the earlier run


def _train(data, out_dir: Path, seed: int = 0) -> dict:
    return lt.train_scenario(data, MODEL, TRAIN, NO_TUNE, "II", "pca_sv", seed=seed, out_dir=out_dir)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def data():
    return synthetic_arrays(60, seed=3, n_geometries=1, nodes=(80, 120))


@pytest.fixture(scope="module")
def uninterrupted(data, tmp_path_factory) -> dict[str, bytes]:
    out = tmp_path_factory.mktemp("uninterrupted") / "models" / "II" / "pca_sv"
    _train(data, out)
    files = _files(out)
    assert {"test_predictions.csv", "interval_calibration.npz", "figures/error_histogram.png",
            "model/model.json"} <= set(files), sorted(files)
    return files


def _old_model(data, variant_dir: Path) -> set[str]:
    """An earlier run's model in ``variant_dir`` (another seed: other cases, other numbers), every file marked."""
    _train(data, variant_dir, seed=7)
    for p in variant_dir.rglob("*"):
        if p.is_file():
            with open(p, "ab") as fh:
                fh.write(OLD)
    return set(_files(variant_dir))


@pytest.mark.parametrize("step", ["calibration_predictions", "_write_predictions", "repeated_splits"])
def test_an_interrupted_training_leaves_no_file_of_the_old_model(data, uninterrupted, tmp_path, monkeypatch,
                                                                 fault_ledger, step):
    """Interrupted before it wrote anything (calibration), after the model and figures, and after every file."""
    variant_dir = tmp_path / "models" / "II" / "pca_sv"
    old = _old_model(data, variant_dir)
    shutil.rmtree(variant_dir / "model")  # what Snakemake removes of the interrupted job: its declared output

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    rows = uninterrupted["test_predictions.csv"].count(b"\n") - 1
    with fault_ledger.check(f"KeyboardInterrupt mid-training at {step}", rows_expected=rows) as seen:
        with monkeypatch.context() as m:
            m.setattr(lt, step, interrupt)
            with pytest.raises(KeyboardInterrupt):
                _train(data, variant_dir)
        left = _files(variant_dir)
        stale = sorted(name for name, content in left.items() if content.endswith(OLD))
        assert not stale, f"the old model's files stayed beside the interrupted run's: {stale} (of {sorted(old)})"
        assert not [p for p in variant_dir.rglob("*") if p.name.startswith(".")], "a temporary file stayed"
        assert set(left) <= set(uninterrupted)  # only files the new run wrote, complete
        for name, content in left.items():
            assert content == uninterrupted[name], name

        _train(data, variant_dir)  # the re-run
        again = _files(variant_dir)
        seen.rows_found = again["test_predictions.csv"].count(b"\n") - 1
        assert sorted(again) == sorted(uninterrupted)
        for name, content in again.items():
            assert content == uninterrupted[name], f"{name} differs from an uninterrupted run's"


def test_clearing_knows_every_file_a_training_writes_and_touches_nothing_else(data, tmp_path):
    variant_dir = tmp_path / "pca_sv"
    (variant_dir / "figures").mkdir(parents=True)
    (variant_dir / "figures" / "my_plot.png").write_bytes(b"a user's")
    (variant_dir / "notes.txt").write_text("a user's")
    (variant_dir / "metrics.json").write_text("{}")  # the pipeline's (Snakemake's declared output), not the trainer's
    (variant_dir / "interval_calibration_folds4.npz").write_bytes(b"an experiment's earlier run")
    (variant_dir / ".test_predictions.abcd1234.tmp.csv").write_text("a killed write's")
    (variant_dir / ".model.k1lled_x").mkdir()  # a killed ForceModel.save's temporary folder
    _train(data, variant_dir)
    gone = lt.clear_outputs(variant_dir)
    assert sorted(_files(variant_dir)) == ["figures/my_plot.png", "metrics.json", "notes.txt"]
    assert not (variant_dir / "model").exists() and variant_dir / "model" in gone
    assert sorted(p.name for p in variant_dir.iterdir()) == ["figures", "metrics.json", "notes.txt"]
    (variant_dir / "figures" / "my_plot.png").unlink()
    _train(data, variant_dir)
    lt.clear_outputs(variant_dir)
    assert sorted(p.name for p in variant_dir.iterdir()) == ["metrics.json", "notes.txt"]  # an empty figures/ goes


def test_the_train_step_removes_the_old_model_before_reading_any_shard(tmp_path, monkeypatch):
    """Interrupted while it loads the shards, the train step has already removed the earlier run's files."""
    from liverforce.pipeline import train as pt

    variant_dir = tmp_path / "models" / "II" / "pca_sv"
    (variant_dir / "figures").mkdir(parents=True)
    for name in ("metrics.json", "test_predictions.csv", "interval_calibration.npz", "figures/error_histogram.png",
                 "shard-0000.parquet"):
        (variant_dir / name).write_bytes(b"old")

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pt.dio, "verify_manifest", interrupt)
    with pytest.raises(KeyboardInterrupt):
        pt.train_model(tmp_path / "manifest.json", "II", "pca_sv", MODEL, TRAIN, NO_TUNE,
                       f"sqlite:///{tmp_path / 'mlflow.db'}", "e", "e", 0, 1,
                       variant_dir / "metrics.json", variant_dir / "model")
    assert sorted(_files(variant_dir)) == ["shard-0000.parquet"]  # not a training output: left alone


def test_a_symlinked_figures_folder_is_unlinked_never_followed(data, tmp_path):
    """figures/ a symlink to a folder holding files of the figures' names: clearing removes the link only, the
    folder and its files stay, and the next training writes its figures into a folder of its own (a followed
    link would have had them deleted, then overwritten)."""
    elsewhere = tmp_path / "shared_figures"
    elsewhere.mkdir()
    theirs = {name: f"someone else's {name}".encode() for name in lt.FIGURE_FILES}
    for name, content in theirs.items():
        (elsewhere / name).write_bytes(content)
        (elsewhere / f".{Path(name).stem}.abcd1234.tmp.png").write_bytes(b"someone else's temporary file")
    variant_dir = tmp_path / "pca_sv"
    variant_dir.mkdir()
    (variant_dir / "figures").symlink_to(elsewhere, target_is_directory=True)
    kept = _files(elsewhere)
    gone = lt.clear_outputs(variant_dir)
    assert gone == [variant_dir / "figures"] and not (variant_dir / "figures").exists()
    assert _files(elsewhere) == kept  # nothing deleted through the link
    (variant_dir / "figures").symlink_to(elsewhere, target_is_directory=True)
    _train(data, variant_dir)
    assert _files(elsewhere) == kept  # nor overwritten by the training
    figures = variant_dir / "figures"
    assert not figures.is_symlink() and sorted(p.name for p in figures.iterdir()) == sorted(lt.FIGURE_FILES)


def test_a_killed_writes_temporary_file_goes_without_its_final_file(tmp_path):
    """A fold-count calibration killed mid-write leaves only its temporary file (the final name was never
    written): it is removed all the same; another file's look-alike is not."""
    variant_dir = tmp_path / "pca_sv"
    variant_dir.mkdir()
    temp = variant_dir / ".interval_calibration_folds4.k1lled_0.tmp.npz"
    temp.write_bytes(b"a killed write's")
    figure_temp = variant_dir / "figures" / ".error_histogram.x9y8z7w6.tmp.png"
    figure_temp.parent.mkdir()
    figure_temp.write_bytes(b"a killed write's")
    other = variant_dir / ".interval_calibration_folds4.notes.k1lled_0.tmp.npz"  # not atomic_path's name for it
    other.write_bytes(b"a user's")
    gone = lt.clear_outputs(variant_dir)
    assert temp in gone and not temp.exists()
    assert figure_temp in gone and not figure_temp.exists() and not figure_temp.parent.exists()
    assert other.exists() and sorted(p.name for p in variant_dir.iterdir()) == [other.name]


class _StatusTracker:
    """Records the status a training ends its MLflow run with (a duck-typed tracker)."""

    status = None

    def start_run(self, *a, **k):
        return "run"

    def end_run(self, run_id, status="FINISHED"):
        self.status = status

    def __getattr__(self, name):
        return lambda *a, **k: "uri"


@pytest.mark.parametrize("error, status", [(KeyboardInterrupt, "KILLED"), (MemoryError, "FAILED")])
def test_an_interrupted_training_ends_its_run_killed_not_failed(data, tmp_path, monkeypatch, error, status):
    """Ctrl-C is no failure of the code: the run is KILLED, as the stale-run sweep marks a killed job's; an error
    still ends it FAILED."""
    def stop(*args, **kwargs):
        raise error

    tracker = _StatusTracker()
    monkeypatch.setattr(lt, "repeated_splits", stop)
    with pytest.raises(error):
        lt.train_scenario(data, MODEL, TRAIN, NO_TUNE, "II", "pca_sv", seed=0, out_dir=tmp_path, tracker=tracker)
    assert tracker.status == status
