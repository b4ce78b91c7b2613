"""``--neural-preset`` on ``torchseq eval`` and ``torchseq train``: the classmethod's config,
typed flags on top, refusals, and the record a ``--config`` replay reproduces."""

import dataclasses
import json

import pytest

import torchseq.cli.eval as cli_eval
import torchseq.cli.train as cli_train
from torchseq.cli.errors import UsageError
from torchseq.cli.presets import NEURAL_PRESETS, apply_preset
from torchseq.cli.runs import config_text, run_main
from torchseq.neural import NeuralConfig

CLASSMETHODS = {"default": NeuralConfig, "table1": NeuralConfig.table1,
                "dense-readout": NeuralConfig.dense_readout,
                "adaptive-velocity": NeuralConfig.adaptive_velocity}


def eval_neural(*args):
    return cli_eval.parse_args(list(args))[0].neural


def train_neural(*args):
    return cli_train.parse_args(list(args))[1]


def test_the_preset_names_are_the_classmethods():
    assert set(NEURAL_PRESETS) == set(CLASSMETHODS)
    for name, make in CLASSMETHODS.items():
        assert make().seed == NeuralConfig().seed  # no preset sets the seed


@pytest.mark.parametrize("name", list(CLASSMETHODS))
def test_each_preset_is_its_classmethods_config(name):
    want = CLASSMETHODS[name]()
    assert eval_neural("--neural-preset", name) == want
    assert train_neural("--neural-preset", name) == want
    assert eval_neural("--neural-preset", name.replace("-", "_")) == want
    if name != "default":
        assert want != NeuralConfig()  # the preset changes something


def test_typed_flags_win_over_the_preset_even_at_the_default_value():
    got = eval_neural("--neural-preset", "dense-readout", "--neural-ring-decay", "0.97",
                      "--neural-hidden", "512")
    assert got == NeuralConfig.dense_readout(ring_decay=0.97, hidden=512)
    got = train_neural("--neural-preset", "table1", "--neural-k-fraction", "0.1")
    assert got == NeuralConfig.table1(k_fraction=0.1)
    got = eval_neural("--neural-preset", "adaptive-velocity", "--neural-ring-spread", "2",
                      "--seed", "7")
    assert got == NeuralConfig.adaptive_velocity(ring_spread=2, seed=7)
    # abbreviated flags count as typed too (argparse accepts unique prefixes)
    got = train_neural("--neural-preset", "table1", "--neural-density-o", "1.0")
    assert got == NeuralConfig.table1(density_out=1.0)


def test_apply_preset_keeps_fields_no_preset_sets():
    flags = NeuralConfig(seed=9, hidden=100)
    got = apply_preset(flags, "table1", typed=set())
    assert got == NeuralConfig.table1(seed=9, hidden=100)


