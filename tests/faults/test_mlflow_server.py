"""MLflow against a tracking server with a database backend (``tracking.uri=http://...``).

The test starts ``mlflow server`` on 127.0.0.1 (SQLite backend, artifacts served
by the server into a local folder), trains a small model with Ax trials against
it, and checks that the run, its nested trial runs, metrics and the model
artifact are on the server (and in the server's own artifact folder), and that
the model loads back through the server. The server is stopped at the end.
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from liverforce.config import compose, tracking_uri

MODEL = {
    "encoder": "pca", "code_size": 3, "state_vector": True, "grid_size": 6, "hidden": [16], "dropout": 0.0,
    "occlusion": {"radius_mm": 2.0, "mode": "remove"}, "noise_mm": 0.05,
}
TRAIN = {"test_fraction": 0.25, "epochs": 8, "batch_size": 16, "lr": 3e-3, "weight_decay": 0.0, "seed": 0}
TUNE = {"enabled": True, "trials": 2, "folds": 2, "sobol_trials": 2, "epochs": 3}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def listening_addresses(port: int) -> set[str]:
    """Local addresses with a listening TCP socket on ``port`` (from /proc/net/tcp and tcp6)."""
    out = set()
    for name in ("tcp", "tcp6"):
        path = Path("/proc/net") / name
        if not path.exists():
            continue
        for line in path.read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            addr, p = local.split(":")
            if state == "0A" and int(p, 16) == port:  # 0A = LISTEN
                if len(addr) == 8:
                    out.add(socket.inet_ntop(socket.AF_INET, bytes.fromhex(addr)[::-1]))
                else:
                    words = bytes.fromhex(addr)
                    out.add(socket.inet_ntop(socket.AF_INET6, b"".join(words[i:i + 4][::-1] for i in range(0, 16, 4))))
    return out


@pytest.fixture
def mlflow_server(tmp_path):
    port = _free_port()
    artifacts = tmp_path / "server-artifacts"
    cmd = [str(Path(sys.executable).with_name("mlflow")), "server",
           "--backend-store-uri", f"sqlite:///{tmp_path / 's.db'}",
           "--artifacts-destination", str(artifacts),
           "--host", "127.0.0.1", "--port", str(port), "--workers", "1"]
    log = open(tmp_path / "server.log", "w")
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True, cwd=tmp_path)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while True:
            assert proc.poll() is None, (tmp_path / "server.log").read_text()[-3000:]
            try:
                with urllib.request.urlopen(f"{url}/health", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            assert time.monotonic() < deadline, "mlflow server not healthy after 120 s:\n" + (
                tmp_path / "server.log").read_text()[-3000:]
            time.sleep(0.5)
        yield {"url": url, "port": port, "artifacts": artifacts, "proc": proc}
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=30)
        log.close()


def test_config_key_points_the_pipeline_at_a_server():
    cfg = compose(["experiment=smoke", "tracking.uri=http://127.0.0.1:5000"])
    assert tracking_uri(cfg) == "http://127.0.0.1:5000"
    assert tracking_uri(compose(["experiment=smoke"])).startswith("sqlite:///")


@pytest.mark.timeout(600)
@pytest.mark.slow  # starts a real server (~50 s)
def test_training_logs_run_metrics_and_model_to_an_mlflow_server(mlflow_server, tmp_path):
    from mlflow.tracking import MlflowClient

    from liverforce.learn.model import ForceModel, subset
    from liverforce.learn.synthetic import synthetic_arrays
    from liverforce.learn.train import train_scenario
    from liverforce.tracking import Tracker, download_force_model

    url = mlflow_server["url"]
    assert listening_addresses(mlflow_server["port"]) == {"127.0.0.1"}  # loopback only

    arrays = synthetic_arrays(40, n_geometries=4, seed=3, nodes=(100, 150))
    tracker = Tracker(url, "liverforce-server-test")
    res = train_scenario(arrays, MODEL, TRAIN, TUNE, "IV", "pca_sv", tracker=tracker, out_dir=tmp_path / "out",
                         tags={"rule": "train"})

    # a fresh client, talking to the server only
    client = MlflowClient(tracking_uri=url)
    exp = client.get_experiment_by_name("liverforce-server-test")
    assert exp is not None and exp.artifact_location.startswith("mlflow-artifacts:")
    run = client.get_run(res["run_id"])
    assert run.info.status == "FINISHED"
    for key in ("mae_vec", "rmse_vec", "accuracy_pct"):
        assert run.data.metrics[key] == pytest.approx(res["metrics"][key], rel=1e-12)
    assert len(client.get_metric_history(res["run_id"], "train_loss")) == TRAIN["epochs"]
    runs = client.search_runs([exp.experiment_id], max_results=100)
    assert len(runs) == 1 + TUNE["trials"]  # parent + one nested run per Ax trial, none lost
    model_files = {f.path for f in client.list_artifacts(res["run_id"], "model")}
    assert "model/MLmodel" in model_files
    # the bytes live in the server's artifact folder, not in the client's working directory
    on_server = list(mlflow_server["artifacts"].rglob("MLmodel"))
    assert len(on_server) == 1  # MLflow 3 keeps logged models under <exp>/models/m-<id>/artifacts
    assert list(on_server[0].parent.glob("artifacts/*/model.json"))  # the bundle inside the pyfunc model
    run_dirs = [p for p in mlflow_server["artifacts"].rglob(res["run_id"]) if p.is_dir()]
    assert run_dirs and list(run_dirs[0].rglob("*.png"))  # the run's figures
    assert not (Path.cwd() / "mlruns").exists() and not (tmp_path / "mlruns").exists()

    # the logged model comes back through the server and predicts what the trained one predicts
    bundle = download_force_model(res["run_id"], tmp_path / "dl", tracking_uri=url)
    model = ForceModel.load(bundle)
    local = ForceModel.load(res["model_path"])
    few = subset(arrays, np.arange(5))
    np.testing.assert_allclose(model.predict(few, observation_seed=1), local.predict(few, observation_seed=1))
