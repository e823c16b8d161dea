"""`dgs reconstruct --downscale F`: training, held-out renders and `dgs eval` at 1/F resolution,
the factor recorded in config.json."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from core.cli import main
from core.config import read_run
from core.synth import SynthConfig, synthesize

pytestmark = pytest.mark.usefixtures("one_thread")

SHORT = {"train": {"schedule": {"iterations": 60, "stage2_start": 20, "stage3_start": 45,
                                "densify_from": 5, "densify_until": 40, "densify_interval": 10,
                                "reset_interval": 30, "sh_interval": 5},
                   "init_points": 300}}


def test_downscaled_run_trains_renders_and_scores_at_the_reduced_size(tmp_path: Path, capsys):
    capture = tmp_path / "capture"
    synthesize(capture, SynthConfig(frames=1, views=8, width=40, height=32, seed=6, priors=True,
                                    ao_directions=4))
    (tmp_path / "short.json").write_text(json.dumps(SHORT))
    run = tmp_path / "run"
    args = ["reconstruct", str(capture), "--out", str(run), "--preset", "test", "--config",
            str(tmp_path / "short.json"), "--no-progress", "--downscale", "2"]
    assert main(args) == 0
    assert read_run(run).views.downscale == 2.0
    rgb = np.asarray(Image.open(run / "renders" / "000000" / "cam00_rgb.png"))
    assert rgb.shape == (16, 20, 3) and rgb.max() > 0
    assert np.load(run / "renders" / "000000" / "cam00_depth.npy").shape == (16, 20)
    assert main(["eval", str(run)]) == 0
    result = json.loads((run / "eval.json").read_text())
    assert 8 < result["psnr_full"] < 60 and result["normal_reference"] == "ground truth"
    assert -1 <= result["normal_cos"] <= 1
    # Resuming needs the same factor: the run records it as part of its configuration.
    assert main(args[:-2] + ["--resume"]) == 2
    assert "another configuration" in capsys.readouterr().err
    assert main(args[:-2] + ["--downscale", "0.5"]) == 2
    assert "downscale" in capsys.readouterr().err