@pytest.mark.parametrize("args, message", [
    (["--engine", "seqslam", "--neural-preset", "table1"],
     "--neural-preset has no effect with --engine seqslam"),
    (["--engine", "seqslam", "--neural-preset", "default"],
     "--neural-preset has no effect with --engine seqslam"),
    (["--checkpoint", "model.pt", "--neural-preset", "adaptive-velocity"],
     "--neural-preset has no effect with --checkpoint"),
    (["--neural-preset", "fast"], "--neural-preset must be one of default, table1, "
                                  "dense-readout, adaptive-velocity, got 'fast'"),
])
def test_refusals_are_one_line_and_exit_2(tmp_path, capsys, args, message):
    code = run_main(cli_eval.main, "eval.py", [*args, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err
    assert not (tmp_path / "o").exists()


def test_train_refuses_an_unknown_preset(tmp_path, capsys):
    code = run_main(cli_train.main, "train.py", ["--neural-preset", "Table1",
                                                  "--out", str(tmp_path / "o")])
    assert code == 2 and "--neural-preset must be one of" in capsys.readouterr().err


def test_eval_records_the_preset_and_replay_reproduces_it(tmp_path, capsys):
    out = tmp_path / "run"
    code = run_main(cli_eval.main, "eval.py", [
        "--engine", "neural", "--neural-preset", "table1", "--neural-hidden", "256",
        "--demo-frames", "40", "--no-tensorboard", "--no-progress", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    want = NeuralConfig.table1(hidden=256)
    config = json.loads((out / "config.json").read_text())
    metrics = json.loads((out / "metrics.json").read_text())
    assert config["neural_preset"] == "table1"
    assert metrics["neural"]["preset"] == "table1"
    # the model's parameters as fitted: "auto" resolved (40 frames: the ring, issue 33)
    assert NeuralConfig.from_dict(metrics["neural"]["parameters"]) == dataclasses.replace(
        want, unit_search="off")
    replay = ["--config", str(out / "config.json")]
    assert eval_neural(*replay) == want
    # flags typed on the replay still win; a new preset keeps the recorded run's own flags
    assert eval_neural(*replay, "--neural-k-fraction", "0.2") == dataclasses.replace(
        want, k_fraction=0.2)
    assert eval_neural(*replay, "--neural-preset", "dense-readout") == \
        NeuralConfig.dense_readout(hidden=256)
    assert eval_neural(*replay, "--neural-preset", "default") == NeuralConfig(hidden=256)


def test_train_records_the_preset_and_replay_reproduces_it(tmp_path):
    cfg, ncfg = cli_train.parse_args(["--neural-preset", "dense-readout", "--neural-hidden", "128",
                                      "--neural-ring-decay", "0.97"])
    assert ncfg == NeuralConfig.dense_readout(hidden=128, ring_decay=0.97)
    path = tmp_path / "config.json"
    path.write_text(config_text({"train": cfg, "model": ncfg}))  # as train() writes it
    assert json.loads(path.read_text())["train"]["neural_preset"] == "dense-readout"
    assert train_neural("--config", str(path)) == ncfg
    assert train_neural("--config", str(path), "--neural-preset", "adaptive-velocity") == \
        NeuralConfig.adaptive_velocity(hidden=128, ring_decay=0.97)


def test_train_run_writes_the_preset(tmp_path, capsys):
    out = tmp_path / "t"
    code = run_main(cli_train.main, "train.py", [
        "--neural-preset", "adaptive-velocity", "--neural-hidden", "128", "--neural-n-output", "30",
        "--demo-frames", "30", "--no-tensorboard", "--no-progress", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    assert json.loads((out / "train.json").read_text())["neural_preset"] == "adaptive-velocity"
    config = json.loads((out / "config.json").read_text())
    assert config["train"]["neural_preset"] == "adaptive-velocity"
    assert train_neural("--config", str(out / "config.json")) == \
        NeuralConfig.adaptive_velocity(hidden=128, n_output=30)


def test_a_sweep_over_presets_builds_each():
    _, points, _, _ = cli_eval.parse_args(["--engine", "neural", "--sweep",
                                           "neural_preset=table1,adaptive-velocity"])
    assert [p.neural for p in points] == [NeuralConfig.table1(),
                                          NeuralConfig.adaptive_velocity()]


def test_bad_preset_in_apply_is_a_usage_error():
    with pytest.raises(UsageError, match="--neural-preset must be one of"):
        apply_preset(NeuralConfig(), "nope", typed=())


@pytest.mark.parametrize("script", ["eval", "train"])
def test_the_scripts_take_the_preset_and_say_typed_flags_win(script, capsys):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / f"{script}.py"
    spec = importlib.util.spec_from_file_location(f"{script}_preset_script", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    with pytest.raises(SystemExit):
        module.main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--neural-preset" in text and "you type are applied on top of it and win" in text
    assert "20% L2 -> L3 mask, 5% winners" in text
    code = run_main(module.main, f"{script}.py", ["--neural-preset", "x"])
    assert code == 2 and "--neural-preset must be one of" in capsys.readouterr().err


def test_replay_drops_the_recorded_settings_of_an_engine_it_does_not_configure(tmp_path,
                                                                                capsys):
    # a run with neural and SeqSLAM settings of its own, replayed for one engine: the
    # other engine's recorded settings are not this command's flags, so not refused
    out = tmp_path / "run"
    code = run_main(cli_eval.main, "eval.py", [
        "--neural-preset", "adaptive-velocity", "--neural-hidden", "256", "--ds", "12",
        "--demo-frames", "40", "--no-tensorboard", "--no-progress", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    replay = ["--config", str(out / "config.json")]
    seqslam_only = cli_eval.parse_args([*replay, "--engine", "seqslam"])[0]
    assert seqslam_only.seqslam.ds == 12 and seqslam_only.run.neural_preset is None
    neural_only = cli_eval.parse_args([*replay, "--engine", "neural"])[0]
    assert neural_only.seqslam.ds == 10
    assert neural_only.neural == NeuralConfig.adaptive_velocity(hidden=256)
    checkpoint = cli_eval.parse_args([*replay, "--checkpoint", "m.pt"])[0]
    assert checkpoint.neural == NeuralConfig() and checkpoint.seqslam.ds == 12
    # typed now, they are still refused
    for typed in (["--engine", "seqslam", "--neural-preset", "default"],
                  ["--engine", "neural", "--ds", "12"],
                  ["--checkpoint", "m.pt", "--neural-hidden", "256"]):
        with pytest.raises(UsageError, match="no effect"):
            cli_eval.parse_args([*replay, *typed])
