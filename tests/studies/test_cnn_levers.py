"""studies.cnn_levers: the constant of a run's skill, and its one-line refusals."""

import json

from studies.cnn_levers import main, run_constant


def test_run_constant_reads_the_recorded_training_mean(tmp_path):
    assert run_constant(tmp_path) is None
    (tmp_path / "metrics.json").write_text(
        json.dumps({"test/x/constant/value": -0.0123, "test/x/nlat_mae": 0.05})
    )
    assert run_constant(tmp_path) == -0.0123


def test_a_run_without_checkpoint_is_refused(tmp_path, capsys):
    rc = main(["--run", f"a={tmp_path}", "--survey", str(tmp_path), "--out", str(tmp_path)])
    assert rc == 2
    assert "expected LABEL=RUN_DIR" in capsys.readouterr().err


def test_a_checkpoint_file_is_a_run(tmp_path, capsys):
    ckpt = tmp_path / "run" / "checkpoints" / "step_228.ckpt"
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(b"")
    rc = main(
        ["--run", f"a={ckpt}", "--survey", str(tmp_path / "nosurvey"), "--out", str(tmp_path)]
    )
    assert rc == 2  # accepted as a run: refused only for its survey
    assert "expected a survey folder" in capsys.readouterr().err
