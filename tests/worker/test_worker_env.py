"""Several workers on one machine (`dgs serve --workers N`, `dgs worker --gpus 0,1`): each its
own Celery node and its share of the cores, a GPU worker only its GPU."""

from __future__ import annotations

import os
from pathlib import Path

from core.cli import build_parser
from worker.settings import WorkerSettings
from worker.supervise import worker_env


def test_n_workers_share_the_cores_and_have_their_own_names(tmp_path: Path):
    settings = WorkerSettings(data_dir=tmp_path)
    envs = [worker_env(settings, i, 2) for i in range(2)]
    share = str(max(1, (os.cpu_count() or 1) // 2))
    assert [e["DGS_TORCH_THREADS"] for e in envs] == [share, share]
    assert [e["OMP_NUM_THREADS"] for e in envs] == [share, share]
    assert [e["DGS_WORKER_NAME"] for e in envs] == ["w1", "w2"]
    assert "DGS_WORKER_NAME" not in worker_env(settings, 0, 1)  # one worker keeps its name
    # Threads the operator fixed win.
    fixed = WorkerSettings(data_dir=tmp_path, torch_threads=3, worker_name="box")
    assert worker_env(fixed, 1, 8)["DGS_TORCH_THREADS"] == "3"
    assert worker_env(fixed, 1, 8)["DGS_WORKER_NAME"] == "box-w2"


def test_a_gpu_worker_sees_only_its_gpu(tmp_path: Path):
    env = worker_env(WorkerSettings(data_dir=tmp_path), 1, 2, gpu="3")
    assert env["CUDA_VISIBLE_DEVICES"] == "3" and env["DGS_WORKER_NAME"] == "gpu3"


def test_the_commands_take_their_counts(capsys):
    args = build_parser(["worker"]).parse_args(["worker", "--gpus", "0,x"])
    assert args.func(args) == 2
    assert "--gpus: expected GPU indices" in capsys.readouterr().err
    args = build_parser(["serve"]).parse_args(["serve", "--workers", "0"])
    assert args.func(args) == 2
    assert "--workers: expected at least 1" in capsys.readouterr().err
