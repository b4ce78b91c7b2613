"""--help shows the common flags in groups within a screenful; --help-all shows every flag."""

import argparse
from dataclasses import dataclass

import pytest

import torchseq.cli.help as cli_help
from torchseq.cli.eval import build_parser as eval_parser
from torchseq.cli.eval_settings import ENGINES
from torchseq.cli.event_options import EVENT_MODES, EVT3_KERNEL_CHOICES
from torchseq.cli.export import build_parser as export_parser
from torchseq.cli.flags import Parser, add_config_flags
from torchseq.cli.presets import NEURAL_PRESETS
from torchseq.cli.train import build_parser as train_parser

PARSERS = {"eval": (eval_parser, cli_help.EVAL), "train": (train_parser, cli_help.TRAIN),
           "export": (export_parser, cli_help.EXPORT)}
LIMIT = {"eval": 150, "train": 120, "export": 45}  # lines of --help at 80 columns


def help_text(parser, flag, capsys):
    with pytest.raises(SystemExit) as exit_info:
        parser.parse_args([flag] if flag else ["--help"])
    assert exit_info.value.code == 0
    return capsys.readouterr().out


def every_option(parser):
    return {s for a in parser._actions for s in (a.option_strings or [a.dest])}


@pytest.mark.parametrize("command", PARSERS)
def test_short_help_fits_and_help_all_lists_every_flag(command, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")
    parser = PARSERS[command][0]()
    short = help_text(parser, "--help", capsys)
    full = help_text(parser, "--help-all", capsys)
    assert len(short.splitlines()) <= LIMIT[command], len(short.splitlines())
    assert "examples:" in short and f"torchseq {command}" in short.split("examples:")[1]
    words = set(full.replace("[", " ").replace("]", " ").replace(",", " ").split())
    missing = {o for o in every_option(parser) if o not in words}
    assert not missing, missing
    # the short help holds the common flags and no other
    layout = parser.help_layout
    for action in parser._actions:
        name = cli_help.flag_name(action)
        if name in ("--help", "--help-all"):
            continue
        first = action.option_strings[0] if action.option_strings else action.dest
        assert (f"\n  {first}" in short) == layout.place(name)[1], name


@pytest.mark.parametrize("command", ["eval", "train"])
def test_groups_in_order_and_choices_in_the_usage(command, capsys):
    parser = PARSERS[command][0]()
    full = help_text(parser, "--help-all", capsys)
    titles = [t for k, t in cli_help.GROUPS.items() if k != "SeqSLAM" or command == "eval"]
    at = [full.index(f"\n{t}:\n") for t in titles]
    assert at == sorted(at)
    usage = full.split("\n\n")[0]
    assert "--neural-preset {default,table1,dense-readout,adaptive-velocity}" in usage
    assert "--event-mode {count,signed,two-channel,binary}" in usage
    if command == "eval":
        assert "[--engine {seqslam,neural,both}]" in usage


def test_a_flag_the_table_does_not_name_is_advanced(capsys):
    @dataclass
    class Extra:
        reference: str | None = None
        brand_new_setting: int = 3

    parser = Parser(prog="torchseq eval")
    add_config_flags(parser, Extra, {})
    cli_help.organise_help(parser, cli_help.EVAL, cli_help.EVAL_EXAMPLES)
    short = help_text(parser, "--help", capsys)
    full = help_text(parser, "--help-all", capsys)
    assert "--reference PATH" in short and "--brand-new-setting" not in short
    advanced = full.split("\nadvanced:\n")[1]
    assert "--brand-new-setting N" in advanced


def test_the_table_names_only_real_flags_and_real_choices():
    for command, (build, table) in PARSERS.items():
        names = {cli_help.flag_name(a) for a in build()._actions}
        listed = {n for _, common, other in table for n in (*common, *other) if "*" not in n}
        assert listed <= names, (command, listed - names)
    assert cli_help.CHOICES["--engine"] == ENGINES
    assert cli_help.CHOICES["--event-mode"] == EVENT_MODES
    assert cli_help.CHOICES["--evt3-kernel"] == EVT3_KERNEL_CHOICES
    assert cli_help.CHOICES["--neural-preset"] == tuple(NEURAL_PRESETS)


def test_parsers_without_a_layout_keep_argparse_help():
    parser = Parser(prog="x")
    parser.add_argument("--a")
    assert parser.format_help() == argparse.ArgumentParser.format_help(parser)
