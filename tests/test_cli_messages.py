"""What the command line says when something is wrong: one line ``waveforest: error: ...`` on
stderr; exit 2 for what was typed (usage), 1 for bad input content, 130 for Ctrl-C; and the
top-level help shows each command's first sentence whole."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from waveforest import cli as cli_module
from waveforest.cli import COMMANDS, first_sentence, main, short_help
from waveforest.cliutil import stage_options
from waveforest.errors import WaveforestError

TESTS = Path(__file__).resolve().parent


def _run(argv, capsys) -> tuple[int, list[str]]:
    """``main(argv)``: its exit code and the non-empty lines it wrote on stderr."""
    with pytest.raises(SystemExit) as exc:
        main([str(a) for a in argv])
    return exc.value.code, [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]


def _one_error_line(lines: list[str]) -> str:
    assert len(lines) == 1 and lines[0].startswith("waveforest: error: "), lines
    return lines[0]


@pytest.mark.parametrize(("typed", "meant"), [("quiklook", "quicklook"), ("tune-cdf", "tune-cfd"),
                                              ("calibrat", "calibrate")])
def test_a_misspelled_command_suggests_the_right_one(typed, meant, capsys):
    code, lines = _run([typed, "x"], capsys)
    line = _one_error_line(lines)
    assert code == 2 and f"'{typed}'" in line and f"Did you mean '{meant}'" in line


def test_an_unknown_command_without_a_close_one_has_no_suggestion(capsys):
    code, lines = _run(["xyzzy"], capsys)
    assert code == 2 and "Did you mean" not in _one_error_line(lines)


def test_a_missing_input_file_is_a_usage_error_in_the_same_style_everywhere(tmp_path, capsys):
    missing = tmp_path / "nowhere.las"
    out = tmp_path / "out"
    for argv in (["quicklook", missing, "--out", out],
                 ["agc", missing, "--targets", missing, "--datasets", missing, "--out", out / "a.parquet"],
                 ["trace", "--species", "sand_road", "--config", missing, "--out", out / "s.csv"]):
        code, lines = _run(argv, capsys)
        line = _one_error_line(lines)
        assert code == 2 and f"File '{missing}' does not exist." in line, line
        assert line.endswith(f"(see 'waveforest {argv[0]} --help')"), line
    assert not out.exists()


def test_options_are_named_as_typed(capsys):
    code, lines = _run(["trace", "--species", "sand_road", "--threads", "0", "--out", "x.csv"], capsys)
    assert code == 2 and "'--threads'" in _one_error_line(lines)
    code, lines = _run(["trace", "--specis", "sand_road"], capsys)
    assert code == 2 and "Did you mean '--species'" in _one_error_line(lines)


def test_a_scene_file_name_without_ply_is_refused_before_work(tmp_path, capsys):
    out = tmp_path / "scene.txt"
    code, lines = _run(["vegetation", "--species", "birch", "--height", "2", "--out", str(out)], capsys)
    line = _one_error_line(lines)
    assert code == 2 and "'--out'" in line and "scene.txt: expected a .ply file name" in line, line
    assert list(tmp_path.iterdir()) == []


def test_bad_input_content_exits_1_with_one_line(tmp_path, capsys):
    junk = tmp_path / "junk.las"
    junk.write_bytes(b"not a LAS file at all" * 20)
    code, lines = _run(["info", junk], capsys)
    assert code == 1 and junk.name in _one_error_line(lines)

    bad = tmp_path / "bad.yaml"
    bad.write_text("seed: -1\n")
    code, lines = _run(["info", junk, "--config", bad], capsys)
    line = _one_error_line(lines)
    assert code == 1 and f"{bad}: seed:" in line  # names the file the value came from


@pytest.mark.parametrize(("raised", "code", "text"), [
    (WaveforestError("t.csv: row 3: expected a number"), 1, "waveforest: error: t.csv: row 3"),
    (click.exceptions.Abort(), 130, "waveforest: interrupted"),
])
def test_library_errors_and_ctrl_c(monkeypatch, capsys, raised, code, text):
    def fail(*args, **kwargs):
        raise raised

    monkeypatch.setattr(cli_module.cli, "main", fail)
    got, lines = _run(["anything"], capsys)
    assert got == code and len(lines) == 1 and lines[0].startswith(text), lines


def test_shared_options_show_their_ranges():
    @click.command()
    @stage_options
    def probe(cfg):
        """Probe."""

    out = CliRunner().invoke(probe, ["--help"]).output
    flat = " ".join(out.split())
    assert "an integer >= 0" in flat and "[x>=0]" in flat
    assert "1 or more" in flat and "[x>=1]" in flat


def test_smoke_check_has_a_help():
    r = subprocess.run([sys.executable, str(TESTS / "smoke_check.py"), "--help"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and "RESULTS_DIR" in r.stdout and "--paper-scale" in r.stdout, r.stderr
    r = subprocess.run([sys.executable, str(TESTS / "smoke_check.py")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr and "RESULTS_DIR" in r.stderr


def test_first_sentence_is_whole():
    assert first_sentence("Fit the law (Eq. 1). Then more.\n\nDetails.") == "Fit the law (Eq. 1)."
    assert first_sentence("A vs. b, e.g. c.\nNext sentence.") == "A vs. b, e.g. c."
    assert first_sentence("No period at all\n\nx.") == "No period at all"


def test_top_level_help_lines_are_whole_sentences():
    out = CliRunner().invoke(cli_module.cli, ["--help"]).output
    flat = " ".join(out.split())
    for name, target in COMMANDS.items():
        line = short_help(target)
        assert line.endswith(".") and not line.endswith("..."), (name, line)
        assert f" {name} {line}" in flat, name


def test_every_command_that_reads_a_file_shows_a_valid_example():
    """The help of each command with an input file ends in an example whose options exist and
    that gives every required option."""
    import importlib
    import re

    from waveforest.cli import COMMANDS

    checked = 0
    for name, target in COMMANDS.items():
        module, attr = target.split(":")
        command = getattr(importlib.import_module(module), attr)
        takes_file = any(isinstance(p, click.Argument) for p in command.params) or name in ("compare", "diagnose",
                                                                                              "report")
        if not takes_file:
            continue
        found = re.search(r"Example:\s*(?:\x08\s*)?(waveforest [^\n]*)", command.help or "")
        assert found, f"{name}: no example in --help"
        flags = set(re.findall(r"(--[a-z-]+)", found.group(1)))
        options = {o for p in command.params for o in getattr(p, "opts", [])}
        assert flags <= options, (name, flags - options)
        required = {p.opts[0] for p in command.params
                    if isinstance(p, click.Option) and p.required}
        assert required <= flags, (name, required - flags)
        checked += 1
    assert checked >= 12, checked
